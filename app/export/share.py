"""A replay that opens anywhere: ``snakeloco export GAIT.csv --format html --out DIR``.

The gait is replayed in MuJoCo (with its ensemble fan: the same commands with 0.1% noise), and the
scene is recorded with viser's own scene serializer while the snake moves: the metre grid, the
simulated path (blue), the model's path where one is given (orange), the fan (grey), the readout's
figures as a label, and the snake's link poses frame by frame. ``DIR/index.html`` is viser's client
build with the recording inside (``StateSerializer.as_html``): it opens from disk or any static
host, with no server, and plays the replay with viser's playback bar.
"""

from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path

import numpy as np
import trimesh

from snakeloco.app.designer.scene import FAN_COLOR, GEN_COLOR, SIM_COLOR, SNAKE_COLOR
from snakeloco.app.designer.scene_geometry import path_points, polyline
from snakeloco.app.designer.view import framing
from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.physics.body import heading_text, travel
from snakeloco.sim.robot.description import Robot, resolve_robot
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE, perturbed_commands

SHARE_FPS = 10.0
"""Frames per second of the recorded replay (the snake's poses: 1000 frames over 100 s)."""


def readout(body: np.ndarray, fan_ends: np.ndarray, model_body: np.ndarray | None, title: str) -> str:
    """The figures a reader of the page needs, as lines of text."""
    end = body[-1, 1:3]
    figures = travel(body)
    spread = float(np.sqrt(np.mean(np.sum((fan_ends - end) ** 2, axis=1)))) if len(fan_ends) else 0.0
    lines = [
        title,
        f"MuJoCo (blue): distance {figures['distance_m']:.2f} m in {RECORD.duration:.0f} s, direction of travel "
        f"{figures['direction_deg']:+.0f}°, heading change {heading_text(360.0 * figures['turns'])}",
        f"Ensemble fan (grey, 0.1% noise): ends within {spread:.2f} m RMS of the replay",
    ]
    if model_body is not None:
        gap = float(np.hypot(*(model_body[-1, 1:3] - end)))
        lines.append(f"Model (orange): ends {gap:.2f} m from MuJoCo's end point")
    return "\n".join(lines)


def replay_for_share(
    commands: np.ndarray, robot: Robot, ensemble: int = ENSEMBLE_SIZE, workers: int | None = None
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The replay's body (T, 6) and qpos (T, nq), and its fan's bodies (the perturbed replays that
    did not break), as the designer shows them."""
    from snakeloco.sim.physics.results import SimulationError
    from snakeloco.sim.physics.simulator import Simulator

    simulator = Simulator(workers=workers, robot=robot)
    try:
        result = simulator.simulate(perturbed_commands(np.asarray(commands, np.float64), ensemble))
    finally:
        simulator.close()
    if result.failures[0] is not None:
        raise SimulationError(f"the replay broke: {result.failures[0]}")
    fan = [b for b, f in zip(result.body[1:], result.failures[1:], strict=True) if f is None]
    return result.body[0], result.qpos[0], fan


def record_html(
    body: np.ndarray,
    qpos: np.ndarray,
    fan: list[np.ndarray],
    robot: Robot | None = None,
    model_body: np.ndarray | None = None,
    title: str = "snakeloco gait",
    fps: float = SHARE_FPS,
) -> tuple[str, int]:
    """The page (viser's client with the recording inside) and its frame count, for a replay's body
    (T, 6) and qpos (T, nq) at 20 Hz, its fan's bodies, and the model's path (T', 6) if any."""
    import viser

    from snakeloco.sim.robot.kinematics import LinkPoses

    kinematics = LinkPoses(resolve_robot(robot))
    start = kinematics.start_frame(qpos[0])
    z0 = float(start[0][2])
    step = max(1, round(RECORD.sample_rate / fps))
    frames = range(0, len(qpos), step)

    with contextlib.redirect_stdout(io.StringIO()):  # viser's banner names a server nobody should open
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = server.scene
        serializer = server.get_scene_serializer()
        scene.set_up_direction("+z")
        points = [path_points(body, z0)]
        scene.add_grid("/grid", width=40, height=40, cell_size=1.0, section_size=5.0, plane="xy")
        for i, b in enumerate(fan):
            scene.add_line_segments(
                f"/fan/{i}",
                polyline(path_points(b[::4], z0)),
                FAN_COLOR,
                thickness=1.0,
                thickness_units="screen",
            )
        scene.add_line_segments(
            "/simulated", polyline(points[0][::4]), SIM_COLOR, thickness=4.0, thickness_units="screen"
        )
        if model_body is not None:
            points.append(path_points(model_body, z0))
            scene.add_line_segments(
                "/generated", polyline(points[1]), GEN_COLOR, thickness=4.0, thickness_units="screen"
            )
        radius, length = kinematics.capsule()
        capsule = trimesh.creation.capsule(height=length, radius=radius, count=[12, 12])
        capsule.visual.vertex_colors = np.array(SNAKE_COLOR, dtype=np.uint8)
        positions, wxyzs = kinematics.poses(qpos[0], start)
        snake = scene.add_batched_meshes_trimesh(
            "/snake", capsule, batched_wxyzs=wxyzs, batched_positions=positions
        )
        cloud = np.concatenate(points)
        text = readout(body, np.array([b[-1, 1:3] for b in fan]), model_body, title)
        position, look_at = framing(cloud, 50.0 * np.pi / 180.0, 1.6)
        size = max(float(np.ptp(cloud[:, :2], axis=0).max()), 1.0)
        # The label floats above the paths (high in the view, never over them); the snake, 1 m long
        # in a view of tens of metres, is ringed so the eye finds it.
        scene.add_label("/readout", text, position=tuple(look_at + np.array([0.0, 0.0, 0.45 * size])))
        server.initial_camera.position = tuple(position)
        server.initial_camera.look_at = tuple(look_at)
        r = max(0.6, 0.04 * size)
        marker = trimesh.creation.annulus(r_min=0.7 * r, r_max=r, height=0.02)
        marker.visual.vertex_colors = np.array(SNAKE_COLOR, dtype=np.uint8)
        ring = scene.add_mesh_trimesh("/snake_marker", marker)
        for n in frames:
            positions, wxyzs = kinematics.poses(qpos[n], start)
            with server.atomic():
                snake.batched_positions = positions
                snake.batched_wxyzs = wxyzs
                ring.position = tuple(positions.mean(axis=0) * [1, 1, 0])
            serializer.insert_sleep(step / RECORD.sample_rate)
        html = serializer.as_html()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
    return html, len(frames)


def share_html(
    commands: np.ndarray,
    out: Path,
    robot: Robot | None = None,
    model_body: np.ndarray | None = None,
    title: str = "snakeloco gait",
    ensemble: int = ENSEMBLE_SIZE,
    fps: float = SHARE_FPS,
    workers: int | None = None,
) -> dict:
    """Replay ``commands`` (T, J) rad on ``robot`` with its fan and write ``out/index.html``; returns
    its path, size (bytes), frames, the seconds it took and the readout's text."""
    t0 = time.perf_counter()
    robot = resolve_robot(robot)
    body, qpos, fan = replay_for_share(commands, robot, ensemble, workers)
    html, frames = record_html(body, qpos, fan, robot, model_body, title, fps)
    out.mkdir(parents=True, exist_ok=True)
    (out / "index.html").write_text(html)
    return {
        "path": str(out / "index.html"),
        "bytes": (out / "index.html").stat().st_size,
        "frames": frames,
        "seconds": time.perf_counter() - t0,
        "readout": readout(body, np.array([b[-1, 1:3] for b in fan]), model_body, title),
    }
