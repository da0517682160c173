"""The snake robot as data: one pydantic description of its geometry and physics, and its MuJoCo model.

Units: metres, kilograms, seconds, radians (angles of the world, the slope, in degrees where the field
says so). ``Robot()`` is the paper's 8-joint snake; ``Robot.build_spec`` builds its model with
``mujoco.MjSpec`` (no string templates) and the compiled default equals ``sim/snake.xml``, the
hand-commented MJCF that documents each number (tested field by field and by bit-identical replays).

One type serves every use: a new robot (``snakeloco robot show|mjcf ROBOT.yaml``), a *variation* (a
named partial change of the physical fields, ``sim.robot.variations``) and a robot fitted to a measured run.
Importing this module does not import MuJoCo (``build_spec`` and ``compile`` do): the model package
reads the description and its hash without the simulator.

The module-level constants (``LINK_LENGTH``, ``BODY_LENGTH`` ...) are the default robot's, kept for the
code that has not yet been taught to read a description.
"""

from __future__ import annotations

import hashlib
import math
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.sim.robot.files import read_yaml, validated
from snakeloco.sim.robot.sensing import Sensing

if TYPE_CHECKING:
    import mujoco

MJCF_PATH = Path(__file__).parents[1] / "snake.xml"
ROBOTS_DIR = Path(__file__).parents[1] / "robots"
"""Example robot descriptions shipped with the package (``twelve.yaml``, ``planar6.yaml``)."""
COMMAND_RATE = 20.0
"""Command samples per second (Hz); the timestep must divide the command period."""
BODY_SITE = "body_frame"
"""Site whose pose is the measured body state: the middle link's centre (see ``Robot.body_link``)."""
FLOOR = "floor"


class RobotError(ValueError):
    """A robot description that cannot be: the message names the file, the field and the reason."""


class Robot(BaseModel):
    """A snake robot: ``n_joints`` hinges joining ``n_joints + 1`` identical capsule links in a chain,
    position servos, anisotropic floor friction, and the world it lies in.

    Joint k (1-based) sits at the rear of link k and joins it to link k + 1. ``alternate``: odd
    joints pitch (axis y of the link frame), even joints yaw (axis z), neighbouring axes
    perpendicular; ``planar``: every joint yaws. The body frame is the middle link's centre (odd
    link count) or the middle joint (even link count), head at +x at rest.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field("snakeloco-8", min_length=1, max_length=64, description="A name for people and files.")
    # Geometry.
    n_joints: int = Field(8, ge=4, le=32, description="Actuated hinge joints (links = n_joints + 1).")
    link_length: float = Field(0.10, gt=0, le=1.0, description="Joint-to-joint distance along a link (m).")
    link_radius: float = Field(0.025, gt=0, le=0.25, description="Capsule radius (m).")
    link_mass: float = Field(0.2, gt=0, le=50.0, description="Mass of each link (kg).")
    joint_pattern: Literal["alternate", "planar"] = Field(
        "alternate", description="alternate: pitch, yaw, pitch, ... from the head; planar: all yaw."
    )
    joint_range: float = Field(2.3, gt=0, le=math.pi, description="Joint stops at +/- this angle (rad).")
    command_limit: float = Field(
        2.2, gt=0, le=math.pi, description="Commands are clipped to +/- this angle (rad), inside the range."
    )
    joint_speed_limit: float = Field(
        12.0,
        gt=0,
        description="Fastest joint command the servos follow (rad/s), checked by export: a hobby "
        "servo's 0.1 s per 60 degrees at no load is 10.5 rad/s.",
    )
    # Servos.
    servo_kp: float = Field(30.0, gt=0, description="Position gain (N m/rad).")
    servo_kv: float = Field(0.6, ge=0, description="Velocity damping of the servo (N m s/rad).")
    servo_force: float = Field(8.0, gt=0, description="Torque limit (N m).")
    armature: float = Field(0.002, ge=0, description="Rotor inertia reflected at the joint (kg m^2).")
    joint_damping: float = Field(0.01, ge=0, description="Passive joint damping (N m s/rad).")
    servo_ids: tuple[int, ...] | None = Field(
        None, description="Bus id of each joint's servo, head to tail (None: 1..n_joints)."
    )
    home_offsets: tuple[float, ...] | None = Field(
        None, description="Servo reading at joint angle 0, per joint (rad; None: all 0)."
    )
    # Contact.
    friction_along: float = Field(0.15, gt=0, le=5.0, description="Floor friction along each link.")
    friction_across: float = Field(0.6, gt=0, le=5.0, description="Floor friction across each link.")
    friction_torsion: float = Field(0.005, ge=0, description="Torsional floor friction (m).")
    friction_rolling: float = Field(0.0001, ge=0, description="Rolling floor friction (m).")
    # World.
    slope_deg: float = Field(0.0, ge=0, le=30.0, description="Ground slope (degrees).")
    slope_direction_deg: float = Field(
        0.0,
        ge=-180.0,
        le=180.0,
        description="Direction the ground rises, degrees from the snake's initial heading (+x), "
        "counter-clockwise (90: uphill to the snake's left).",
    )
    latency: float = Field(
        0.0, ge=0, le=0.2, description="Command latency (s): each servo target arrives this much late."
    )
    timestep: float = Field(0.0025, gt=0, le=0.005, description="Physics step (s); divides 1/20 s.")
    sensing: Sensing = Field(default_factory=Sensing, description="The pose estimate a steering loop gets.")

    @model_validator(mode="after")
    def _consistent(self) -> Robot:
        if self.command_limit >= self.joint_range:
            raise ValueError(
                f"command_limit {self.command_limit} rad must be inside joint_range {self.joint_range} rad"
            )
        if 2 * self.link_radius >= self.link_length:
            raise ValueError(
                f"link_radius {self.link_radius} m: two link radii must be shorter than link_length "
                f"{self.link_length} m, or links two apart touch at rest"
            )
        steps = 1.0 / (COMMAND_RATE * self.timestep)
        if abs(steps - round(steps)) > 1e-9 * steps:
            raise ValueError(f"timestep {self.timestep} s does not divide the command period 0.05 s")
        for field in ("servo_ids", "home_offsets"):
            value = getattr(self, field)
            if value is not None and len(value) != self.n_joints:
                raise ValueError(f"{field} has {len(value)} entries for {self.n_joints} joints")
        if self.servo_ids is not None and len(set(self.servo_ids)) != self.n_joints:
            raise ValueError("servo_ids repeat an id")
        return self

    # Derived figures.

    @property
    def n_links(self) -> int:
        return self.n_joints + 1

    @property
    def body_length(self) -> float:
        """Overall length of the straight snake (m)."""
        return self.n_links * self.link_length + 2 * self.link_radius

    @property
    def mass(self) -> float:
        """Whole robot (kg)."""
        return self.n_links * self.link_mass

    @property
    def link_geoms(self) -> tuple[str, ...]:
        """MJCF names of the link capsules, head (link 1) to tail."""
        return tuple(f"link{i}" for i in range(1, self.n_links + 1))

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(f"joint{k}" for k in range(1, self.n_joints + 1))

    @property
    def joint_axes(self) -> tuple[str, ...]:
        """'pitch' or 'yaw' per joint, head to tail."""
        if self.joint_pattern == "planar":
            return ("yaw",) * self.n_joints
        return tuple("pitch" if k % 2 == 0 else "yaw" for k in range(self.n_joints))

    @property
    def body_link(self) -> tuple[int, float]:
        """(link, x along it in m) of the body frame: the middle link's centre, or the middle joint
        (the rear end of link n_links / 2) where the link count is even."""
        if self.n_links % 2:
            return (self.n_links + 1) // 2, self.link_length / 2
        return self.n_links // 2, self.link_length

    @property
    def servo_ids_or_default(self) -> tuple[int, ...]:
        return self.servo_ids if self.servo_ids is not None else tuple(range(1, self.n_joints + 1))

    @property
    def home_offsets_or_default(self) -> tuple[float, ...]:
        return self.home_offsets if self.home_offsets is not None else (0.0,) * self.n_joints

    @property
    def gravity(self) -> tuple[float, float, float]:
        """Gravity (m/s^2) in the world frame, whose floor plane stays z = 0: a slope tilts gravity
        instead of the floor, so the start pose, the contacts and the drawn grid stay as they are."""
        theta, phi = math.radians(self.slope_deg), math.radians(self.slope_direction_deg)
        down_slope = 9.81 * math.sin(theta)
        return (-down_slope * math.cos(phi), -down_slope * math.sin(phi), -9.81 * math.cos(theta))

    def servo_bandwidth_hz(self) -> float:
        """Natural frequency (Hz) of one joint under its servo alone, sqrt(kp / I) / 2 pi, with I the
        rotor armature plus the rest of the chain's inertia about the joint taken as one link's
        about its end (m L^2 / 3): the frequency above which the joint lags its command."""
        inertia = self.armature + self.link_mass * self.link_length**2 / 3
        return math.sqrt(self.servo_kp / inertia) / (2 * math.pi)

    def figures(self) -> dict[str, float | int | str]:
        """The derived figures ``snakeloco robot show`` prints."""
        return {
            "name": self.name,
            "joints": self.n_joints,
            "links": self.n_links,
            "pattern": self.joint_pattern,
            "body_length_m": round(self.body_length, 6),
            "mass_kg": round(self.mass, 6),
            "servo_bandwidth_hz": round(self.servo_bandwidth_hz(), 3),
            "stall_torque_per_body_weight_m": round(self.servo_force / (self.mass * 9.81), 4),
            "friction_anisotropy": round(self.friction_across / self.friction_along, 4),
            "physics_steps_per_command": round(1.0 / (COMMAND_RATE * self.timestep)),
            "mjcf_sha256": self.mjcf_sha256,
        }

    # The model.

    @property
    def floor_friction(self) -> list[float]:
        """A floor pair's five friction coefficients: along and across the link (the contact frame's
        first and second tangents), torsional, and rolling twice."""
        return [
            self.friction_along,
            self.friction_across,
            self.friction_torsion,
            *[self.friction_rolling] * 2,
        ]

    def build_spec(self) -> mujoco.MjSpec:
        """The robot as a ``mujoco.MjSpec``: the same elements in the same order as ``sim/snake.xml``
        for the default description, so the compiled models are equal field by field."""
        import mujoco

        spec = mujoco.MjSpec()
        spec.modelname = "snakeloco_snake"
        spec.compiler.degree = False  # radians throughout (MJCF's default is degrees)
        spec.compiler.autolimits = True
        spec.option.timestep = self.timestep
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICIT
        spec.option.gravity = self.gravity
        world = spec.worldbody
        world.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
        # The floor takes part in no default collision (contype 2 / conaffinity 2 do not match the
        # links' 1 / 1): its contacts are the anisotropic pairs below.
        world.add_geom(
            name=FLOOR,
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0, 0, 0.1],
            contype=2,
            conaffinity=2,
            rgba=[0.8, 0.8, 0.8, 1],
        )
        body_link, body_x = self.body_link
        parent = world
        for i in range(1, self.n_links + 1):
            pos = [0, 0, self.link_radius] if i == 1 else [self.link_length, 0, 0]
            body = parent.add_body(name=f"link{i}", pos=pos)
            if i == 1:
                body.add_freejoint(name="root")
            else:
                body.add_joint(
                    name=f"joint{i - 1}",
                    type=mujoco.mjtJoint.mjJNT_HINGE,
                    axis=[0, 1, 0] if self.joint_axes[i - 2] == "pitch" else [0, 0, 1],
                    armature=self.armature,
                    damping=self.joint_damping,
                    range=[-self.joint_range, self.joint_range],
                )
            body.add_geom(
                name=f"link{i}",
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                size=[self.link_radius, 0, 0],
                fromto=[0, 0, 0, self.link_length, 0, 0],
                mass=self.link_mass,
                contype=1,
                conaffinity=1,
                rgba=[0.85, 0.55, 0.2, 1],
            )
            if i == body_link:
                body.add_site(name=BODY_SITE, pos=[body_x, 0, 0])
            parent = body
        for name in self.link_geoms:
            spec.add_pair(geomname1=FLOOR, geomname2=name, condim=3, friction=self.floor_friction)
        for k, joint in enumerate(self.joint_names, start=1):
            servo = spec.add_actuator(name=f"servo{k}", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            servo.set_to_position(kp=self.servo_kp, kv=self.servo_kv)
            servo.forcerange = [-self.servo_force, self.servo_force]
            servo.ctrlrange = [-self.joint_range, self.joint_range]
        sens, obj = mujoco.mjtSensor, mujoco.mjtObj
        for k, joint in enumerate(self.joint_names, start=1):
            spec.add_sensor(name=f"q{k}", type=sens.mjSENS_JOINTPOS, objtype=obj.mjOBJ_JOINT, objname=joint)
        spec.add_sensor(name="body_pos", type=sens.mjSENS_FRAMEPOS, objtype=obj.mjOBJ_SITE, objname=BODY_SITE)
        spec.add_sensor(
            name="body_quat", type=sens.mjSENS_FRAMEQUAT, objtype=obj.mjOBJ_SITE, objname=BODY_SITE
        )
        # Whole-robot centre of mass and its velocity: used only to detect a snake thrown into the air.
        spec.add_sensor(name="com_pos", type=sens.mjSENS_SUBTREECOM, objtype=obj.mjOBJ_BODY, objname="link1")
        spec.add_sensor(
            name="com_vel", type=sens.mjSENS_SUBTREELINVEL, objtype=obj.mjOBJ_BODY, objname="link1"
        )
        return spec

    def compile(self) -> mujoco.MjModel:
        """A fresh MjModel of this robot (each caller gets its own, so threads never share one)."""
        return self.build_spec().compile()

    def mjcf(self) -> str:
        """The robot as MJCF text (MuJoCo's own writer)."""
        spec = self.build_spec()
        spec.compile()  # to_xml writes a compiled spec
        return spec.to_xml()

    @property
    def mjcf_sha256(self) -> str:
        """Hash of the physics this description builds: of ``sim/snake.xml`` for the default robot (the
        hash every dataset and checkpoint before robot descriptions stored), of its MJCF text
        otherwise."""
        if self == DEFAULT_ROBOT:
            return default_mjcf_sha256()
        return _mjcf_hash(self.model_dump_json())

    def to_yaml(self) -> str:
        import yaml

        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


DEFAULT_ROBOT = Robot()
"""The paper's robot: ``sim/snake.xml``."""


def robot_from_dict(data: object, source: str = "robot") -> Robot:
    """Validate a parsed description; RobotError names ``source``, the field and the reason."""
    return validated(Robot, data, source, RobotError, "robot")


def load_robot(path: str | Path) -> Robot:
    """Read a robot description from YAML (or JSON, a subset); RobotError names the problem."""
    return robot_from_dict(read_yaml(Path(path), RobotError), str(path))


def resolve_robot(robot: Robot | str | Path | None) -> Robot:
    """A description from a Robot, a YAML path, or None (the default robot)."""
    if robot is None:
        return DEFAULT_ROBOT
    return robot if isinstance(robot, Robot) else load_robot(robot)


# The default robot's figures, for the code that has not yet been taught to read a description.
LINK_LENGTH = DEFAULT_ROBOT.link_length
"""Joint-to-joint distance along a link (m); the capsule runs from 0 to LINK_LENGTH on the link's x axis."""
LINK_RADIUS = DEFAULT_ROBOT.link_radius
"""Capsule radius (m)."""
BODY_LENGTH = DEFAULT_ROBOT.body_length
"""Overall length of the straight snake (m), used to express speeds in body lengths per second."""
JOINT_RANGE = DEFAULT_ROBOT.joint_range
"""Joint stops at +/- this angle (rad)."""
COMMAND_LIMIT = DEFAULT_ROBOT.command_limit
"""Every joint command is clipped to +/- this angle (rad), inside the joint range."""
LINK_GEOMS = DEFAULT_ROBOT.link_geoms
"""MJCF names of the link capsules, head (link 1) to tail."""


@cache
def _mjcf_hash(description_json: str) -> str:
    return hashlib.sha256(Robot.model_validate_json(description_json).mjcf().encode()).hexdigest()


@cache
def default_mjcf_sha256() -> str:
    """Hash of ``sim/snake.xml``, stored with datasets and checkpoints to catch a changed robot."""
    return hashlib.sha256(MJCF_PATH.read_bytes()).hexdigest()


def mjcf_sha256(robot: Robot | None = None) -> str:
    """Hash of a robot's physics (the default robot's: ``sim/snake.xml``'s)."""
    return (robot or DEFAULT_ROBOT).mjcf_sha256


def load_model(robot: Robot | None = None) -> mujoco.MjModel:
    """Compile a fresh MjModel of ``robot`` (the default: the paper's snake, as ``sim/snake.xml``)."""
    return (robot or DEFAULT_ROBOT).compile()
