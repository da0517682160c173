"""A gait for the robot and for colleagues: ``snakeloco export GAIT.csv --format ...``.

Every format samples the one command curve the simulator replays (``sim.physics.command_rule``): the gait's
20 Hz samples joined by straight lines, periodic over the record, preceded (unless ``lead_in`` is
off) by the rule's 3 s lead-in from the straight rest pose, so a robot starts as the simulation did.
Time 0 is the start of the lead-in; the record starts at ``lead_in_s``.

- ``csv``: ``time_s,joint_1..joint_N`` at ``rate`` Hz, rad or deg, optional ``vel_1..vel_N`` columns.
- ``ros2``: a ``trajectory_msgs/JointTrajectory`` as YAML (joint names from the robot description,
  positions and velocities in rad and rad/s, ``time_from_start`` as sec/nanosec): with velocities,
  ``joint_trajectory_controller`` interpolates cubically instead of jumping in velocity.
- ``dynamixel``: goal positions in ticks (4096 per turn, 2048 at centre) per servo id, the robot's
  home offsets added: ``time_s,id_<ID>...``.
- ``gait-equation``: the gait's named parameters as YAML (a structured-family member, or a library
  gait's equation), which re-synthesise the commands to the bit; refused for any other gait.

Velocities are the slope of the command curve: a segment's own between samples, the mean of the two
segments' at a sample. Every export checks the robot's command limit and joint speed limit and
refuses with the joint, the time and the value, unless ``clip`` (then it says what it clipped).
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field

import numpy as np
import yaml

from snakeloco.app.export.gait_csv import MEMBER_KEY, GaitCSVError, read_gait_csv
from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.physics.command_rule import CommandRule, lead_in_window
from snakeloco.sim.robot.description import Robot

FORMATS = ("csv", "ros2", "dynamixel", "gait-equation", "html")
ROBOT_FORMATS: dict[str, tuple[str, str, dict]] = {
    "ROS 2 trajectory (100 Hz)": ("ros2", "yaml", {}),
    "CSV 100 Hz + velocities": ("csv", "csv", {"velocities": True}),
    "Dynamixel ticks (100 Hz)": ("dynamixel", "csv", {}),
    "Gait equation (YAML)": ("gait-equation", "yaml", {}),
}
"""The designer's Robot format choices: format, file extension and options (the CLI's defaults
otherwise: 100 Hz, rad, one record after the lead-in, refused beyond the robot's limits)."""
TICKS_PER_TURN = 4096
CENTRE_TICK = 2048
GAIT_EQUATION_SCHEMA = 1


class ExportError(ValueError):
    """The gait cannot be exported as asked: the message names the joint, the time and the value."""


@dataclass
class Trajectory:
    """Sampled commands: ``times`` (S,) s from the start of the lead-in, ``positions`` and
    ``velocities`` (S, J) in rad and rad/s, and what clipping changed (empty: nothing)."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    lead_in_s: float
    clipped: list[str] = field(default_factory=list)


def command_curve(commands: np.ndarray, periods: int, lead_in: bool, rule: CommandRule) -> np.ndarray:
    """The knots of the command curve at 20 Hz: the faded lead-in then ``periods`` records, plus the
    closing knot (the first sample again: the curve is periodic), (K + 1, J) rad."""
    pre = (
        commands[len(commands) - rule.lead_in :] * lead_in_window(rule)[:, None] if lead_in else commands[:0]
    )
    return np.concatenate([pre, np.tile(commands, (periods, 1)), commands[:1]])


def sample_curve(knots: np.ndarray, rate: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (S, J) and velocities (S, J) of the piecewise-linear curve through ``knots`` (20 Hz
    from t = 0) at ``count`` samples of ``rate`` Hz from t = 0. Sample j sits at x = 20 j / rate
    knots (computed from integers, so a sample on a knot is that knot to the bit)."""
    x = (np.arange(count) * RECORD.sample_rate) / rate
    n = np.minimum(np.floor(x).astype(int), len(knots) - 2)  # segment index
    frac = (x - n)[:, None]
    slope = np.diff(knots, axis=0) * RECORD.sample_rate  # (K, J) rad/s of each segment
    positions = knots[n] + (knots[n + 1] - knots[n]) * frac
    velocities = slope[n].copy()
    at_knot = (frac[:, 0] == 0) & (n > 0)
    velocities[at_knot] = 0.5 * (slope[n[at_knot] - 1] + slope[n[at_knot]])
    return positions, velocities


def _refuse(bad: np.ndarray, clip: bool, why) -> None:
    """ExportError at the first (sample n, joint k) of ``bad`` (S, J), unless ``clip``: 'joint_K at
    t = T s: ' and ``why(n, k)``."""
    if bad.any() and not clip:
        n, k = np.argwhere(bad)[0]
        raise ExportError(f"joint_{k + 1} at t = {n / RECORD.sample_rate:.2f} s: {why(n, k)}")


def trajectory(
    commands: np.ndarray,
    robot: Robot,
    rate: float = RECORD.sample_rate,
    periods: int = 1,
    lead_in: bool = True,
    clip: bool = False,
    rule: CommandRule | None = None,
) -> Trajectory:
    """The command curve of ``commands`` (T, J) rad sampled at ``rate`` Hz, checked against ``robot``.

    Raises ExportError where a command passes the robot's command limit or the curve passes its joint
    speed limit (unless ``clip``: then the positions are clipped to the limit and a slew-rate limit
    applied in time order, and ``clipped`` says where and by how much).
    """
    rule = rule or CommandRule()
    commands = np.asarray(commands, np.float64)
    if commands.shape[1] != robot.n_joints:
        raise ExportError(f"the gait has {commands.shape[1]} joints, the robot {robot.name} {robot.n_joints}")
    if not 0 < rate <= 1000:
        raise ExportError(f"rate {rate} Hz: choose 1-1000 Hz")
    knots = command_curve(commands, periods, lead_in, rule)
    lead_in_s = (rule.lead_in if lead_in else 0) / RECORD.sample_rate
    count = round((len(knots) - 1) * rate / RECORD.sample_rate)
    times = np.arange(count) / rate
    clipped: list[str] = []
    limit, speed = robot.command_limit, robot.joint_speed_limit
    over = np.abs(knots) > limit + 1e-12
    _refuse(
        over,
        clip,
        lambda n, k: (
            f"{knots[n, k]:+.4f} rad is beyond the robot's command limit +/-{limit} rad (joint range "
            f"+/-{robot.joint_range} rad); --clip clips it"
        ),
    )
    if over.any():
        for k in np.flatnonzero(over.any(axis=0)):
            worst = float(np.abs(knots[:, k]).max() - limit)
            clipped.append(
                f"joint_{k + 1}: {int(over[:, k].sum())} samples clipped to +/-{limit} rad (by up to {worst:.4f} rad)"
            )
        knots = np.clip(knots, -limit, limit)
    slope = np.abs(np.diff(knots, axis=0)) * RECORD.sample_rate
    fast = slope > speed * (1 + 1e-9)
    _refuse(
        fast,
        clip,
        lambda n, k: (
            f"{slope[n, k]:.2f} rad/s is beyond the robot's joint speed limit {speed} rad/s; --clip slows it"
        ),
    )
    if fast.any():
        step = speed / RECORD.sample_rate
        limited = knots.copy()
        for n in range(1, len(limited)):
            limited[n] = limited[n - 1] + np.clip(knots[n] - limited[n - 1], -step, step)
        for k in np.flatnonzero(fast.any(axis=0)):
            worst = float(np.abs(limited[:, k] - knots[:, k]).max())
            clipped.append(
                f"joint_{k + 1}: {int(fast[:, k].sum())} segments slowed to {speed} rad/s (lagging by up to {worst:.4f} rad)"
            )
        knots = limited
    positions, velocities = sample_curve(knots, rate, count)
    return Trajectory(times, positions, velocities, lead_in_s, clipped)


# --- writers and readers ---------------------------------------------------------------------------


def _header(lines: dict[str, str]) -> str:
    return "".join(f"# {k}: {v}\n" for k, v in lines.items())


def write_csv(
    traj: Trajectory, units: str = "rad", velocities: bool = False, about: dict | None = None
) -> str:
    """``time_s,joint_1..`` (and ``vel_1..``) at the trajectory's rate, in ``units`` (rad or deg)."""
    scale = 1.0 if units == "rad" else 180.0 / math.pi
    n_joints = traj.positions.shape[1]
    cols = ["time_s", *(f"joint_{k}" for k in range(1, n_joints + 1))]
    data = [traj.times[:, None], traj.positions * scale]
    if velocities:
        cols += [f"vel_{k}" for k in range(1, n_joints + 1)]
        data.append(traj.velocities * scale)
    head = {
        "snakeloco export": f"csv, joint angles in {units}"
        + (f", velocities in {units}/s" if velocities else ""),
        "lead-in": f"t = 0 is the straight rest pose; the record starts at {traj.lead_in_s:g} s",
        **(about or {}),
        **({"clipped": "; ".join(traj.clipped)} if traj.clipped else {}),
    }
    out = io.StringIO()
    out.write(_header(head) + ",".join(cols) + "\n")
    np.savetxt(out, np.hstack(data), delimiter=",", fmt="%.17g")
    return out.getvalue()


def read_csv(text: str) -> tuple[np.ndarray, np.ndarray, str]:
    """An exported csv back: times (S,), positions (S, J) in rad, and the units it was written in."""
    units = "deg" if "joint angles in deg" in text.split("\n", 1)[0] else "rad"
    rows = [line for line in text.splitlines() if line and not line.startswith("#")]
    cols = rows[0].split(",")
    values = np.loadtxt(io.StringIO("\n".join(rows[1:])), delimiter=",", ndmin=2)
    joints = [i for i, c in enumerate(cols) if c.startswith("joint_")]
    scale = 1.0 if units == "rad" else math.pi / 180.0
    return values[:, 0], values[:, joints] * scale, units


def write_ros2(traj: Trajectory, robot: Robot, about: dict | None = None) -> str:
    """A ``trajectory_msgs/JointTrajectory`` as YAML (``ros2 topic pub`` and launch files take it)."""
    points = []
    for t, p, v in zip(traj.times, traj.positions, traj.velocities, strict=True):
        sec = math.floor(t + 1e-12)
        points.append(
            {
                "positions": [float(x) for x in p],
                "velocities": [float(x) for x in v],
                "time_from_start": {"sec": int(sec), "nanosec": round((t - sec) * 1e9)},
            }
        )
    head = {
        "snakeloco export": "ros2 trajectory_msgs/JointTrajectory, rad and rad/s",
        "lead-in": f"t = 0 is the straight rest pose; the record starts at {traj.lead_in_s:g} s",
        **(about or {}),
        **({"clipped": "; ".join(traj.clipped)} if traj.clipped else {}),
    }
    msg = {"header": {"frame_id": ""}, "joint_names": list(robot.joint_names), "points": points}
    return _header(head) + yaml.safe_dump(msg, sort_keys=False, default_flow_style=None, width=1 << 16)


def read_ros2(text: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A JointTrajectory YAML back: times (S,) s, positions (S, J) rad, joint names."""
    msg = yaml.safe_load(text)
    times = np.array(
        [p["time_from_start"]["sec"] + p["time_from_start"]["nanosec"] * 1e-9 for p in msg["points"]]
    )
    return times, np.array([p["positions"] for p in msg["points"]]), msg["joint_names"]


def to_ticks(positions: np.ndarray, robot: Robot) -> np.ndarray:
    """Joint angles (S, J) rad -> goal positions in ticks (int), home offsets added; ExportError
    where one leaves the servo's 0..4095."""
    ticks = np.rint(
        CENTRE_TICK + (positions + robot.home_offsets_or_default) * TICKS_PER_TURN / (2 * math.pi)
    )
    bad = np.argwhere((ticks < 0) | (ticks >= TICKS_PER_TURN))
    if len(bad):
        s, k = bad[0]
        raise ExportError(f"joint_{k + 1}: goal position {int(ticks[s, k])} ticks leaves the servo's 0..4095")
    return ticks.astype(int)


def from_ticks(ticks: np.ndarray, robot: Robot) -> np.ndarray:
    """Goal positions in ticks -> joint angles (rad)."""
    return (np.asarray(ticks) - CENTRE_TICK) * (2 * math.pi / TICKS_PER_TURN) - np.asarray(
        robot.home_offsets_or_default
    )


def write_dynamixel(traj: Trajectory, robot: Robot, about: dict | None = None) -> str:
    """Goal positions in ticks per servo id at the trajectory's rate: ``time_s,id_<ID>...``."""
    ticks = to_ticks(traj.positions, robot)
    head = {
        "snakeloco export": "dynamixel goal positions (ticks: 4096 per turn, 2048 at joint angle 0 "
        "plus the home offset), one column per servo id, for a sync write each row",
        "home offsets (rad)": json.dumps(list(robot.home_offsets_or_default)),
        "lead-in": f"t = 0 is the straight rest pose; the record starts at {traj.lead_in_s:g} s",
        **(about or {}),
        **({"clipped": "; ".join(traj.clipped)} if traj.clipped else {}),
    }
    out = io.StringIO()
    out.write(_header(head) + ",".join(["time_s", *(f"id_{i}" for i in robot.servo_ids_or_default)]) + "\n")
    for t, row in zip(traj.times, ticks, strict=True):
        out.write(f"{t:.6f}," + ",".join(map(str, row)) + "\n")
    return out.getvalue()


def read_dynamixel(text: str) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """A dynamixel export back: times (S,), ticks (S, J) int, servo ids."""
    rows = [line for line in text.splitlines() if line and not line.startswith("#")]
    ids = [int(c.removeprefix("id_")) for c in rows[0].split(",")[1:]]
    values = np.loadtxt(io.StringIO("\n".join(rows[1:])), delimiter=",", ndmin=2)
    return values[:, 0], values[:, 1:].astype(int), ids


def gait_equation_of(text: str, robot: Robot) -> dict:
    """The named parameters behind a gait CSV: ``{"member": ...}`` (a structured-family member) or
    ``{"library": NAME, "gait_equation": ...}``; ExportError for a gait that is neither (or whose
    commands are not its parameters' to the bit: an edited file)."""
    from snakeloco.app.export.gait_csv import read_member
    from snakeloco.sim.gaits.library import PRESETS, GaitEquation

    commands = read_gait_csv(text, robot, limit=np.inf).commands
    member = read_member(text)
    if member is not None:
        params, synthesised = {"member": member.params()}, member.commands(robot)
    else:
        library = next((n for n in PRESETS if f"# snakeloco gait: library gait {n}:" in text), None)
        if library is None:
            raise ExportError(
                "this gait is not a member of the structured family nor a library gait (its header "
                f"has no '# {MEMBER_KEY}:' line): its commands have no gait-equation parameters; export "
                "it as csv, ros2 or dynamixel"
            )
        gait = PRESETS[library].gait.on_robot(robot)
        params, synthesised = {"library": library, "gait_equation": gait.model_dump()}, gait.commands(robot)
        GaitEquation.model_validate(params["gait_equation"])
    if not np.array_equal(synthesised, commands):
        raise ExportError(
            "the file's commands are not its parameters' (edited after export?): export it as csv"
        )
    return params


EQUATION = (
    "pitch joints (odd k): u_k(t) = a_pitch sin(nu_pitch k + 2 pi frequency t); yaw joints (even k): "
    "u_k(t) = a_yaw sin(nu_yaw k + 2 pi frequency t + delta); k = 1..N from the head; a member adds a "
    "curve wave of the same form and a steering wave steering_amplitude cos(2 pi 0.05 t + "
    "steering_phase) on the yaw joints, then clips to the command limit (sim/gaits/members.py)"
)


def write_gait_equation(params: dict, robot: Robot) -> str:
    """The parameters as YAML, with the equation they are read by."""
    doc = {
        "snakeloco_gait_equation": GAIT_EQUATION_SCHEMA,
        "units": "rad, rad per module, Hz",
        "equation": EQUATION,
        "robot": robot.name,
        "joint_pattern": robot.joint_pattern,
        **params,
    }
    return yaml.safe_dump(doc, sort_keys=False, width=100)


def read_gait_equation(text: str, robot: Robot) -> np.ndarray:
    """A gait-equation YAML back to its commands (T, J) rad on ``robot``, to the bit."""
    from snakeloco.sim.gaits.library import GaitEquation
    from snakeloco.sim.gaits.members import Member

    doc = yaml.safe_load(text)
    if not isinstance(doc, dict) or doc.get("snakeloco_gait_equation") != GAIT_EQUATION_SCHEMA:
        raise GaitCSVError("not a snakeloco gait-equation file (no 'snakeloco_gait_equation: 1')")
    if "member" in doc:
        return Member.model_validate(doc["member"]).commands(robot)
    return GaitEquation.model_validate(doc["gait_equation"]).commands(robot)


def export_gait(
    text: str,
    fmt: str,
    robot: Robot,
    rate: float = 100.0,
    units: str = "rad",
    velocities: bool = False,
    periods: int = 1,
    lead_in: bool = True,
    clip: bool = False,
    source: str = "gait",
) -> tuple[str, list[str]]:
    """A gait CSV's text in format ``fmt`` (any but html): (the file's text, what was clipped).
    GaitCSVError or ExportError say why it cannot be."""
    table = read_gait_csv(text, robot, limit=np.inf)  # ``trajectory`` checks the limits, saying where
    if units == "deg" and fmt != "csv":
        raise ExportError(f"degrees are for the csv format; {fmt} has its own units")
    if fmt == "gait-equation":
        return write_gait_equation(gait_equation_of(text, robot), robot), []
    traj = trajectory(table.commands, robot, rate, periods, lead_in, clip)
    about = {"gait": source, "robot": robot.name}
    if fmt == "csv":
        return write_csv(traj, units, velocities, about), traj.clipped
    if fmt == "ros2":
        return write_ros2(traj, robot, about), traj.clipped
    if fmt == "dynamixel":
        return write_dynamixel(traj, robot, about), traj.clipped
    raise ExportError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")
