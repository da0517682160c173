"""A measured run of the real robot: where its body went while it ran a gait (motion capture or
odometry), as the CSV a user writes.

    # gait: sidewind.csv            (optional: the gait CSV that was sent; or name it on the command line)
    time_s,x,y,yaw[,joint_1,...,joint_N]

- ``time_s``: seconds from the start of the gait's record (the exported trajectory's ``lead_in_s``:
  3 s after the lead-in began), strictly increasing, any rate; at most the 100 s record.
- ``x``, ``y`` (m) and ``yaw`` (rad, unwrapped or not) of the body frame of docs/robot.md (the middle
  link's centre) in any fixed world frame: the run is re-expressed in its first row's position and
  heading, as the simulator's body channels are in theirs at t = 0.
- ``joint_k`` (rad, optional): measured joint angles, head to tail.

A file that cannot be a run is refused with its line and the reason (``MeasuredRunError``).
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_SPEED = 5.0
"""m/s: a snake robot of this size that moves faster between two rows was not measured in metres."""
MAX_YAW_RATE = 4 * np.pi
"""rad/s between rows: faster is a yaw in degrees (or a broken tracker)."""


class MeasuredRunError(ValueError):
    """A measured-run file that cannot be: the message names the line and the reason."""


@dataclass(frozen=True)
class MeasuredRun:
    """A measured run in its start frame: ``times`` (S,) s, ``xy`` (S, 2) m, ``yaw`` (S,) rad (0 at the
    first row, unwrapped), ``joints`` (S, J) rad or None; ``gait``: the header's gait file, if any."""

    times: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    joints: np.ndarray | None
    gait: str | None
    source: str

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    @property
    def distance(self) -> float:
        """Start-to-end distance (m)."""
        return float(np.hypot(*self.xy[-1]))


def read_measured_run(text: str, source: str = "measured run", n_joints: int | None = None) -> MeasuredRun:
    """Parse and check a measured run (module docstring); ``n_joints``: the gait's joint count, which
    measured joint columns must match."""
    lines = text.splitlines()
    gait = None
    for line in lines:
        m = re.match(r"#\s*gait:\s*(\S.*)$", line.strip())
        if m:
            gait = m.group(1).strip()
    numbered = [
        (i + 1, ln.strip()) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not numbered:
        raise MeasuredRunError(f"{source}: empty: expected a header 'time_s,x,y,yaw' and rows")
    head_no, head = numbered[0]
    cols = [c.strip() for c in head.split(",")]
    if cols[:4] != ["time_s", "x", "y", "yaw"]:
        raise MeasuredRunError(
            f"{source}: line {head_no}: header must start 'time_s,x,y,yaw' (metres, radians), got '{head[:60]}'"
        )
    joint_cols = cols[4:]
    want = [f"joint_{k}" for k in range(1, len(joint_cols) + 1)]
    if joint_cols != want:
        raise MeasuredRunError(f"{source}: line {head_no}: joint columns must be {','.join(want) or 'none'}")
    if joint_cols and n_joints is not None and len(joint_cols) != n_joints:
        raise MeasuredRunError(
            f"{source}: line {head_no}: {len(joint_cols)} measured joints, but the gait has {n_joints}"
        )
    rows = numbered[1:]
    if len(rows) < 2:
        raise MeasuredRunError(f"{source}: {len(rows)} data rows: a run needs at least two")
    values = np.empty((len(rows), len(cols)))
    for r, (no, line) in enumerate(rows):
        cells = line.split(",")
        if len(cells) != len(cols):
            raise MeasuredRunError(f"{source}: line {no}: {len(cells)} values for {len(cols)} columns")
        try:
            values[r] = [float(c) for c in cells]
        except ValueError:
            raise MeasuredRunError(f"{source}: line {no}: '{line[:40]}' is not a row of numbers") from None
        if not np.isfinite(values[r]).all():
            raise MeasuredRunError(f"{source}: line {no}: not a finite number")
    t = values[:, 0]
    dt = np.diff(t)
    back = np.flatnonzero(dt <= 0)
    if back.size:
        no = rows[back[0] + 1][0]
        raise MeasuredRunError(
            f"{source}: line {no}: time {t[back[0] + 1]:g} s does not come after {t[back[0]]:g} s (timestamps go back)"
        )
    if t[0] < 0:
        raise MeasuredRunError(
            f"{source}: line {rows[0][0]}: time {t[0]:g} s is before the record starts (0)"
        )
    step = np.hypot(np.diff(values[:, 1]), np.diff(values[:, 2])) / dt
    fast = np.flatnonzero(step > MAX_SPEED)
    if fast.size:
        no = rows[fast[0] + 1][0]
        raise MeasuredRunError(
            f"{source}: line {no}: the body moves at {step[fast[0]]:.3g} m/s between rows: x and y must be "
            f"metres (millimetres?), and no snake of this kind runs faster than {MAX_SPEED:g} m/s"
        )
    yaw = np.unwrap(values[:, 3])
    turn = np.abs(np.diff(yaw)) / dt
    spin = np.flatnonzero(turn > MAX_YAW_RATE)
    if spin.size:
        no = rows[spin[0] + 1][0]
        raise MeasuredRunError(
            f"{source}: line {no}: yaw turns at {turn[spin[0]]:.3g} rad/s between rows: yaw must be radians (degrees?)"
        )
    xy = values[:, 1:3] - values[0, 1:3]
    c, s = np.cos(-yaw[0]), np.sin(-yaw[0])
    xy = xy @ np.array([[c, -s], [s, c]]).T  # into the first row's heading frame
    joints = values[:, 4:] if joint_cols else None
    return MeasuredRun(t, xy, yaw - yaw[0], joints, gait, source)


def load_measured_run(path: str | Path, n_joints: int | None = None) -> MeasuredRun:
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise MeasuredRunError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    return read_measured_run(text, str(path), n_joints)


def write_measured_run(
    run_times: np.ndarray,
    xy: np.ndarray,
    yaw: np.ndarray,
    gait: str | None = None,
    joints: np.ndarray | None = None,
) -> str:
    """A measured-run CSV (what a motion-capture script writes), e.g. for synthetic runs."""
    out = io.StringIO()
    if gait:
        out.write(f"# gait: {gait}\n")
    cols = ["time_s", "x", "y", "yaw"]
    data = [run_times[:, None], xy, yaw[:, None]]
    if joints is not None:
        cols += [f"joint_{k}" for k in range(1, joints.shape[1] + 1)]
        data.append(joints)
    out.write(",".join(cols) + "\n")
    np.savetxt(out, np.hstack(data), delimiter=",", fmt="%.9g")
    return out.getvalue()
