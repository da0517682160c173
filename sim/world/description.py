"""The ground as data: a world description (YAML, a pydantic model like the robot's), built into the
robot's ``mujoco.MjSpec``.

A world is today's plane, tilted by ``slope_deg`` (gravity turned, as ``Robot.gravity`` does: the
floor stays z = 0, so the start pose, the contacts and the drawn grid stay as they are), plus any of:
rough ground (a heightfield of seeded smooth noise: ``rough``), steps (boxes across the way:
``steps``) and a peg field (upright cylinders: ``pegs``), placed along the snake's way. Every ground
ground geom gets the robot's own floor pairs (friction along / across the links), as the plane has
them; pegs meet the links as the links meet each other.
The default world is the plane alone: ``World().add_to(spec, robot)`` changes nothing, so its replays
are today's, bit for bit.

Off the plane, MuJoCo orients a contact's friction frame from the normal alone, which loses the links'
anisotropy (docs/terrain.md): replays on rough ground, steps or pegs need the re-aligned contact frames
of ``sim.physics.anisotropy_probe``; what a world builds here is the geometry and the pairs.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.sim.robot.description import FLOOR, Robot, read_yaml, validated

if TYPE_CHECKING:
    import mujoco

GROUND = "ground"
"""Name prefix of a world's ground geoms beyond the plane (``ground_rough``, ``ground_step1``, ...)."""


class WorldError(ValueError):
    """A world description that cannot be used; the message names the file, the field and the reason."""


class _Part(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Rough(_Part):
    """Rough ground: a square heightfield of smooth seeded noise, its mean at z = 0."""

    height_m: float = Field(0.02, gt=0, le=0.3, description="Peak-to-peak height of the bumps (m).")
    wavelength_m: float = Field(0.3, ge=0.05, le=5.0, description="Typical distance between bumps (m).")
    extent_m: float = Field(30.0, gt=1.0, le=100.0, description="Half the side of the rough square (m).")
    resolution_m: float = Field(0.05, ge=0.01, le=0.5, description="Grid spacing of the heightfield (m).")
    seed: int = Field(0, ge=0, description="Seed of the noise.")

    @model_validator(mode="after")
    def _grid(self) -> Rough:
        if self.resolution_m > self.wavelength_m / 2:
            raise ValueError(f"resolution_m {self.resolution_m} must be at most half of wavelength_m")
        if 2 * self.extent_m / self.resolution_m + 1 > 2001:
            raise ValueError("extent_m / resolution_m makes a heightfield over 2001 x 2001 points")
        return self

    @property
    def points(self) -> int:
        return round(2 * self.extent_m / self.resolution_m) + 1

    def heights(self) -> np.ndarray:
        """(points, points) heights in [0, 1] (MuJoCo's heightfield data, row = y): noise low-passed to
        ``wavelength_m`` by a Gaussian in the frequency domain, seeded."""
        n = self.points
        noise = np.random.default_rng(self.seed).standard_normal((n, n))
        k = np.fft.fftfreq(n, d=self.resolution_m)
        kk = np.hypot(*np.meshgrid(k, k, indexing="ij"))
        smooth = np.fft.ifft2(np.fft.fft2(noise) * np.exp(-0.5 * (kk * self.wavelength_m) ** 2)).real
        lo, hi = smooth.min(), smooth.max()
        return (smooth - lo) / (hi - lo) if hi > lo else np.zeros_like(smooth)


class Steps(_Part):
    """Steps across the way: ``count`` boxes, each ``height_m`` higher than the one before (a stair)."""

    height_m: float = Field(0.02, gt=0, le=0.3, description="Rise of each step (m).")
    depth_m: float = Field(0.5, gt=0.05, le=10.0, description="Tread of each step along the way (m).")
    count: int = Field(3, ge=1, le=50, description="Number of steps.")
    start_m: float = Field(
        1.0, ge=0.0, le=100.0, description="Where the first step begins along the way (m)."
    )
    direction_deg: float = Field(0.0, ge=-360, le=360, description="The way the stair climbs (deg, 0: +x).")
    width_m: float = Field(20.0, gt=0.5, le=200.0, description="Width of the steps across the way (m).")


class Pegs(_Part):
    """A peg field: upright cylinders on a staggered grid, jittered, a snake can push against."""

    radius_m: float = Field(0.03, gt=0.005, le=0.5, description="Peg radius (m).")
    spacing_m: float = Field(0.4, gt=0.05, le=5.0, description="Grid spacing between peg centres (m).")
    jitter_m: float = Field(0.05, ge=0.0, le=2.0, description="Uniform jitter of each peg's place (m).")
    height_m: float = Field(0.15, gt=0.01, le=1.0, description="Peg height (m).")
    extent_m: float = Field(3.0, gt=0.1, le=30.0, description="Half the side of the peg field (m).")
    clear_m: float = Field(0.6, ge=0.0, le=10.0, description="Radius around the start kept clear (m).")
    seed: int = Field(0, ge=0, description="Seed of the jitter.")

    @model_validator(mode="after")
    def _fits(self) -> Pegs:
        if self.spacing_m <= 2 * self.radius_m:
            raise ValueError(f"spacing_m {self.spacing_m} must exceed the peg diameter {2 * self.radius_m}")
        if (2 * self.extent_m / self.spacing_m + 1) ** 2 > 10_000:
            raise ValueError("extent_m / spacing_m makes over 10000 pegs")
        return self

    def centres(self) -> np.ndarray:
        """(n, 2) peg centres (m): a staggered (hexagonal) lattice through the start's row, so no
        straight corridor runs between the pegs, jittered; none within ``clear_m`` of the start."""
        rows = self.spacing_m * math.sqrt(3) / 2
        xy = np.array(
            [
                (i * self.spacing_m + (j % 2) * self.spacing_m / 2, j * rows)
                for j in range(-int(self.extent_m / rows), int(self.extent_m / rows) + 1)
                for i in range(
                    -int(self.extent_m / self.spacing_m) - 1, int(self.extent_m / self.spacing_m) + 1
                )
            ]
        )
        xy = xy[(np.abs(xy) <= self.extent_m + 1e-9).all(axis=1)]
        rng = np.random.default_rng(self.seed)
        xy = xy + rng.uniform(-self.jitter_m, self.jitter_m, xy.shape)
        return xy[np.hypot(xy[:, 0], xy[:, 1]) > self.clear_m + self.radius_m]


class World(_Part):
    """The ground a robot is replayed on (docs/terrain.md); the default is the flat plane."""

    name: str = Field("flat", min_length=1, max_length=64, description="A name for tables and the designer.")
    slope_deg: float = Field(
        0.0, ge=-30.0, le=30.0, description="Incline of the ground (deg; gravity turned)."
    )
    slope_direction_deg: float = Field(
        0.0, ge=-360.0, le=360.0, description="The way the ground rises (deg from +x, counter-clockwise)."
    )
    rough: Rough | None = Field(None, description="Rough ground (a heightfield); none: flat.")
    steps: Steps | None = Field(None, description="Steps across the way; none: no steps.")
    pegs: Pegs | None = Field(None, description="A peg field; none: no pegs.")

    @property
    def flat(self) -> bool:
        """Whether this is the plane alone (the robot's model as it is, but for a slope)."""
        return self.rough is None and self.steps is None and self.pegs is None

    def gravity(self, robot: Robot) -> tuple[float, float, float]:
        """Gravity (m/s^2) with this world's slope, tilted further by a robot's own ``slope_deg`` (an old
        robot file, or a slope variation replayed on this world): the two tilts compose."""
        s, d = math.radians(self.slope_deg), math.radians(self.slope_direction_deg)
        world = np.array([-math.sin(s) * math.cos(d), -math.sin(s) * math.sin(d), -math.cos(s)])
        own = np.asarray(robot.gravity, np.float64) / 9.81  # the robot's tilt of straight down
        axis = np.cross([0.0, 0.0, -1.0], own)  # rotate by the tilt that takes down to ``own``
        sin, cos = np.linalg.norm(axis), -own[2]
        if sin > 1e-12:
            k = axis / sin
            world = world * cos + np.cross(k, world) * sin + k * (k @ world) * (1 - cos)
        return tuple(float(v) for v in 9.81 * world)

    def figures(self) -> dict[str, float | int | str]:
        """What ``snakeloco world show`` prints."""
        out: dict[str, float | int | str] = {"name": self.name, "slope_deg": self.slope_deg}
        if self.slope_deg:
            out["slope_direction_deg"] = self.slope_direction_deg
        if self.rough is not None:
            r = self.rough
            out |= {"rough_points": f"{r.points} x {r.points}", "rough_height_m": r.height_m}
        if self.steps is not None:
            s = self.steps
            out |= {"steps": s.count, "steps_top_m": round(s.count * s.height_m, 4)}
        if self.pegs is not None:
            out["pegs"] = len(self.pegs.centres())
        out["ground_geoms"] = len(self.ground_geoms())
        return out

    def ground_geoms(self) -> list[str]:
        """The names of the geoms the world adds (the ground's get the robot's floor pairs; pegs collide
        with the links by default)."""
        names = [f"{GROUND}_rough"] if self.rough is not None else []
        names += (
            [f"{GROUND}_step{k}" for k in range(1, self.steps.count + 1)] if self.steps is not None else []
        )
        names += [f"{GROUND}_peg{k}" for k in range(1, len(self.pegs.centres()) + 1)] if self.pegs else []
        return names

    def add_to(self, spec: mujoco.MjSpec, robot: Robot) -> mujoco.MjSpec:
        """Build this world into ``robot``'s spec (``Robot.build_spec()``): its slope, its ground geoms,
        and the robot's floor pairs on each. The default world returns ``spec`` unchanged."""
        import mujoco

        if self.slope_deg != 0.0:
            spec.option.gravity = self.gravity(robot)  # the robot's spec has its own tilt already
        if self.flat:
            return spec
        world = spec.worldbody
        common = {"contype": 2, "conaffinity": 2, "rgba": [0.62, 0.58, 0.5, 1]}
        if self.rough is not None:
            r = self.rough
            field = spec.add_hfield(
                name=f"{GROUND}_rough",
                size=[r.extent_m, r.extent_m, r.height_m, 0.1],
                nrow=r.points,
                ncol=r.points,
            )
            heights = r.heights()
            field.userdata = heights.reshape(-1).tolist()
            mean = float(heights.mean()) * r.height_m
            world.add_geom(
                name=f"{GROUND}_rough", type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname=f"{GROUND}_rough",
                pos=[0, 0, -mean], **common,
            )  # fmt: skip
            spec.geom(FLOOR).pos = [0, 0, -mean]  # the plane under the valleys, not through them
        if self.steps is not None:
            s = self.steps
            d = math.radians(s.direction_deg)
            for k in range(1, s.count + 1):
                top = k * s.height_m
                along = s.start_m + (k - 0.5) * s.depth_m
                world.add_geom(
                    name=f"{GROUND}_step{k}",
                    type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=[s.depth_m / 2, s.width_m / 2, top / 2],
                    pos=[along * math.cos(d), along * math.sin(d), top / 2],
                    quat=[math.cos(d / 2), 0, 0, math.sin(d / 2)],
                    **common,
                )
        if self.pegs is not None:
            # Pegs meet the links through the default collision (the links' contype 1, a broadphase)
            # rather than a pair per peg and link; their friction is the links' along the body (a
            # link slides past a peg it pushes against), taken by priority over the link's own.
            p = self.pegs
            for k, (x, y) in enumerate(self.pegs.centres(), start=1):
                world.add_geom(
                    name=f"{GROUND}_peg{k}",
                    type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                    size=[p.radius_m, p.height_m / 2, 0],
                    pos=[float(x), float(y), p.height_m / 2],
                    contype=1,
                    conaffinity=1,
                    priority=1,
                    friction=[robot.friction_along, robot.friction_torsion, robot.friction_rolling],
                    rgba=[0.45, 0.42, 0.38, 1],
                )
        for ground in self.ground_geoms():
            if ground.startswith(f"{GROUND}_peg"):
                continue
            for link in robot.link_geoms:
                spec.add_pair(geomname1=ground, geomname2=link, condim=3, friction=robot.floor_friction)
        return spec

    def compile(self, robot: Robot) -> mujoco.MjModel:
        """``robot`` on this world, compiled."""
        return self.add_to(robot.build_spec(), robot).compile()

    def mjcf(self, robot: Robot) -> str:
        return self.add_to(robot.build_spec(), robot).to_xml()


DEFAULT_WORLD = World()
"""The flat plane: today's ground."""
WORLDS_DIR = Path(__file__).resolve().parent.parent / "worlds"
"""The shipped worlds (``sim/worlds/*.yaml``)."""


def world_from_dict(data: object, source: str = "world") -> World:
    """Validate a parsed world; WorldError names ``source``, the field and the reason."""
    return validated(World, data, source, WorldError, "world")


def load_world(path: str | Path) -> World:
    """A world from YAML: a path, or the name of a shipped world (``rough``, ``steps``, ...)."""
    path = Path(path)
    if not path.exists() and (WORLDS_DIR / f"{path.name}.yaml").exists():
        path = WORLDS_DIR / f"{path.name}.yaml"
    shipped = ", ".join(sorted(p.stem for p in WORLDS_DIR.glob("*.yaml")))
    return world_from_dict(read_yaml(path, WorldError, f"; shipped worlds: {shipped}"), str(path))
