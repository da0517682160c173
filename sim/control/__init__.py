"""Closed-loop gaits: a steering input per gait and a path follower a robot's own loop runs.

Importing this package imports numpy and pydantic only (no MuJoCo, torch or viser):
``PathFollower`` and ``FollowerConfig`` (``sim.control.follower``), ``Steering``
(``sim.control.steering``). What replays gaits in MuJoCo is imported from its own module:
``sim.control.closed_loop`` (batched closed-loop replays), ``sim.control.find`` (a gait's steering
input, found by replays).
"""

from snakeloco.sim.control.follower import FollowerConfig, PathFollower
from snakeloco.sim.control.steering import STEERING_KINDS, Steering

__all__ = ["STEERING_KINDS", "FollowerConfig", "PathFollower", "Steering"]
