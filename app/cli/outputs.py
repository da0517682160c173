"""Where each command writes, checked before it starts: an evaluation or a calibration must not run
for most of an hour only to fail when it saves."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from snakeloco.app.cli import commands as c
from snakeloco.app.cli.options import Command, flag

# What each command writes: "dir" (a directory it fills) or "file"; a "file" that already exists
# where the option is also an input (--replays, --gaits: reused when present) is not written.
OUTPUTS: dict[type, dict[str, str]] = {
    c.Generate: {"out": "file"},
    c.Design: {"out": "dir"},
    c.Gait: {"out": "file"},
    c.Train: {"out": "dir"},
    c.Evaluate: {"report": "file", "replays": "file"},
    c.Calibrate: {"out": "dir", "gaits": "file"},
    c.Figures: {"out": "dir"},
    c.RobotMjcf: {"out": "file"},
    c.WorldMjcf: {"out": "file"},
    c.Export: {"out": "file"},
    c.FitRobot: {"out": "file"},
}
REUSED_WHEN_PRESENT = {"replays", "gaits"}


def output_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` (a "dir" to fill or a "file" to write) cannot be written, or None.

    Checked before a command starts, without leaving anything behind (a probe file in the nearest
    existing directory, removed at once), so that an evaluation or a calibration does not run for
    most of an hour only to fail when it saves.
    """
    path = Path(path)
    if kind == "dir" and path.exists() and not path.is_dir():
        return f"{path}: exists and is not a directory"
    if kind == "file" and path.is_dir() and path.suffix != ".zarr":  # a zarr store is a folder
        return f"{path}: is a directory, not a file"
    existing = path if kind == "dir" else path.parent
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f"{path}: {existing} is not a directory"
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".snakeloco-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"{path}: cannot write in {existing} ({exc.strerror})"
    return None


def outputs_problem(cmd: Command) -> str | None:
    """The first output path of ``cmd`` that cannot be written, naming its flag, or None."""
    for name, kind in OUTPUTS.get(type(cmd), {}).items():
        path = getattr(cmd, name)
        if path is None or (name in REUSED_WHEN_PRESENT and Path(path).is_file()):
            continue
        if isinstance(cmd, c.Export) and cmd.format == "html":
            kind = "dir"  # the html export writes a folder
        if isinstance(cmd, c.Calibrate) and cmd.physics_head and name == "gaits":
            kind = "dir"  # the physics head's replays are a folder of chunks
        problem = output_problem(path, kind)
        if problem is not None:
            return f"{flag(name)} {problem}"
    return None
