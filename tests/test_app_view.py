"""The designer's view of the scene: the camera that follows the snake, light rendering."""

from __future__ import annotations

import numpy as np

from helpers import connect_headless


def test_follow_snake_keeps_the_camera_on_the_snake(server):
    client, d = connect_headless(server)
    try:
        camera = d.client.camera
        offset = np.asarray(camera.position) - np.asarray(camera.look_at)
        d.controls.follow.value = True
        d.draw_snake(1500)  # 75 s into the replay: the snake has moved
        center = d.scene.snake.batched_positions.mean(axis=0)
        np.testing.assert_allclose(camera.look_at, center, atol=1e-6)
        np.testing.assert_allclose(
            np.asarray(camera.position) - np.asarray(camera.look_at), offset, atol=1e-6
        )
        d.controls.follow.value = False
        d.draw_snake(10)
        np.testing.assert_allclose(camera.look_at, center, atol=1e-6)  # left where it was
    finally:
        client.close()


def test_light_rendering_drops_shadows_environment_and_grid_and_full_brings_them_back(server):
    client, d = connect_headless(server)
    try:
        calls = []
        scene = d.client.scene
        lights, environment = scene.configure_default_lights, scene.configure_environment_map
        scene.configure_default_lights = lambda *a, **kw: (calls.append(("lights", a, kw)), lights(*a, **kw))
        env = lambda *a, **kw: (calls.append(("environment", a, kw)), environment(*a, **kw))  # noqa: E731
        scene.configure_environment_map = env
        assert d.controls.light.value is False and d.scene.grid.visible
        d.controls.light.value = True  # as the page's software-renderer check or a user ticks it
        assert ("lights", (True,), {"cast_shadow": False}) in calls
        assert ("environment", (None,), {}) in calls
        assert d.controls.layers["Grid"].value is False and not d.scene.grid.visible
        assert d.scene.metres.visible  # the metre grid is a few quads: light rendering keeps it
        calls.clear()
        d.controls.light.value = False
        assert ("lights", (True,), {"cast_shadow": True}) in calls
        assert ("environment", ("city",), {}) in calls
        assert d.controls.layers["Grid"].value is True and d.scene.grid.visible
    finally:
        client.close()
