"""``snakeloco export GAIT.csv --format controller``: a folder a robot's own loop runs.

``snakeloco.sim.control.PathFollower.load(DIR)`` reads it (numpy and pydantic only): ``controller.json``
(the steering input, the follower's parameters, the command rule's lead-in, the joints), ``commands.csv``
(the gait, rad at 20 Hz), ``reference.csv`` (the path it follows, m, in the frame of the robot's first
pose) and ``gait.csv`` (the gait CSV it came from). docs/closed-loop.md has the loop in 20 lines.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from snakeloco.app.export.gait_csv import read_closed_loop_path, read_steering


def gait_steering(text: str, commands: np.ndarray, simulator):
    """The gait's steering input: its CSV's ``# steering:`` comment where it has one, else found by
    replays on ``simulator``'s robot (``sim.control.find``), and where it came from in words."""
    from snakeloco.sim.control.find import find_steering

    steering = read_steering(text)
    if steering is not None:
        return steering, "from the gait's '# steering:' comment"
    return find_steering(commands, simulator), f"found by replays on {simulator.robot.name}"


def follower_for(text: str, commands: np.ndarray, robot, workers=None):
    """The ``PathFollower`` of a gait CSV on ``robot`` (its steering input and the path it follows,
    cut and turned where a closed-loop design says so), and where its input came from in words."""
    from snakeloco.sim.control.closed_loop import cut_and_turn, make_follower, nominal_path
    from snakeloco.sim.physics.simulator import Simulator

    simulator = Simulator(workers=workers, robot=robot)
    try:
        steering, origin = gait_steering(text, commands, simulator)
        reference, record = nominal_path(commands, simulator, steering.period)
        cut = read_closed_loop_path(text)  # a closed-loop design's candidate: to its target, turned
        if cut is not None:
            reference = cut_and_turn(reference, cut["until"], record[:2], math.radians(cut["turn_deg"]))
    finally:
        simulator.close()
    return make_follower(commands, reference, steering, simulator), origin


def export_controller(text: str, commands: np.ndarray, out: Path, robot, source: str, workers=None) -> dict:
    """Write the controller folder of a gait (module docstring) and its path as ``path.yaml``
    (``nav_msgs/Path``); returns what was written."""
    follower, origin = follower_for(text, commands, robot, workers)
    steering, reference = follower.steering, follower.reference
    follower.save(
        out, about={"gait": source, "robot": robot.name, "steering": origin, "line": steering.line()}
    )
    (out / "gait.csv").write_text(text)
    (out / "path.yaml").write_text(ros2_path(reference, follower_parameters(follower)))
    return {
        "path": str(out),
        "steering": steering.model_dump(),
        "steering_line": steering.line(),
        "steering_from": origin,
        "reference_points": len(reference),
        "distance_m": float(np.linalg.norm(reference[-1] - reference[0])),
        "files": sorted(p.name for p in out.iterdir()),
    }


def follower_parameters(follower) -> dict:
    """What a ROS 2 node needs besides the path: the steering input and the follower's config."""
    return {
        "steering": follower.steering.model_dump(),
        "follower": follower.config.model_dump(),
        "rate_hz": follower.rate,
    }


def ros2_path(reference: np.ndarray, follower: dict, frame_id: str = "odom") -> str:
    """A ``nav_msgs/Path`` YAML of ``reference`` (n, 2) m, every pose facing along the path, with the
    follower's parameters (``controller.json``'s) in the comments above it."""
    import yaml

    step = max(1, len(reference) // 1000)  # at most ~1000 poses: a 5 Hz path of the 100 s record
    xy = reference[::step]
    heading = np.arctan2(*np.gradient(xy, axis=0)[:, ::-1].T)  # (n,) rad: atan2(dy, dx)
    poses = [
        {
            "header": {"frame_id": frame_id},
            "pose": {
                "position": {"x": float(x), "y": float(y), "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": float(np.sin(h / 2)), "w": float(np.cos(h / 2))},
            },
        }
        for (x, y), h in zip(xy, heading, strict=True)
    ]
    head = "".join(f"# {k}: {json.dumps(v, separators=(',', ':'))}\n" for k, v in follower.items())
    msg = {"header": {"frame_id": frame_id}, "poses": poses}
    return (
        "# snakeloco export: nav_msgs/Path the gait's steering loop follows, m, in the frame of the robot's "
        "first pose\n" + head + yaml.safe_dump(msg, sort_keys=False, default_flow_style=None, width=1 << 16)
    )
