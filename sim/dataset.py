"""Training dataset: generation (batched, deterministic, atomic) and validated loading.

File format: one ``.npz`` (uncompressed zip of ``.npy`` members), float32 unless noted:

=================  ===============  ==================================================================
key                shape            meaning
=================  ===============  ==================================================================
``commands``       (N, 2000, 8)     joint commands (rad), exactly what was simulated
``joint_angles``   (N, 2000, 8)     measured joint angles (rad) at 20 Hz
``body``           (N, 2000, 6)     body states at 20 Hz (``sim.BODY_CHANNELS``; m and rad)
``body_ds``        (N, 500, 6)      ``body[:, ::4]``: every 4th sample, 5 Hz, t = 0.2 k s
``freqs``          (L,)             excited frequencies (Hz), float64
``phases``         (N, 8, L)        multisine phases (rad), float64
``amplitude``      (N,)             shared per-component amplitude U (rad)
``attempts``       (N,)             int32: phase draws needed (1 = first draw simulated cleanly)
``shape``          (N, 8, L, 2)     single-sided FFT coefficients of ``joint_angles`` at the excited
                                    bins (real, imag; rad), ``sim.joint_shape`` of the stored angles
``meta``           ()               JSON string: schema version, generating config, mujoco version,
                                    MJCF sha256, failure log
=================  ===============  ==================================================================

A sample whose simulation breaks (diverges, is reset by MuJoCo, or throws the snake) is regenerated
with a fresh phase draw from the same deterministic stream, up to ``max_attempts`` times; every
failure is logged in ``meta["failures"]`` and counted in ``attempts``. No NaN is ever written.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from sim.excitation import ExcitationConfig, multisine, random_phases
from sim.physics import SimConfig, SimulationError, Simulator
from sim.robot import N_JOINTS, mjcf_sha256
from sim.spectra import joint_shape

SCHEMA_VERSION = 1
BODY_DOWNSAMPLE = 4
"""The model sees the body series at 20 Hz / 4 = 5 Hz (500 steps)."""
N_BODY = 6
_MEMORY_BUDGET = 512 * 2**20
"""Bytes of rollout buffers per chunk; bounds peak memory whatever the dataset size."""


class GenerateConfig(BaseModel):
    """Everything that determines a dataset's contents (worker count does not: results are identical)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    num_samples: int = Field(4096, gt=0, description="Number of records N.")
    seed: int = Field(0, ge=0, description="Seed of the phase draws; sample i, attempt a uses (seed, i, a).")
    max_attempts: int = Field(5, ge=1, description="Phase draws tried per sample before giving up.")
    excitation: ExcitationConfig = ExcitationConfig()
    sim: SimConfig = SimConfig()


class DatasetError(ValueError):
    """A dataset file is missing, truncated, foreign or of another schema; the message says which."""


def write_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Write a small side file (.npz, no pickle) atomically: to a temporary name beside ``path``,
    then renamed, so an interrupted write never leaves a truncated file that ``read_npz`` meets."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def read_npz(path: str | Path, what: str, need: Iterable[str]) -> dict[str, np.ndarray]:
    """Every array of a small side file (.npz, no pickle) the tools write: ``what`` names the kind
    in the messages; a file that cannot be read, or lacks an array of ``need``, is a DatasetError."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such {what} file")
    if not zipfile.is_zipfile(path):  # np.load would call a text file "pickled (object) data"
        raise DatasetError(f"{path}: not a {what} .npz (no zip archive inside: truncated or another format)")
    try:
        with np.load(path, allow_pickle=False) as f:
            stored = {k: f[k] for k in f.files}
    except Exception as exc:  # zip, header or pickle errors all mean the same to the user
        raise DatasetError(f"{path}: not a readable {what} .npz ({exc})") from exc
    missing = [k for k in need if k not in stored]
    if missing:
        raise DatasetError(f"{path}: not a {what} file (missing arrays {missing})")
    return stored


@dataclass(frozen=True)
class _Member:
    shape: tuple[int | str, ...]
    dtype: str


def _members(cfg: GenerateConfig) -> dict[str, _Member]:
    t, n_l = cfg.excitation.n_samples, cfg.excitation.n_components
    n = cfg.num_samples
    return {
        "commands": _Member((n, t, N_JOINTS), "float32"),
        "joint_angles": _Member((n, t, N_JOINTS), "float32"),
        "body": _Member((n, t, N_BODY), "float32"),
        "body_ds": _Member((n, -(-t // BODY_DOWNSAMPLE), N_BODY), "float32"),
        "freqs": _Member((n_l,), "float64"),
        "phases": _Member((n, N_JOINTS, n_l), "float64"),
        "amplitude": _Member((n,), "float32"),
        "attempts": _Member((n,), "int32"),
        "shape": _Member((n, N_JOINTS, n_l, 2), "float32"),
    }


def default_chunk_size(simulator: Simulator) -> int:
    """Samples per rollout call: all threads busy, rollout buffers within the memory budget."""
    m = simulator.model
    per_step = 8 * (mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS) + m.nsensordata + 4 * m.nu)
    per_sample = per_step * simulator.n_steps
    return max(simulator.workers, _MEMORY_BUDGET // per_sample)


@dataclass
class _Chunk:
    commands: np.ndarray  # (B, T, 8) float32
    joint_angles: np.ndarray  # (B, T, 8) float32
    body: np.ndarray  # (B, T, 6) float32
    phases: np.ndarray  # (B, 8, L) float64
    amplitude: np.ndarray  # (B,)
    attempts: np.ndarray  # (B,) int32
    failures: list[dict] = field(default_factory=list)


def _draw(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng([cfg.seed, index, attempt])
    phases = random_phases(rng, cfg.excitation)
    commands, amplitude = multisine(phases, cfg.excitation)
    # The float32 commands are stored; simulate exactly those, so a replay of the file matches.
    return phases, commands.astype(np.float32), amplitude


def simulate_samples(cfg: GenerateConfig, simulator: Simulator, indices: np.ndarray) -> _Chunk:
    """Draw, simulate and measure samples ``indices`` (regenerating broken ones)."""
    b = len(indices)
    t, n_l = cfg.excitation.n_samples, cfg.excitation.n_components
    chunk = _Chunk(
        commands=np.empty((b, t, N_JOINTS), np.float32),
        joint_angles=np.empty((b, t, N_JOINTS), np.float32),
        body=np.empty((b, t, N_BODY), np.float32),
        phases=np.empty((b, N_JOINTS, n_l)),
        amplitude=np.empty(b, np.float32),
        attempts=np.zeros(b, np.int32),
    )
    todo = np.arange(b)
    for attempt in range(cfg.max_attempts):
        for j in todo:
            chunk.phases[j], chunk.commands[j], chunk.amplitude[j] = _draw(cfg, int(indices[j]), attempt)
            chunk.attempts[j] = attempt + 1
        result = simulator.simulate(chunk.commands[todo])
        chunk.joint_angles[todo] = result.joint_angles
        chunk.body[todo] = result.body
        failed = [i for i, f in enumerate(result.failures) if f is not None]
        for i in failed:
            chunk.failures.append(
                {"index": int(indices[todo[i]]), "attempt": attempt + 1, "reason": result.failures[i]}
            )
        todo = todo[failed]
        if len(todo) == 0:
            return chunk
    raise SimulationError(
        f"samples {indices[todo].tolist()} broke the simulation in all {cfg.max_attempts} phase draws; "
        f"last reasons: {[f['reason'] for f in chunk.failures[-len(todo) :]]}"
    )


def generate_dataset(
    cfg: GenerateConfig,
    out: str | Path,
    *,
    workers: int | None = None,
    chunk_size: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Generate a dataset and write it atomically to ``out`` (a partial run never leaves a file there).

    Args:
        cfg: what to generate.
        out: destination ``.npz`` path.
        workers: simulation threads (default: all cores).
        chunk_size: samples per rollout call (default: bounded by a 512 MiB buffer budget).
        progress: called with the number of samples finished after each chunk.

    Returns:
        The written path.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    simulator = Simulator(workers or os.cpu_count() or 1, cfg.excitation, cfg.sim)
    chunk_size = chunk_size or default_chunk_size(simulator)
    members = _members(cfg)
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        # Each array is filled chunk by chunk in a memory-mapped .npy on disk, so memory stays
        # bounded by one chunk whatever N is; the members are then streamed into the zip.
        arrays = {
            key: np.lib.format.open_memmap(tmp_dir / f"{key}.npy", "w+", np.dtype(m.dtype), m.shape)
            for key, m in members.items()
            if key != "freqs"
        }
        failures: list[dict] = []
        n = cfg.num_samples
        for start in range(0, n, chunk_size):
            idx = np.arange(start, min(n, start + chunk_size))
            chunk = simulate_samples(cfg, simulator, idx)
            sl = slice(idx[0], idx[-1] + 1)
            for key in ("commands", "joint_angles", "body", "phases", "amplitude", "attempts"):
                arrays[key][sl] = getattr(chunk, key)
            arrays["body_ds"][sl] = chunk.body[:, ::BODY_DOWNSAMPLE]
            arrays["shape"][sl] = joint_shape(chunk.joint_angles, cfg.excitation)
            failures.extend(chunk.failures)
            if progress is not None:
                progress(len(idx))
        for arr in arrays.values():
            arr.flush()
        del arrays
        np.save(tmp_dir / "freqs.npy", cfg.excitation.freqs.astype(np.float64))
        meta = {
            "schema_version": SCHEMA_VERSION,
            "config": cfg.model_dump(mode="json"),
            "mujoco_version": mujoco.__version__,
            "mjcf_sha256": mjcf_sha256(),
            "failures": failures,
        }
        np.save(tmp_dir / "meta.npy", np.array(json.dumps(meta)))
        tmp_file = tmp_dir / "dataset.npz"
        with zipfile.ZipFile(tmp_file, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key in [*members, "meta"]:
                zf.write(tmp_dir / f"{key}.npy", arcname=f"{key}.npy")
        os.replace(tmp_file, out)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    return out


class Dataset:
    """A validated dataset file; arrays are read from disk on first access and then kept.

    Attributes mirror the file's keys (``commands``, ``joint_angles``, ``body``, ``body_ds``, ``freqs``,
    ``phases``, ``amplitude``, ``attempts``, ``shape``); ``meta`` is the parsed JSON and ``config``
    the validated ``GenerateConfig``.
    """

    def __init__(self, path: Path, meta: dict, config: GenerateConfig) -> None:
        self.path = path
        self.meta = meta
        self.config = config
        self._cache: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return self.config.num_samples

    def __getattr__(self, key: str) -> np.ndarray:
        if key.startswith("_") or key not in _members(self.config):
            raise AttributeError(key)
        if key not in self._cache:
            try:
                with np.load(self.path, allow_pickle=False) as npz:
                    self._cache[key] = npz[key]
            except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
                raise DatasetError(f"{self.path}: array '{key}' is unreadable ({exc})") from exc
        return self._cache[key]

    @property
    def meta_hash(self) -> str:
        """sha256 of the meta JSON: identifies the dataset a checkpoint was trained on."""
        import hashlib

        return hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode()).hexdigest()


def _read_header(zf: zipfile.ZipFile, name: str) -> tuple[tuple[int, ...], np.dtype]:
    with zf.open(name) as f:
        version = np.lib.format.read_magic(f)
        read = (
            np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read(f)
    return shape, dtype


def load_dataset(path: str | Path) -> Dataset:
    """Open and validate a dataset written by ``snakeloco generate``.

    Checks that the file is a complete npz, has every key with the right shape and dtype, a meta
    of this schema version, and a config that validates. Arrays are loaded lazily.

    Raises:
        DatasetError: naming the problem (missing, truncated, foreign, wrong schema, wrong shapes).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such dataset file")
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            if "meta.npy" not in names:
                raise DatasetError(f"{path}: not a snakeloco dataset (no 'meta' entry)")
            with zf.open("meta.npy") as f:
                meta_arr = np.lib.format.read_array(f, allow_pickle=False)
            headers = {n[:-4]: _read_header(zf, n) for n in names if n.endswith(".npy")}
    except zipfile.BadZipFile as exc:
        raise DatasetError(f"{path}: not a complete .npz file (truncated or foreign): {exc}") from exc
    except DatasetError:
        raise
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(f"{path}: unreadable dataset ({exc})") from exc
    try:
        meta = json.loads(str(meta_arr))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: 'meta' is not valid JSON ({exc})") from exc
    version = meta.get("schema_version") if isinstance(meta, dict) else None
    if version != SCHEMA_VERSION:
        raise DatasetError(
            f"{path}: dataset schema version {version!r}, this snakeloco reads version {SCHEMA_VERSION}; "
            "regenerate it with `snakeloco generate`"
        )
    try:
        config = GenerateConfig.model_validate(meta.get("config"))
    except ValidationError as exc:
        raise DatasetError(f"{path}: invalid generating config in meta: {exc}") from exc
    expected = _members(config)
    missing = sorted(set(expected) - set(headers))
    if missing:
        raise DatasetError(f"{path}: missing arrays {missing}")
    for key, member in expected.items():
        shape, dtype = headers[key]
        if shape != member.shape or dtype != np.dtype(member.dtype):
            raise DatasetError(
                f"{path}: array '{key}' is {dtype}{list(shape)}, expected {member.dtype}{list(member.shape)}"
            )
    return Dataset(path, meta, config)
