"""Writing a dataset chunk of records by chunk: atomically, with bounded memory, resumably, as an
``.npz`` file (``DatasetWriter``) or a chunked zarr store (``ZarrDatasetWriter``, ``PATH.zarr``).

Both keep a work folder beside the destination (``PATH.partial``) whose ``progress.json`` records the
config, the physics and every finished chunk's log; the same run started again resumes from there,
and ``finish`` makes the result visible at ``PATH`` in one rename. A chunk's arrays are written
either by the process that gathers the results (``write``) or, where a simulation worker sees the
same filesystem, by the worker itself (``write_rows`` on the writer's ``target``, then ``done``).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import zipfile
from pathlib import Path

import numpy as np

from snakeloco.sim.data.dataset import SCHEMA_VERSION, DatasetError, dataset_members, import_zarr
from snakeloco.sim.data.generate_config import GenerateConfig


def is_zarr_path(path: str | Path) -> bool:
    """Whether ``path`` names a zarr store (``.zarr``) rather than an ``.npz`` file."""
    return Path(path).suffix == ".zarr"


def read_progress(path: str | Path, cfg: GenerateConfig, physics: dict) -> tuple[int, dict[int, dict]]:
    """Chunk size and per-chunk logs (first record -> log) of a run's ``progress.json`` or a copy of
    it, checked to be a run of ``cfg`` on the same ``physics`` (MuJoCo version and model hash, as
    ``generate`` records them).

    Raises:
        DatasetError: the file is unreadable, not a progress file, or of another config or physics.
    """
    path = Path(path)
    try:
        progress = json.loads(path.read_text())
        chunk_size = int(progress["chunk_size"])
        chunks = {int(k): dict(v) for k, v in progress["chunks"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(f"{path} is not a generation progress file ({type(exc).__name__}: {exc})") from exc
    if progress.get("config") != cfg.to_meta():
        raise DatasetError(
            f"{path} is a run of another config; delete it (or give the same options) to start this one "
            f"(its config: {progress.get('config')})"
        )
    if progress.get("physics", {}) != physics:
        raise DatasetError(
            f"{path} was simulated with other physics ({progress.get('physics')}, here {physics}): "
            "its records would not be those this run makes"
        )
    if chunk_size < 1 or any(s % chunk_size or not 0 <= s < cfg.num_samples for s in chunks):
        raise DatasetError(f"{path}: chunk starts {sorted(chunks)} do not fit chunks of {chunk_size}")
    return chunk_size, chunks


class DatasetWriter:
    """Writes an ``.npz`` dataset atomically, chunk of records by chunk, with bounded memory, resumably.

    Each array is filled in a memory-mapped ``.npy`` in the work folder (``PATH.partial``); after each
    chunk, ``done`` records it (with what the chunk logged) in the folder's ``progress.json``.
    ``finish`` streams the arrays into the zip, renames it to ``out``, keeps a structured run's log
    beside it (``OUT.screening.json``) and removes the folder. A run that
    stops (an error, Ctrl-C) leaves ``out`` as it was and keeps the folder where at least one chunk
    finished: the same config writing to the same ``out`` again resumes from there and gives the same
    file as an uninterrupted run.
    """

    kind = "npz"

    def __init__(
        self, cfg: GenerateConfig, out: str | Path, chunk_size: int, physics: dict | None = None
    ) -> None:
        self.cfg = cfg
        self.out = Path(out)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.work = self.out.with_name(self.out.name + ".partial")
        self._members = {k: m for k, m in dataset_members(cfg).items() if k != "freqs"}
        self._progress = self.work / "progress.json"
        self.physics = physics or {}
        self.chunks: dict[int, dict] = {}  # start -> what that chunk logged
        resuming = self._progress.is_file()
        if resuming:
            chunk_size, self.chunks = read_progress(self._progress, cfg, self.physics)
        self.chunk_size = chunk_size
        self.work.mkdir(exist_ok=True)
        self._arrays = self._open(resuming)
        # A worker writes a chunk itself only where it reads this very token (the same filesystem).
        self._token = secrets.token_hex(16)
        (self.work / "writer.token").write_text(self._token)

    def _open(self, resuming: bool) -> dict:
        mode = "r+" if resuming else "w+"
        return {
            key: np.lib.format.open_memmap(self.work / f"{key}.npy", mode, np.dtype(m.dtype), m.shape)
            for key, m in self._members.items()
        }

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._arrays.clear()
        if not self.chunks:  # nothing to resume from
            shutil.rmtree(self.work, ignore_errors=True)

    @property
    def target(self) -> dict:
        """What a simulation worker needs to write a chunk itself (``write_rows``); JSON-ready."""
        return {"kind": self.kind, "work": str(self.work.resolve()), "token": self._token}

    def starts(self) -> list[int]:
        """First record of every chunk not written yet, in order."""
        return [s for s in range(0, self.cfg.num_samples, self.chunk_size) if s not in self.chunks]

    def write(self, start: int, log: dict | None = None, **arrays: np.ndarray) -> None:
        """Store the chunk of records from ``start`` (each named per-record array) and mark it done,
        with ``log`` (JSON-ready: what ``finish`` gathers into the meta)."""
        _store_rows(self._arrays, start, arrays)
        self.done(start, log)

    def done(self, start: int, log: dict | None = None) -> None:
        """Mark the chunk from ``start`` finished (its arrays are stored), with its ``log``."""
        self.chunks[start] = log or {}
        progress = {
            "config": self.cfg.to_meta(),
            "physics": self.physics,
            "chunk_size": self.chunk_size,
            "chunks": self.chunks,
        }
        tmp = self._progress.with_suffix(".tmp")
        tmp.write_text(json.dumps(progress))
        os.replace(tmp, self._progress)

    def logs(self) -> list[dict]:
        """What every written chunk logged, in record order."""
        return [self.chunks[s] for s in sorted(self.chunks)]

    def _keep_screening_log(self) -> None:
        """Copy the run's ``progress.json`` beside ``out`` as ``OUT.screening.json`` (structured family):
        screening is most of a run's physics, and ``generate --screened`` rebuilds the same file from
        the log with one replay per record."""
        if self.cfg.family == "structured" and self._progress.is_file():
            shutil.copyfile(self._progress, self.out.with_name(self.out.name + ".screening.json"))

    def _full_meta(self, meta: dict) -> dict:
        return {"schema_version": SCHEMA_VERSION, "config": self.cfg.to_meta(), **meta}

    def finish(self, meta: dict) -> Path:
        """Write ``freqs`` and ``meta`` (schema version and config added), zip every member, rename to
        ``out`` and remove the work folder."""
        self._arrays.clear()
        np.save(self.work / "freqs.npy", self.cfg.excitation.freqs.astype(np.float64))
        np.save(self.work / "meta.npy", np.array(json.dumps(self._full_meta(meta))))
        tmp_file = self.work / "dataset.npz"
        with zipfile.ZipFile(tmp_file, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key in [*self._members, "freqs", "meta"]:
                zf.write(self.work / f"{key}.npy", arcname=f"{key}.npy")
        os.replace(tmp_file, self.out)
        self._keep_screening_log()
        self.chunks = {}
        shutil.rmtree(self.work, ignore_errors=True)
        return self.out


class ZarrDatasetWriter(DatasetWriter):
    """Writes a zarr store (``PATH.zarr``): the ``.npz`` file's arrays, chunked by record (one zarr
    chunk per chunk of records, so writers of different chunks never touch the same file), zstd
    compressed, with ``meta`` as the group's attribute. Built in ``PATH.partial/store.zarr`` and
    renamed to ``PATH`` when finished; resumable like the ``.npz`` writer."""

    kind = "zarr"

    def __init__(self, cfg, out, chunk_size, physics=None) -> None:
        import_zarr()  # before anything is made on disk
        out = Path(out)
        if out.exists() and not (out / "zarr.json").is_file():
            raise DatasetError(
                f"{out} exists and is not a zarr store: choose another path (nothing was replaced)"
            )
        super().__init__(cfg, out, chunk_size, physics)

    def _open(self, resuming: bool) -> dict:
        zarr = import_zarr()
        store = self.work / "store.zarr"
        if resuming:
            group = zarr.open_group(store, mode="r+")
            return {key: group[key] for key in self._members}
        group = zarr.open_group(store, mode="w")
        return {
            key: group.create_array(
                key,
                shape=m.shape,
                chunks=(self.chunk_size, *m.shape[1:]),
                dtype=m.dtype,
                fill_value=0,
                config={"write_empty_chunks": True},  # every chunk a file: completeness is checkable
            )
            for key, m in self._members.items()
        }

    def finish(self, meta: dict) -> Path:
        """Write ``freqs`` and ``meta`` into the store and rename it to ``out`` (replacing an older
        store there), then remove the work folder."""
        zarr = import_zarr()
        store = self.work / "store.zarr"
        group = zarr.open_group(store, mode="r+")
        freqs = self.cfg.excitation.freqs.astype(np.float64)
        group.create_array("freqs", shape=freqs.shape, dtype="float64", overwrite=True)[:] = freqs
        group.attrs["meta"] = json.dumps(self._full_meta(meta))
        self._arrays.clear()
        old = self.work / "replaced.zarr"
        if self.out.exists():
            os.replace(self.out, old)  # a directory cannot be renamed onto another
        os.replace(store, self.out)
        self._keep_screening_log()
        self.chunks = {}
        shutil.rmtree(self.work, ignore_errors=True)
        return self.out


def open_writer(
    cfg: GenerateConfig, out: str | Path, chunk_size: int, physics: dict | None = None
) -> DatasetWriter:
    """The writer for ``out``: a zarr store for ``PATH.zarr``, else an ``.npz`` file."""
    kind = ZarrDatasetWriter if is_zarr_path(out) else DatasetWriter
    return kind(cfg, out, chunk_size, physics)


def _store_rows(arrays: dict, start: int, values: dict[str, np.ndarray]) -> None:
    for key, value in values.items():
        arrays[key][start : start + len(value)] = value
    for arr in arrays.values():
        if isinstance(arr, np.memmap):
            arr.flush()


def write_rows(target: dict, start: int, values: dict[str, np.ndarray]) -> bool:
    """Write a chunk's arrays into the writer described by ``target`` (``DatasetWriter.target``) from
    another process, if this process sees that writer's work folder; returns whether it wrote them
    (False: hand them to the writer instead)."""
    work = Path(target["work"])
    try:
        if (work / "writer.token").read_text() != target["token"]:
            return False
    except OSError:
        return False  # another machine: the folder is not here
    if target["kind"] == "zarr":
        group = import_zarr().open_group(work / "store.zarr", mode="r+")
        arrays = {key: group[key] for key in values}
    else:
        arrays = {key: np.lib.format.open_memmap(work / f"{key}.npy", "r+") for key in values}
    _store_rows(arrays, start, values)
    return True
