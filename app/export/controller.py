"""``snakeloco export GAIT.csv --format controller``: a folder a robot's own loop runs.

``snakeloco.sim.control.PathFollower.load(DIR)`` reads it (numpy and pydantic only): ``controller.json``
(the steering input, the follower's parameters, the command rule's lead-in, the joints), ``commands.csv``
(the gait, rad at 20 Hz), ``reference.csv`` (the path it follows, m, in the frame of the robot's first
pose) and ``gait.csv`` (the gait CSV it came from). docs/closed-loop.md has the loop in 20 lines.
"""

from __future__ import annotations

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


def export_controller(text: str, commands: np.ndarray, out: Path, robot, source: str, workers=None) -> dict:
    """Write the controller folder of a gait (module docstring); returns what was written."""
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
    follower = make_follower(commands, reference, steering, simulator)
    follower.save(
        out, about={"gait": source, "robot": robot.name, "steering": origin, "line": steering.line()}
    )
    (out / "gait.csv").write_text(text)
    return {
        "path": str(out),
        "steering": steering.model_dump(),
        "steering_line": steering.line(),
        "steering_from": origin,
        "reference_points": len(reference),
        "distance_m": float(np.linalg.norm(reference[-1] - reference[0])),
        "files": sorted(p.name for p in out.iterdir()),
    }
