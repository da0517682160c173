"""The terrain set: the worlds a gait is scored over beside the physics variations (docs/terrain.md).

Rough ground of 1, 2 and 3 cm, steps of 2 and 4 cm, slopes of 5, 10 and 15 deg rising ahead and to the
left, and a peg field: what a snake robot meets off the lab floor, in steps a family of gaits can be
ranked by. ``robustness --set terrain`` replays a gait on each (``sim.scores.terrain``).
"""

from __future__ import annotations

from snakeloco.sim.world.description import Pegs, Rough, Steps, World


def _rough(cm: int) -> World:
    return World(name=f"rough {cm} cm", rough=Rough(height_m=cm / 100, extent_m=15.0, seed=cm))


def _steps(cm: int) -> World:
    return World(name=f"steps {cm} cm", steps=Steps(height_m=cm / 100, depth_m=0.5, count=3, start_m=1.0))


def _slope(deg: int, direction: float, way: str) -> World:
    return World(name=f"slope {deg} deg {way}", slope_deg=float(deg), slope_direction_deg=direction)


TERRAIN_SET: tuple[World, ...] = (
    _rough(1),
    _rough(2),
    _rough(3),
    _steps(2),
    _steps(4),
    *(_slope(d, a, w) for d in (5, 10, 15) for a, w in ((0.0, "ahead"), (90.0, "left"))),
    World(name="pegs", pegs=Pegs()),
)
"""12 worlds, one change of ground each (the flat plane is the reference, not a member)."""
