"""Gait CSV files: what "Export CSV" writes and "Import CSV" accepts.

Format: optional ``#`` comment lines (export writes z_B, the z_k mode and seed, the slider values
along a cluster's axes, the structured family member as JSON (``# member:``, whose parameters give the
commands to the bit: ``read_member``), the checkpoint hash and the consistency figures there; import
ignores them), then the header
``time_s,joint_1,...,joint_N`` and exactly 2000 rows at a 0.05 s step starting at 0: time (s) and
the robot's N joint commands (rad) within its command limit (the default robot: 8 joints, +/-2.2
rad). No other columns; a file of another joint count than the robot's is refused saying so. Numbers are written in Python's
shortest round-trip form, so an exported gait re-imports to the very same float64 commands, and
is replayed exactly as written under the command rule of ``sim.physics.simulator``.
"""

from __future__ import annotations

import io
import json
import re

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

from snakeloco.sim import RECORD
from snakeloco.sim.physics.body import heading_text
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.scores.consistency import PREDICTABLE

N_ROWS = RECORD.n_samples
"""One record: 2000 rows."""
TIME_STEP = 1.0 / RECORD.sample_rate
"""0.05 s between rows (20 Hz)."""


def header(n_joints: int) -> list[str]:
    """The CSV columns of a robot of ``n_joints`` joints: time_s, joint_1, ..., joint_N."""
    return ["time_s", *[f"joint_{k}" for k in range(1, n_joints + 1)]]


MAX_BYTES = 2 * 2**20
"""Largest accepted upload: a 2000-row gait written at full precision is ~0.4 MB."""


EXPORT_FIGURES = ("final_spread", *(f"{k}_err" for k in PREDICTABLE), "xy_r2")
"""Consistency figures an exported CSV records in its comments."""


MEMBER_KEY = "member"
"""The comment that carries a structured-family gait's parameters (JSON of ``sim.gaits.members.Member``):
``Member.model_validate_json`` of it re-synthesises the file's commands to the bit."""


class GaitCSVError(ValueError):
    """The file is not a valid gait CSV; the message says what is wrong and where."""


class GaitTable(BaseModel):
    """A parsed gait: validated commands (2000, N) rad at 20 Hz (their range is checked against a
    robot by ``check_range``)."""

    model_config = ConfigDict(arbitrary_types_allowed=True, frozen=True)

    time_s: np.ndarray
    commands: np.ndarray

    @field_validator("time_s")
    @classmethod
    def _time_grid(cls, t: np.ndarray) -> np.ndarray:
        if t.shape != (N_ROWS,):
            raise ValueError(f"expected {N_ROWS} rows, got {t.shape[0]}")
        expected = np.arange(N_ROWS) * TIME_STEP
        bad = np.flatnonzero(np.abs(t - expected) > 1e-6)
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"time_s must start at 0 and step by {TIME_STEP} s: row {i + 1} has {float(t[i])!r}, expected {expected[i]:.2f}"
            )
        return t

    @field_validator("commands")
    @classmethod
    def _shape(cls, u: np.ndarray) -> np.ndarray:
        if u.ndim != 2 or u.shape[0] != N_ROWS or u.shape[1] < 1:
            raise ValueError(f"expected ({N_ROWS}, N) joint commands, got {u.shape}")
        return u


def check_range(u: np.ndarray, robot: Robot, limit: float | None = None) -> None:
    """A ValueError unless commands (2000, N) are ``robot``'s: N joints, within its command limit
    (or ``limit``)."""
    if u.shape[1] != robot.n_joints:
        raise ValueError(
            f"a gait of {u.shape[1]} joints for robot {robot.name} of {robot.n_joints}: export it for this "
            "robot (its checkpoint), or pick the robot it was made for"
        )
    limit = robot.command_limit if limit is None else limit
    out = np.flatnonzero(np.abs(u).max(axis=1) > limit + 1e-9)
    if out.size:
        i = int(out[0])
        k = int(np.argmax(np.abs(u[i])))
        raise ValueError(
            f"joint_{k + 1} = {u[i, k]:.4g} rad in row {i + 1} is outside the +/-{limit} rad "
            f"command range ({out.size} rows out of range)"
        )


def _fmt(x: float) -> str:
    return repr(float(x))


def write_gait_csv(commands: np.ndarray, comments: dict[str, str] | None, robot: Robot) -> str:
    """CSV text of ``robot``'s commands (2000, N) rad, with ``# key: value`` comment lines first."""
    commands = np.asarray(commands, dtype=np.float64)
    GaitTable(time_s=np.arange(N_ROWS) * TIME_STEP, commands=commands)  # validate before writing
    check_range(commands, robot)
    out = io.StringIO()
    for key, value in (comments or {}).items():
        for line in str(value).splitlines() or [""]:
            out.write(f"# {key}: {line}\n")
    out.write(",".join(header(robot.n_joints)) + "\n")
    for n in range(N_ROWS):
        out.write(_fmt(round(n * TIME_STEP, 10)) + "," + ",".join(_fmt(v) for v in commands[n]) + "\n")
    return out.getvalue()


def read_gait_csv(data: bytes | str, robot: Robot, limit: float | None = None) -> GaitTable:
    """Parse and validate a gait CSV of ``robot`` (its joint count and command limit, or ``limit``:
    ``np.inf`` for a caller that checks the range itself, saying where); raise GaitCSVError naming
    the problem."""
    if isinstance(data, bytes):
        if len(data) > MAX_BYTES:
            raise GaitCSVError(
                f"file is {len(data) / 2**20:.1f} MiB; a gait CSV is at most {MAX_BYTES / 2**20:.0f} MiB"
            )
        if b"\x00" in data:
            raise GaitCSVError("file is binary, not a CSV text file")
        try:
            text = data.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise GaitCSVError(f"file is not UTF-8 text (byte {exc.start})") from exc
    else:
        text = data
    lines = [(i + 1, line.strip()) for i, line in enumerate(text.splitlines())]
    lines = [(i, line) for i, line in lines if line and not line.startswith("#")]
    if not lines:
        raise GaitCSVError(
            f"file is empty: expected a header 'time_s,joint_1,...,joint_{robot.n_joints}' and 2000 rows"
        )
    header_line, text_header = lines[0]
    columns = [c.strip() for c in text_header.split(",")]
    want = header(robot.n_joints)
    if columns != want:
        if len(columns) == 1 and any(d in text_header for d in (";", "\t", "|")):
            raise GaitCSVError(
                f"line {header_line}: columns must be separated by commas, got '{text_header[:60]}'"
            )
        n = len(columns) - 1
        missing = [c for c in want if c not in columns]
        if n >= 4 and columns == header(n):  # a robot of 4-32 joints
            raise GaitCSVError(
                f"line {header_line}: a gait of {n} joints"
                + (f" (missing {missing})" if missing else "")
                + f"; robot {robot.name} has {robot.n_joints} (a gait exported for another robot: "
                "open it with that robot's checkpoint)"
            )
        extra = [c for c in columns if c not in want]
        raise GaitCSVError(
            f"line {header_line}: header must be '{','.join(want)}'"
            + (f"; missing {missing}" if missing else "")
            + (f"; unexpected {extra}" if extra else "")
            + ("; columns out of order" if not missing and not extra else "")
        )
    rows = lines[1:]
    if not rows:
        raise GaitCSVError(f"header only: expected {N_ROWS} data rows")
    if len(rows) != N_ROWS:
        raise GaitCSVError(f"expected {N_ROWS} data rows (100 s at 20 Hz), got {len(rows)}")
    try:  # numpy parses the rows; only a file it refuses is read again, cell by cell, to say where
        values = np.loadtxt(io.StringIO("\n".join(line for _, line in rows)), delimiter=",", ndmin=2)
    except ValueError:
        values = None
    if values is None or values.shape[1] != len(want):
        raise GaitCSVError(_first_bad_cell(rows, want))
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        r, c = bad[0]
        cell = rows[r][1].split(",")[c].strip()
        raise GaitCSVError(f"line {rows[r][0]}, column {want[c]}: {cell} is not a finite number")
    try:
        table = GaitTable(time_s=values[:, 0], commands=values[:, 1:])
        check_range(table.commands, robot, limit)
        return table
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        errors = getattr(exc, "errors", None)
        msg = "; ".join(e["msg"].removeprefix("Value error, ") for e in errors()) if errors else str(exc)
        raise GaitCSVError(msg) from None


def _first_bad_cell(rows: list[tuple[int, str]], columns: list[str]) -> str:
    """What is wrong with the first row or cell that is not a number (``rows``: line number, text)."""
    for line_no, line in rows:
        cells = line.split(",")
        if len(cells) != len(columns):
            return f"line {line_no}: expected {len(columns)} values, got {len(cells)}"
        for column, cell in zip(columns, cells, strict=True):
            try:
                float(cell)
            except ValueError:
                return f"line {line_no}, column {column}: '{cell.strip()[:30]}' is not a number"
    return "the rows are not a table of numbers"


def gait_comments(
    gait, sim, checkpoint_sha256: str, encoded_z: tuple[float, ...] | None = None
) -> dict[str, str]:
    """The comment lines Export CSV writes above a gait: where it came from (z_B and the z_k mode, or
    the imported file and where it encodes), the checkpoint, and its consistency figures.

    ``gait``: the tab's ``DecodedGait``; ``sim``: its ``SimulatedGait`` or None.
    """
    comments = {"snakeloco gait": "commands (rad) at 20 Hz, replay with `snakeloco` or sim.physics.replay"}
    if gait.latents is not None:
        lat = gait.latents
        comments["z_B"] = "[" + ", ".join(repr(float(v)) for v in lat.z_b) + "]"  # exact: import restores it
        if lat.axes is not None:  # sliders along a cluster's axes (``model.heads.density``)
            comments["sliders"] = (
                "[" + ", ".join(f"{v:.4f}" for v in lat.axes) + f"] in cluster {lat.component + 1}"
            )
        comments["z_k mode"] = lat.zk_mode + (
            f" (seed {lat.seed}, temperature {lat.temperature})" if lat.zk_mode == "sampled" else ""
        )
    else:
        comments["source"] = gait.source
        if encoded_z is not None:
            comments["z_B (encoded)"] = "[" + ", ".join(f"{v:.4f}" for v in encoded_z) + "]"
    if getattr(gait, "member", None) is not None:
        comments["gait"] = gait.member.describe()
        comments[MEMBER_KEY] = json.dumps(gait.member.params(), separators=(",", ":"))
    comments["checkpoint sha256"] = checkpoint_sha256
    if sim is not None and sim.figures:
        f = sim.figures
        comments["consistency"] = ", ".join(f"{k} {f[k]:.4g}" for k in EXPORT_FIGURES if k in f)
    return comments


def library_gait_csv(name: str, robot: Robot) -> str:
    """The library gait ``name`` (``sim.gaits.library.PRESETS``) on ``robot`` as gait CSV text, its equation
    and measured figures in the comments. On another robot than the paper's the gait is carried
    there by the serpenoid rule (``GaitEquation.on_robot``), and the comments say its figures were
    measured on the paper's robot."""
    from snakeloco.sim.gaits.library import PRESETS

    preset = PRESETS[name]
    gait, m = preset.gait.on_robot(robot), preset.measured
    measured = (
        f"distance {m.displacement:.2f} m in 100 s ({m.body_lengths_per_s:.3f} body lengths/s), "
        f"direction of travel {m.direction_deg:+.0f}°, heading change {heading_text(np.degrees(m.net_yaw))}, "
        f"straightness {m.straightness:.2f}, net roll {m.net_roll:.2f} rad, ensemble spread {m.spread:.3f}"
    )
    comments = {
        "snakeloco gait": f"library gait {name}: {preset.about}",
        "gait equation": ", ".join(f"{k} {v:g}" for k, v in gait.model_dump().items()),
        "measured": measured
        if gait is preset.gait
        else f"on the paper's 8-joint robot: {measured}; "
        f"carried to {robot.name} by the serpenoid rule (docs/robot.md), not measured there",
    }
    return write_gait_csv(gait.commands(robot), comments, robot)


def exported_latents(text: str) -> tuple[dict | None, str]:
    """Where a gait CSV says it came from in its comments (Export CSV's ``gait_comments``): its z_B,
    z_k mode, seed and temperature and the checkpoint's hash, or None and why not in words."""
    found = {}
    for line in text.splitlines():
        if not line.startswith("# "):
            continue
        key, _, value = line[2:].partition(": ")
        found.setdefault(key, value.strip())
    if "z_B" not in found:
        return None, "the file names no z_B (a library gait, a design candidate or a hand-written file)"
    try:
        z_b = tuple(float(v) for v in found["z_B"].strip("[]").split(","))
    except ValueError:
        return None, f"its '# z_B:' comment is not a list of numbers ({found['z_B'][:40]})"
    mode = found.get("z_k mode", "zero")
    latents = {
        "z_b": z_b,
        "zk_mode": "zero",
        "seed": 0,
        "temperature": 1.0,
        "checkpoint": found.get("checkpoint sha256"),
    }
    if mode.startswith("sampled"):
        m = re.fullmatch(r"sampled \(seed (\d+), temperature ([-+0-9.eE]+)\)", mode)
        try:
            numbers = [float(v) for v in m.groups()] if m else []
        except ValueError:
            numbers = []
        if len(numbers) != 2:
            return None, f"its '# z_k mode:' comment is not one Export CSV writes ({mode[:40]})"
        latents |= {"zk_mode": "sampled", "seed": int(numbers[0]), "temperature": numbers[1]}
    return latents, ""


def comment(text: str, key: str) -> str | None:
    """The value of a gait CSV's first ``# key: value`` comment, or None without one."""
    for line in text.splitlines():
        if line.startswith(f"# {key}: "):
            return line[len(key) + 4 :]
    return None


def _comment_model(text: str, key: str, model, what: str):
    """The pydantic ``model`` a ``# key:`` comment holds as JSON, or None; GaitCSVError names it."""
    from pydantic import ValidationError

    value = comment(text, key)
    if value is None:
        return None
    try:
        return model.model_validate_json(value)
    except ValidationError as exc:
        raise GaitCSVError(f"the '# {key}:' comment is not {what}: {exc}") from None


def read_member(text: str):
    """The ``sim.gaits.members.Member`` a gait CSV's ``# member:`` comment names, or None without one;
    GaitCSVError where it is not a valid member's parameters."""
    from snakeloco.sim.gaits.members import Member

    return _comment_model(text, MEMBER_KEY, Member, "a gait's parameters")


PATH_KEY = "closed loop path"
"""The comment of a closed-loop design candidate (JSON ``{"until": n, "turn_deg": a}``): its loop
follows its nominal path's first n + 1 points, turned by a degrees about the record's start, and
stops there (``model.design.closed_loop``; ``export --format controller`` writes that path)."""
STEERING_KEY = "steering"
"""The comment that carries a gait's steering input (JSON of ``sim.control.Steering``), as measured by
``sim.control.find.find_steering`` for the robot it was found on."""


def read_steering(text: str):
    """The ``sim.control.Steering`` a gait CSV's ``# steering:`` comment names, or None without one;
    GaitCSVError where it is not a steering input."""
    from snakeloco.sim.control import Steering

    return _comment_model(text, STEERING_KEY, Steering, "a steering input")


def read_closed_loop_path(text: str) -> dict | None:
    """A gait CSV's ``# closed loop path:`` (``PATH_KEY``) as ``{"until": int, "turn_deg": float}``, or None."""
    value = comment(text, PATH_KEY)
    if value is None:
        return None
    try:
        found = json.loads(value)
        return {"until": int(found["until"]), "turn_deg": float(found["turn_deg"])}
    except (ValueError, KeyError, TypeError):
        raise GaitCSVError(f'the \'# {PATH_KEY}:\' comment is not {{"until": n, "turn_deg": a}}') from None
