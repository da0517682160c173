"""The snake's anisotropic floor friction on any ground (docs/terrain.md).

The robot's floor pairs give friction (along, across) on a contact frame's two tangent axes. Only
MuJoCo's capsule-plane collider orients that frame along the capsule (MuJoCo issue #67); on a
heightfield or a box the tangents follow from the normal alone and the links' anisotropy is lost. A
model whose floor pairs name such a ground geom is stepped here with each ground contact's frame turned
about its normal to lie along its link, after collision and before the constraints are built from it.

``rollout`` is ``mujoco.rollout``'s call for one row or many: a model with nothing to re-align (the
plane) goes to MuJoCo's own rollout untouched, so the default world's replays stay bit-identical; a
world's model runs the staged step natively (``ground_contact.c``, compiled on first use with the
installed mujoco wheel's headers and called through ctypes, which releases the GIL) or, without a C
compiler, the same step in numpy (slower; said once in the log). ``SNAKELOCO_GROUND_STEP=numpy``
picks the numpy step.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_suffix(".c")
_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


def ground_flags(model: mujoco.MjModel) -> np.ndarray | None:
    """(ngeom,) uint8: 1 on the static, non-plane geoms of the model's contact pairs (a world's rough
    ground and steps), whose contacts need re-aligning; None where there are none (the plane)."""
    if model.npair == 0:
        return None
    paired = np.unique(np.concatenate([model.pair_geom1, model.pair_geom2]))
    static = model.geom_bodyid[paired] == 0
    off_plane = model.geom_type[paired] != mujoco.mjtGeom.mjGEOM_PLANE
    grounds = paired[static & off_plane]
    if len(grounds) == 0:
        return None
    flags = np.zeros(model.ngeom, dtype=np.uint8)
    flags[grounds] = 1
    return flags


def realign(data: mujoco.MjData, flags: np.ndarray) -> int:
    """Turn each ground contact's tangent axes about its normal so that the first lies along the link's
    capsule axis (numpy; ``ground_contact.c`` does the same natively). Returns the contacts changed."""
    n = data.ncon
    if n == 0:
        return 0
    con = data.contact[:n]
    g1, g2 = con.geom[:, 0], con.geom[:, 1]
    on1, on2 = flags[g1] == 1, flags[g2] == 1
    rows = np.flatnonzero(on1 | on2)
    if len(rows) == 0:
        return 0
    links = np.where(on1[rows], g2[rows], g1[rows])
    axes = data.geom_xmat[links].reshape(-1, 3, 3)[:, :, 2]  # a capsule's axis is its frame's z
    frames = con.frame[rows].reshape(-1, 3, 3)
    normal = frames[:, 0]
    along = axes - (axes * normal).sum(axis=1, keepdims=True) * normal
    norm = np.linalg.norm(along, axis=1)
    keep = norm > 1e-9  # a link standing on its end keeps its frame
    rows, normal, along = rows[keep], normal[keep], along[keep] / norm[keep, None]
    frame = np.stack([normal, along, np.cross(normal, along)], axis=1).reshape(-1, 9)
    data.contact.frame[rows] = frame  # the struct array's view: written through
    return len(rows)


def staged_step(model: mujoco.MjModel, data: mujoco.MjData, flags: np.ndarray) -> None:
    """``mj_step`` (implicit integrators) with the ground contacts re-aligned before the constraints."""
    mujoco.mj_checkPos(model, data)
    mujoco.mj_checkVel(model, data)
    mujoco.mj_fwdPosition(model, data)
    if realign(data, flags):
        mujoco.mj_makeConstraint(model, data)
        mujoco.mj_island(model, data)
        mujoco.mj_projectConstraint(model, data)
    mujoco.mj_sensorPos(model, data)  # mj_forwardSkip past the position stage skips its sensors too
    mujoco.mj_forwardSkip(model, data, mujoco.mjtStage.mjSTAGE_POS, 0)
    mujoco.mj_checkAcc(model, data)
    mujoco.mj_implicit(model, data)


def _cache_dir() -> Path:
    root = os.environ.get("SNAKELOCO_CACHE") or os.environ.get("XDG_CACHE_HOME") or "~/.cache"
    return Path(root).expanduser() / "snakeloco"


@functools.cache
def native() -> ctypes.CDLL | None:
    """The compiled step (built once per source, mujoco version and Python into the user's cache), or
    None where it cannot be built here (no C compiler, no mujoco headers): then numpy steps."""
    if os.environ.get("SNAKELOCO_GROUND_STEP", "").lower() == "numpy":
        return None
    package = Path(mujoco.__file__).parent
    libs = sorted(p for p in package.glob("libmujoco*") if p.suffix in (".so", ".dylib") or ".so." in p.name)
    cc = shutil.which(os.environ.get("CC", "cc"))
    if cc is None or not libs or not (package / "include" / "mujoco" / "mujoco.h").exists():
        log.warning(
            "no C compiler or mujoco headers: terrain replays step in numpy (measured 7-10x slower than natively)"
        )
        return None
    key = hashlib.sha256(SOURCE.read_bytes() + mujoco.__version__.encode() + sys.platform.encode())
    target = _cache_dir() / f"ground_contact-{key.hexdigest()[:16]}.so"
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            built = Path(tmp) / target.name
            command = [cc, "-O2", "-shared", "-fPIC", "-I", str(package / "include"), str(SOURCE), "-o",
                       str(built), str(libs[0]), f"-Wl,-rpath,{package}", "-lm"]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode != 0:
                log.warning("terrain step not compiled (%s): stepping in numpy", done.stderr.strip()[-300:])
                return None
            os.replace(built, target)  # atomic: a second process finds the whole library or none
    lib = ctypes.CDLL(str(target))
    pointer, n = ctypes.c_void_p, ctypes.c_int
    lib.snakeloco_rollout.argtypes = [pointer, pointer, pointer, n] + [pointer] * 5
    lib.snakeloco_rollout.restype = None
    lib.snakeloco_step.argtypes = [pointer, pointer, pointer]
    lib.snakeloco_step.restype = None
    return lib


def step(model: mujoco.MjModel, data: mujoco.MjData, flags: np.ndarray) -> None:
    """One step with the ground contacts re-aligned: native where it is built, else numpy."""
    lib = native()
    if lib is None:
        staged_step(model, data, flags)
    else:
        lib.snakeloco_step(model._address, data._address, flags.ctypes.data)


def _row(model, data, flags, state0, warm0, control, state, sensordata) -> None:
    """One row as ``mujoco.rollout`` rolls it out, with the staged step (arrays: that row's)."""
    lib = native()
    if lib is not None:
        arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (state0, warm0, control)]
        out_state = state if state.flags.c_contiguous else np.empty(state.shape)
        out_sens = sensordata if sensordata.flags.c_contiguous else np.empty(sensordata.shape)
        lib.snakeloco_rollout(
            model._address, data._address, flags.ctypes.data, len(control),
            *(a.ctypes.data for a in arrays), out_state.ctypes.data, out_sens.ctypes.data,
        )  # fmt: skip
        state[:], sensordata[:] = out_state, out_sens
        return
    data.qfrc_applied[:] = 0
    data.xfrc_applied[:] = 0
    mujoco.mj_setState(model, data, state0, _STATE)
    data.qacc_warmstart[:] = warm0
    for w in data.warning:
        w.number = 0
    for t in range(len(control)):
        if not any(w.number for w in data.warning):
            data.ctrl[:] = control[t]
            staged_step(model, data, flags)
        mujoco.mj_getState(model, data, state[t], _STATE)
        sensordata[t] = data.sensordata


def rollout(
    model: mujoco.MjModel | list[mujoco.MjModel],
    data: mujoco.MjData,
    initial_state: np.ndarray,
    control: np.ndarray,
    *,
    initial_warmstart: np.ndarray,
    state: np.ndarray,
    sensordata: np.ndarray,
    runner=mj_rollout,
) -> None:
    """``runner.rollout`` (``mujoco.rollout`` or a ``Rollout``) for rows (B, ...) on ``model`` (one, or one
    per row): a model with a ground to re-align steps here, row by row on ``data``; the rest go to
    MuJoCo unchanged."""
    models = model if isinstance(model, list) else [model] * len(control)
    flags = [ground_flags(m) for m in models]
    if all(f is None for f in flags):
        runner.rollout(
            model, data, initial_state, control,
            initial_warmstart=initial_warmstart, state=state, sensordata=sensordata,
        )  # fmt: skip
        return
    for i, (m, f) in enumerate(zip(models, flags, strict=True)):
        args = (initial_state[i], initial_warmstart[i], control[i], state[i], sensordata[i])
        if f is None:
            runner.rollout(
                m, data, args[0][None], args[2][None],
                initial_warmstart=args[1][None], state=state[i : i + 1], sensordata=sensordata[i : i + 1],
            )  # fmt: skip
        else:
            _row(m, data, f, *args)
