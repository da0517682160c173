"""Variations of a robot's physics: named partial changes of a ``Robot`` description, and the sets
the designer, ``snakeloco robustness`` and robust design score a gait over.

A variation scales, adds to or sets physical fields only (masses, servo gains and torque, joint
damping and armature, floor friction, slope, latency): a varied robot has the same bodies, joints
and sensors, so a set of variations replays as one batch of models of one size signature
(``Simulator.simulate(..., robots=...)``). Geometry (``n_joints``, link length and radius, joint
pattern) and the timestep are not physics in this sense: another geometry is another robot.

Why each range of the default set (docs/variations.md has the figures):
published randomisation for legged sim-to-real uses floor friction 0.5-1.0x around nominal (up to
2x), command latency 10-50 ms and added payload; snake robots' scales give friction ratios from 2:1
(a smooth shell) to 8:1 and more (~0.11 along, ~0.38 across measured on real snakes); hobby and
Dynamixel-class servos differ by 2x in stiffness between models, loads and firmware settings; a
lab floor is rarely level to better than a few degrees, and 5 degrees is a gentle ramp.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from snakeloco.sim.robot.description import (
    DEFAULT_ROBOT,
    Robot,
    RobotError,
    robot_from_dict,
)
from snakeloco.sim.robot.files import validation_message
from snakeloco.sim.robot.sensing import SENSING_FIELDS

PhysicalField = Literal[
    "link_mass",
    "servo_kp",
    "servo_kv",
    "servo_force",
    "armature",
    "joint_damping",
    "friction_along",
    "friction_across",
    "friction_torsion",
    "friction_rolling",
    "slope_deg",
    "slope_direction_deg",
    "latency",
    "pose_noise_m",
    "pose_noise_deg",
    "heading_drift_deg_per_min",
    "pose_rate",
    "pose_latency",
]
PHYSICAL_FIELDS: tuple[str, ...] = PhysicalField.__args__


class Variation(BaseModel):
    """A named partial change of a robot's physical fields: each field in ``scale`` is multiplied, in
    ``add`` increased, in ``set`` replaced (applied in that order)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    name: str = Field(min_length=1, description="What a person reads: 'floor friction x0.5'.")
    scale: dict[PhysicalField, float] = Field(default_factory=dict)
    add: dict[PhysicalField, float] = Field(default_factory=dict)
    set: dict[PhysicalField, float] = Field(default_factory=dict)
    reason: str = Field("", description="Why this change is plausible on a real robot.")

    @model_validator(mode="after")
    def _changes_something(self) -> Variation:
        if not (self.scale or self.add or self.set):
            raise ValueError(f"variation {self.name!r} changes nothing")
        if any(k <= 0 for k in self.scale.values()):
            raise ValueError(f"variation {self.name!r}: a scale factor must be positive")
        return self

    @property
    def fields(self) -> tuple[str, ...]:
        """The physical fields it changes."""
        return tuple(dict.fromkeys([*self.scale, *self.add, *self.set]))

    def apply(self, robot: Robot) -> Robot:
        """The varied robot; RobotError (naming this variation) where the result is no robot."""
        values = robot.model_dump()
        sensing = values["sensing"]
        for name, k in self.scale.items():
            (sensing if name in SENSING_FIELDS else values)[name] *= k
        for name, v in self.add.items():
            (sensing if name in SENSING_FIELDS else values)[name] += v
        for name, v in self.set.items():
            (sensing if name in SENSING_FIELDS else values)[name] = v
        values["name"] = f"{robot.name} ({self.name})"[:64]
        return robot_from_dict(values, f"variation {self.name!r} of {robot.name}")

    def params(self) -> dict[str, dict[str, float]]:
        """The changes as plain data (for reports)."""
        return {k: dict(v) for k, v in (("scale", self.scale), ("add", self.add), ("set", self.set)) if v}


def _v(name: str, reason: str, **changes: dict[str, float]) -> Variation:
    return Variation(name=name, reason=reason, **changes)


DEFAULT_SET: tuple[Variation, ...] = (
    _v(
        "floor friction x0.5",
        "a polished or dusty floor; randomisation ranges go down to 0.5x nominal",
        scale={"friction_along": 0.5, "friction_across": 0.5},
    ),
    _v(
        "floor friction x2",
        "carpet, rubber mats or a grippier skin",
        scale={"friction_along": 2.0, "friction_across": 2.0},
    ),
    _v(
        "anisotropy 2:1",
        "a smooth shell: friction along the links as high as half that across (nominal 4:1)",
        scale={"friction_along": 2.0},
    ),
    _v(
        "anisotropy 8:1",
        "scales or passive wheels: friction along the links an eighth of that across",
        scale={"friction_along": 0.5},
    ),
    _v(
        "link masses x1.5",
        "batteries, boards and shells heavier than the design mass",
        scale={"link_mass": 1.5},
    ),
    _v(
        "servo kp x0.5",
        "a softer servo, a lower firmware gain, or a sagging supply voltage",
        scale={"servo_kp": 0.5},
    ),
    _v("servo kp x2", "a stiffer servo or a higher gain setting", scale={"servo_kp": 2.0}),
    _v("servo kv x2", "more damping in the gearbox or the servo's loop", scale={"servo_kv": 2.0}),
    _v("joint damping x2", "stiffer gearboxes and cable drag", scale={"joint_damping": 2.0}),
    _v(
        "latency 30 ms",
        "a bus that sends each command late (published ranges 10-50 ms)",
        add={"latency": 0.03},
    ),
    _v(
        "5 deg slope uphill ahead",
        "a floor that is not level: the ground rises along the snake's initial heading",
        add={"slope_deg": 5.0},
        set={"slope_direction_deg": 0.0},
    ),
    _v(
        "5 deg slope uphill left",
        "a floor that is not level: the ground rises to the snake's initial left",
        add={"slope_deg": 5.0},
        set={"slope_direction_deg": 90.0},
    ),
)
"""The default variation set: one physical change at a time, each within the range a real snake
robot of this size plausibly differs from its model (module docstring)."""

SAMPLED_RANGES: dict[str, tuple[str, float, float]] = {
    "friction": ("log", 0.5, 2.0),  # both coefficients together
    "friction_along": ("log", 0.5, 2.0),  # anisotropy, on top
    "link_mass": ("lin", 1.0, 1.5),
    "servo_kp": ("log", 0.5, 2.0),
    "servo_kv": ("log", 0.5, 2.0),
    "slope_deg": ("lin", 0.0, 5.0),
    "slope_direction_deg": ("lin", -180.0, 180.0),
    "latency": ("lin", 0.0, 0.05),
}
"""Ranges of the sampled set: every factor at once, each drawn within the default set's range."""


def sampled_set(n: int = 16, seed: int = 0) -> tuple[Variation, ...]:
    """``n`` combined variations drawn from ``SAMPLED_RANGES`` (deterministic in ``n`` and ``seed``)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        draw = {}
        for name, (kind, lo, hi) in SAMPLED_RANGES.items():
            u = rng.uniform()
            draw[name] = float(
                np.exp(np.log(lo) + u * np.log(hi / lo)) if kind == "log" else lo + u * (hi - lo)
            )
        scale = {
            "friction_along": round(draw["friction"] * draw["friction_along"], 4),
            "friction_across": round(draw["friction"], 4),
            "link_mass": round(draw["link_mass"], 4),
            "servo_kp": round(draw["servo_kp"], 4),
            "servo_kv": round(draw["servo_kv"], 4),
        }
        add = {"slope_deg": round(draw["slope_deg"], 3), "latency": round(draw["latency"], 4)}
        out.append(
            Variation(
                name=f"sampled {i + 1}",
                scale=scale,
                add=add,
                set={"slope_direction_deg": round(draw["slope_direction_deg"], 1)},
                reason="every physical factor at once, each drawn within the default set's range",
            )
        )
    return tuple(out)


VARIATION_SETS = ("default", "sampled")


def variation_set(name: str) -> tuple[Variation, ...]:
    """A named set: ``default`` (one change at a time) or ``sampled`` (16 combined changes, seed 0), or
    a YAML file of variations (``load_variations``)."""
    if name == "default":
        return DEFAULT_SET
    if name == "sampled":
        return sampled_set()
    if name.endswith((".yaml", ".yml", ".json")):
        return load_variations(name)
    raise ValueError(f"unknown variation set {name!r}: one of {', '.join(VARIATION_SETS)}, or a FILE.yaml")


def load_variations(path: str | Path) -> tuple[Variation, ...]:
    """Variations from YAML: a list of ``Variation`` mappings (or ``{variations: [...]}``), each checked
    on the default robot. RobotError names the file, the entry, the field and the reason."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise RobotError(f"{path}: cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise RobotError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
    if isinstance(data, dict) and set(data) == {"variations"}:
        data = data["variations"]
    if not isinstance(data, list) or not data:
        raise RobotError(
            f"{path}: a variation file is a non-empty list of variations (name, scale, add, set)"
        )
    out = []
    for i, entry in enumerate(data, start=1):
        name = entry.get("name") if isinstance(entry, dict) else None
        where = f"{path}: variation {i}" + (f" ({name!r})" if name else "")
        if not isinstance(entry, dict):
            raise RobotError(f"{where}: a variation is a mapping, got {type(entry).__name__}")
        try:
            v = Variation.model_validate(entry)
        except ValidationError as exc:
            raise RobotError(f"{where}: {validation_message(exc)}") from None
        try:
            v.apply(DEFAULT_ROBOT)  # a field pushed out of its range is refused here, naming it
        except RobotError as exc:
            raise RobotError(f"{where}: {str(exc).partition(': ')[2]}") from None
        out.append(v)
    return tuple(out)
