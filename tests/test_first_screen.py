"""The designer's first screen explains itself (a real Chromium page at 1500x950, software WebGL):
the readout's numbers are in view without scrolling and are the server's, the camera frames both
paths after a decode and a replay, and the metre grid stays with light rendering on."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from snakeloco.app.bench.users.load_driver import wait_until
from snakeloco.app.designer.readout import GAP_BASE_M, READOUT_ID, heading_text
from snakeloco.app.designer.scene_geometry import path_points
from snakeloco.app.designer.view import in_view

from helpers import BROWSER, designer_page

pytestmark = BROWSER
VIEWPORT = {"width": 1500, "height": 950}


def _ends_in_view(d) -> bool:
    cam = d.client.camera
    ends = [path_points(d.decoded.body_ds, 0.0)[-1], path_points(d.simulated.body, 0.0)[-1]]
    return bool(in_view(np.array(ends), cam.position, cam.look_at, cam.fov, cam.aspect).all())


def _canvas(page) -> np.ndarray:
    return np.asarray(
        Image.open(io.BytesIO(page.locator("canvas").first.screenshot())).convert("RGB"), np.int16
    )


def _grid_pixels(page, d) -> int:
    """Pixels of the scene that change when the metre grid is turned off (and on again)."""
    with_grid = _canvas(page)
    d.controls.layers["Metre grid"].value = False
    changed = 0
    for _ in range(20):  # the page draws the change within a frame or a few
        changed = int((np.abs(_canvas(page) - with_grid).max(axis=-1) > 30).sum())
        if changed:
            break
    d.controls.layers["Metre grid"].value = True
    return changed


def test_the_readout_is_in_view_and_says_what_the_server_computed_and_the_camera_frames_the_paths(checkpoint):
    with designer_page(checkpoint, viewport=VIEWPORT) as (sync_api, _srv, page, d):
        assert d.wait_idle(90) and d.simulated is not None
        assert wait_until(lambda: d.controls.light.value is True, 30), "the page kept full rendering"
        # The metre grid is drawn in light rendering (the shaded grid is not).
        assert d.scene.metres.visible and not d.controls.layers["Grid"].value
        assert _grid_pixels(page, d) > 2000, "the metre grid is not drawn with light rendering on"
        # The plots open by default in a window this wide.
        sync_api.expect(page.locator(".u-title", has_text="forward (m)")).to_be_visible(timeout=30000)

        # A decode far from the start: the camera frames both paths' ends once the replay is done.
        d.sliders[0].value = 2.5
        assert wait_until(lambda: d.idle() and d.decoded.latents.z_b[0] == 2.5, 90)
        r = d.readout
        assert r.state == "done" and r.gap_m is not None
        assert wait_until(lambda: _ends_in_view(d), 15), "the camera does not frame both path ends"

        expected = {
            "model-distance": f"{r.model.distance_m:.2f} m",
            "model-direction": f"{r.model.direction_deg:+.0f}°",
            "model-heading": heading_text(r.model.heading_change_deg),
            "mujoco-distance": f"{r.mujoco.distance_m:.2f} m",
            "mujoco-direction": f"{r.mujoco.direction_deg:+.0f}°",
            "mujoco-heading": heading_text(r.mujoco.heading_change_deg),
            "gap": f"{r.gap_m:.2f} m",
        }
        if r.mujoco.distance_m >= GAP_BASE_M:
            expected["gap-share"] = f"{100 * r.gap_share:.0f}%"
        readout = page.locator(f"#{READOUT_ID}")
        sync_api.expect(readout.locator('[data-key="gap"]')).to_have_text(expected["gap"], timeout=30000)
        for key, text in expected.items():
            cell = readout.locator(f'[data-key="{key}"]')
            assert cell.inner_text() == text, key
            box = cell.bounding_box()  # in the first viewport: no scrolling
            assert box is not None and box["y"] >= 0 and box["x"] >= 0
            assert (
                box["y"] + box["height"] <= VIEWPORT["height"]
                and box["x"] + box["width"] <= VIEWPORT["width"]
            )
        # The numbers are those of the paths drawn: the model's end and MuJoCo's replay end.
        end = d.decoded.body_ds[-1]
        assert r.model.distance_m == pytest.approx(np.hypot(end[1], end[2]))
        gap = np.hypot(*(d.decoded.body_ds[-1, 1:3] - d.simulated.body[-1, 1:3]))
        assert r.gap_m == pytest.approx(gap)

        # A camera the user moved stays where it is; "Frame paths" frames on demand.
        d.client.camera.position = (30.0, 30.0, 2.0)  # as a drag would leave it (far off)
        d.sliders[0].value = -2.5
        assert wait_until(lambda: d.idle() and d.decoded.latents.z_b[0] == -2.5, 90)
        assert np.allclose(d.client.camera.position, (30.0, 30.0, 2.0), atol=0.05)
        page.get_by_role("button", name="Frame paths").click()
        assert wait_until(lambda: _ends_in_view(d), 15)


def _left_of_panel(d) -> bool:
    """Both paths' ends and the start project inside the canvas, left of the control panel."""
    from snakeloco.app.designer.view import PANEL_PX

    cam = d.client.camera
    pts = np.array(
        [[0.0, 0.0, 0.0], path_points(d.decoded.body_ds, 0.0)[-1], path_points(d.simulated.body, 0.0)[-1]]
    )
    pos, f = np.asarray(cam.position, np.float64), np.asarray(cam.look_at, np.float64) - cam.position
    f /= np.linalg.norm(f)
    right = np.cross(f, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    v = pts - pos
    x = (v @ right) / (v @ f) / (np.tan(cam.fov / 2) * cam.aspect)
    y = (v @ up) / (v @ f) / np.tan(cam.fov / 2)
    edge = 1 - 2 * PANEL_PX / cam.image_width
    return bool(((v @ f) > 0).all() and (x > -1).all() and (x < edge).all() and (np.abs(y) < 1).all())


def test_a_newcomers_first_hour_in_the_browser():
    """Issue 59, points 1-6 in one Chromium page at 1500x950 on the shipped checkpoints: the structured
    family first; framed left of the panel after load, drag, family and cluster; a target beyond
    reach answered at once; numbers in one unit each; an import that round-trips; clusters named apart."""
    with designer_page(None, viewport=VIEWPORT) as (sync_api, _srv, page, d):
        readout = page.locator(f"#{READOUT_ID}")
        # 1. The family whose promise holds, first; the paper family one click away.
        assert d.model.family == "structured" and d.controls.family.options[:2] == ("structured", "paper")
        # 2. Framing, after load and after each change that replaces the gait.
        assert wait_until(lambda: _left_of_panel(d), 15), "first load: a path end behind the panel"
        d.sliders[0].value = 2.0
        assert wait_until(
            lambda: d.idle() and d.decoded.latents.axes[0] == 2.0 and d.simulated is not None, 120
        )
        assert wait_until(lambda: _left_of_panel(d), 15), "drag"
        exported, model_cell = (
            d.files.export_text(),
            readout.locator('[data-key="model-distance"]').inner_text(),
        )
        d.controls.family.value = "paper"
        assert wait_until(lambda: d.model.family == "paper" and d.idle() and d.simulated is not None, 120)
        assert wait_until(lambda: _left_of_panel(d), 15), "family switch"
        sync_api.expect(readout).to_contain_text("paths are a spread", timeout=30000)
        # 6. Clusters named apart (they read "forward, turning left, 1 m", "(2)", "(3)").
        names = d.controls.component.options
        assert len(set(names)) == len(names) and not any("(2)" in n for n in names)
        d.controls.family.value = "structured"
        assert wait_until(lambda: d.model.family == "structured" and d.idle(), 120)
        d.controls.component.value = d.controls.component.options[4]
        assert wait_until(
            lambda: d.idle() and d.decoded.latents.component == 4 and d.simulated is not None, 120
        )
        assert wait_until(lambda: _left_of_panel(d), 15), "cluster change"
        # 4. One unit per quantity: the heading plot in degrees, as the readout.
        sync_api.expect(page.locator(".u-title", has_text="heading (deg)")).to_be_visible(timeout=30000)
        assert page.locator(".u-title", has_text="yaw (rad)").count() == 0
        # 5. The exported gait imports as exported: the same model path in the readout.
        d.files.import_bytes("mine.csv", exported.encode())
        assert wait_until(
            # z_B -> axes is a matrix product: the slider comes back to the last bit or two (BLAS kernels differ)
            lambda: (
                d.idle() and d.decoded.latents is not None and abs(d.decoded.latents.axes[0] - 2.0) < 1e-9
            ),
            120,
        )
        sync_api.expect(readout.locator('[data-key="model-distance"]')).to_have_text(
            model_cell, timeout=30000
        )
        # 3. A target beyond the family's reach is answered at once, from what the family reaches.
        d.controls.design.forward.value, d.controls.design.sideways.value = 1000.0, 0.0
        assert wait_until(lambda: d.design.marker.position[0] == 1000.0, 10)
        d.design.request()
        assert d.design.worker.wait_idle(120)
        assert "Beyond reach" in d.controls.design.status.content  # in its folder, closed at first
        assert d.design.result.replays == 1 and not d.design.result.met
