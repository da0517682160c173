"""A gait's steering input: what is added to (or scales) its joint commands to turn it, kept with the gait.

Three inputs, each a number u added at every control step (``apply``):

- ``yaw_offset``: u rad added to every yaw joint: a steady bend that turns an undulating snake (Hirose;
  González-Gómez et al. 2006 on an 8-module pitch-yaw snake);
- ``pitch_offset``: u rad added to every pitch joint;
- ``conical``: every joint's command scaled by 1 + u g_k, g running from +1 at the head to -1 at the
  tail: an amplitude gradient that turns a sidewinding snake (Gong, Travers, Choset 2013).

Which one turns a gait, how fast per unit, and over what range is measured per gait by replays
(``sim.control.find``); a gait no input steers both ways carries ``kind = "none"`` and its reason, and
is played open loop. Numpy only: a robot's own computer applies it (``sim.control.follower``).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

SteeringKind = Literal["yaw_offset", "pitch_offset", "conical"]
STEERING_KINDS: tuple[str, ...] = SteeringKind.__args__
PROBE: dict[str, float] = {"yaw_offset": 0.15, "pitch_offset": 0.15, "conical": 0.3}
"""The probe amplitude of each input (its unit: rad, rad, a fraction of the amplitude), chosen so that
one probe turns the library's undulation by ~18 deg/s (yaw offset) and its sidewinding by a like rate
(conical). Each is probed at this and twice this (``sim.control.find``)."""
UNIT = {"yaw_offset": "rad", "pitch_offset": "rad", "conical": ""}


def steering_pattern(kind: str, joint_axes: tuple[str, ...]) -> np.ndarray:
    """The per-joint pattern of an input (n_joints,): the joints an offset is added to (1 or 0), or
    the conical gradient g (+1 head ... -1 tail)."""
    axes = np.array(joint_axes)
    if kind == "yaw_offset":
        return (axes == "yaw").astype(np.float64)
    if kind == "pitch_offset":
        return (axes == "pitch").astype(np.float64)
    if kind == "conical":
        return np.linspace(1.0, -1.0, len(axes))
    raise ValueError(f"unknown steering input {kind!r}: one of {', '.join(STEERING_KINDS)}")


def apply(kind: str, pattern: np.ndarray, base: np.ndarray, u, limit: float) -> np.ndarray:
    """Joint targets (..., n_joints) rad with input ``u`` (scalar or (...,)) applied to ``base``
    (..., n_joints), clipped to +/- ``limit`` rad (the robot's command limit)."""
    u = np.asarray(u, np.float64)[..., None]
    out = base * (1.0 + u * pattern) if kind == "conical" else base + u * pattern
    return np.clip(out, -limit, limit)


class Steering(BaseModel):
    """How a gait is steered, as measured by its probes (``sim.control.find``). ``kind = "none"``: no
    input turned it both ways in proportion; ``why`` says what was measured."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    kind: Literal["yaw_offset", "pitch_offset", "conical", "none"] = "none"
    turn_rate: float = Field(
        0.0, description="Turn of the averaged heading per unit input (rad/s per unit), signed."
    )
    limit: float = Field(0.0, ge=0, description="Largest input used (the probes' usable range).")
    period: float = Field(
        1.0, gt=0, description="The gait's wave period (s): the heading is averaged over it."
    )
    travel_offset: float = Field(
        0.0,
        description="Direction of travel minus the averaged heading (rad): +-pi/2 for a sidewinding gait.",
    )
    speed: float = Field(0.0, ge=0, description="Speed of the unsteered gait's averaged body (m/s).")
    why: str = Field("", description="What the probes measured (for a person).")

    @property
    def steers(self) -> bool:
        return self.kind != "none"

    def line(self) -> str:
        """'steers by yaw offset: 18 deg/s at 0.15 rad' or 'no steering input: ...'."""
        if not self.steers:
            return f"no steering input: {self.why}" if self.why else "no steering input"
        probe = PROBE[self.kind]
        rate = math.degrees(abs(self.turn_rate) * probe)
        unit = UNIT[self.kind]
        name = self.kind.replace("_", " ")
        return f"steers by {name}: {rate:.0f} deg/s at {probe:g}{(' ' + unit) if unit else ''}"
