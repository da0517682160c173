"""Training dataset files: the format and the validated reader (numpy only; zarr on demand); what
generated a file is its ``sim.data.generate_config.GenerateConfig``, stored in its meta.

Generation (``sim.data.generate``) simulates the records and writes them with ``sim.data.writer``; a dataset
is an ``.npz`` file or, for sets that outgrow memory, a zarr store (``PATH.zarr``, a folder: the same
arrays chunked by record, ``meta`` as the group attribute).

File format: one ``.npz`` (uncompressed zip of ``.npy`` members), float32 unless noted:

=================  ===============  ==================================================================
key                shape            meaning
=================  ===============  ==================================================================
``commands``       (N, 2000, 8)     joint commands (rad), exactly what was simulated
``joint_angles``   (N, 2000, 8)     measured joint angles (rad) at 20 Hz
``body``           (N, 2000, 6)     body states at 20 Hz (``sim.BODY_CHANNELS``; m and rad)
``body_ds``        (N, 500, 6)      ``body[:, ::4]``: every 4th sample, 5 Hz, t = 0.2 k s
``freqs``          (L,)             excited frequencies (Hz), float64
``phases``         (N, n_joints, L)        multisine phases (rad), float64
``amplitude``      (N,)             shared per-component amplitude U (rad)
``attempts``       (N,)             int32: phase draws needed (1 = first draw simulated cleanly)
``shape``          (N, n_joints, L, 2)     single-sided FFT coefficients of ``joint_angles`` at the excited
                                    bins (real, imag; rad), ``sim.joint_shape`` of the stored angles
``meta``           ()               JSON string: schema version, generating config, mujoco version,
                                    MJCF sha256, failure log
=================  ===============  ==================================================================

A sample whose simulation breaks (diverges, is reset by MuJoCo, or throws the snake) is regenerated
with a fresh phase draw from the same deterministic stream, up to ``max_attempts`` times; every
failure is logged in ``meta["failures"]`` and counted in ``attempts``. No NaN is ever written.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from snakeloco.sim.data.generate_config import GenerateConfig
from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.physics.body import BODY_CHANNELS

SCHEMA_VERSION = 1
BODY_DOWNSAMPLE = 4
"""The model sees the body series at 20 Hz / 4 = 5 Hz (500 steps)."""
BODY_RATE = RECORD.sample_rate / BODY_DOWNSAMPLE
"""Sample rate of the model's body series (Hz): the 20 Hz record, every ``BODY_DOWNSAMPLE``-th sample."""
BODY_STEPS = -(-RECORD.n_samples // BODY_DOWNSAMPLE)
"""Steps of the model's body series: 500 (every 4th of the 2000 record samples)."""
BODY_TIMES = RECORD.times[::BODY_DOWNSAMPLE]
"""(500,) time stamps (s) of the model's body series: 0, 0.2, ... 99.8."""
N_BODY = len(BODY_CHANNELS)


ZARR_MISSING = "zarr stores need the scale extra: pip install 'snakeloco[scale]'"


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


def dataset_members(cfg: GenerateConfig) -> dict[str, _Member]:
    t, n_l = cfg.excitation.n_samples, cfg.excitation.n_components
    n, n_joints = cfg.num_samples, cfg.robot.n_joints
    return {
        "commands": _Member((n, t, n_joints), "float32"),
        "joint_angles": _Member((n, t, n_joints), "float32"),
        "body": _Member((n, t, N_BODY), "float32"),
        "body_ds": _Member((n, -(-t // BODY_DOWNSAMPLE), N_BODY), "float32"),
        "freqs": _Member((n_l,), "float64"),
        "phases": _Member((n, n_joints, n_l), "float64"),
        "amplitude": _Member((n,), "float32"),
        "attempts": _Member((n,), "int32"),
        "shape": _Member((n, n_joints, n_l, 2), "float32"),
    }


class Dataset:
    """A validated dataset (an ``.npz`` file or a zarr store); arrays are read on first access and
    then kept, or read a few rows at a time with ``rows``.

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
        if key.startswith("_") or key not in dataset_members(self.config):
            raise AttributeError(key)
        if key not in self._cache:
            self._cache[key] = self._read(key, None)
        return self._cache[key]

    def rows(self, key: str, index: np.ndarray) -> Rows:
        """Records ``index`` of array ``key``, read a slice at a time when sliced: a zarr store reads
        only the chunks that hold them, so a pass over a large store stays within memory."""
        if key not in dataset_members(self.config) or key == "freqs":
            raise KeyError(f"{key!r} is not a per-record array of a dataset")
        return Rows(self, key, np.asarray(index, np.int64))

    def _read(self, key: str, index: np.ndarray | None) -> np.ndarray:
        if index is not None and key in self._cache:
            return self._cache[key][index]
        try:
            if self.path.is_dir():
                array = import_zarr().open_array(self.path / key, mode="r")
                return array[...] if index is None else array.oindex[index]
            with np.load(self.path, allow_pickle=False) as npz:
                whole = npz[key]
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
            raise DatasetError(f"{self.path}: array '{key}' is unreadable ({exc})") from exc
        if index is None:
            return whole
        self._cache[key] = whole  # an .npz member cannot be read in part: keep what was read
        return whole[index]

    @property
    def meta_hash(self) -> str:
        """sha256 of the meta JSON: identifies the dataset a checkpoint was trained on."""
        return hashlib.sha256(json.dumps(self.meta, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class Rows:
    """Some records of one dataset array (``Dataset.rows``); ``rows[a:b]`` reads those only."""

    dataset: Dataset
    key: str
    index: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, part: slice) -> np.ndarray:
        return self.dataset._read(self.key, self.index[part])


def import_zarr():
    """The zarr module, or a DatasetError saying what to install."""
    try:
        import zarr
    except ImportError as exc:
        raise DatasetError(ZARR_MISSING) from exc
    return zarr


def _read_header(zf: zipfile.ZipFile, name: str) -> tuple[tuple[int, ...], np.dtype]:
    with zf.open(name) as f:
        version = np.lib.format.read_magic(f)
        read = (
            np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read(f)
    return shape, dtype


def _read_npz(path: Path) -> tuple[str, dict[str, tuple[tuple[int, ...], np.dtype]]]:
    """The meta JSON text and every array's (shape, dtype) of an ``.npz`` dataset."""
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
    return str(meta_arr), headers


def _read_zarr(path: Path) -> tuple[str, dict[str, tuple[tuple[int, ...], np.dtype]]]:
    """The meta JSON text and every complete array's (shape, dtype) of a zarr dataset store."""
    zarr = import_zarr()
    try:
        group = zarr.open_group(path, mode="r")
        meta = group.attrs.get("meta")
        arrays = dict(group.arrays())
    except Exception as exc:  # zarr raises several kinds for a folder that is no store
        raise DatasetError(f"{path}: not a readable zarr store ({type(exc).__name__}: {exc})") from exc
    if not isinstance(meta, str):
        raise DatasetError(f"{path}: not a snakeloco dataset (no 'meta' attribute)")
    for key, array in arrays.items():
        if array.nchunks_initialized != array.nchunks:
            raise DatasetError(
                f"{path}: array '{key}' has {array.nchunks_initialized} of its {array.nchunks} chunks "
                "(an incomplete or damaged store)"
            )
    return meta, {key: (array.shape, array.dtype) for key, array in arrays.items()}


def load_dataset(path: str | Path) -> Dataset:
    """Open and validate a dataset written by ``snakeloco generate``: an ``.npz`` file or a zarr
    store (a folder, ``PATH.zarr``).

    Checks that the file is complete (every zip member, every zarr chunk), has every key with the
    right shape and dtype, a meta of this schema version, and a config that validates. Arrays are
    loaded lazily.

    Raises:
        DatasetError: naming the problem (missing, truncated, foreign, wrong schema, wrong shapes).
    """
    path = Path(path)
    if path.is_dir():
        meta_text, headers = _read_zarr(path)
    elif path.is_file():
        meta_text, headers = _read_npz(path)
    else:
        raise DatasetError(f"{path}: no such dataset file")
    try:
        meta = json.loads(meta_text)
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
    expected = dataset_members(config)
    missing = sorted(set(expected) - set(headers))
    if missing:
        raise DatasetError(f"{path}: missing arrays {missing}")
    for key, member in expected.items():
        shape, dtype = headers[key]
        if tuple(shape) != member.shape or dtype != np.dtype(member.dtype):
            raise DatasetError(
                f"{path}: array '{key}' is {dtype}{list(shape)}, expected {member.dtype}{list(member.shape)}"
            )
    return Dataset(path, meta, config)
