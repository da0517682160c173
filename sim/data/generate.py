"""Dataset generation: records simulated chunk by chunk (``sim.data.chunks``) on a backend, written
atomically and resumably.

Deterministic in (N, seed) whatever the number of threads, the chunk size or the backend; every
failure is logged in ``meta["failures"]`` and counted in ``attempts``. No NaN is ever written. The
file format is ``sim.data.dataset``'s.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from snakeloco.sim.data.chunks import rebuild_chunk, simulate_samples, simulate_structured
from snakeloco.sim.data.dataset import BODY_DOWNSAMPLE, DatasetError
from snakeloco.sim.data.generate_config import GenerateConfig
from snakeloco.sim.data.writer import open_writer, read_progress, write_rows
from snakeloco.sim.gaits.spectra import joint_shape
from snakeloco.sim.physics.backend import BackendConfig, open_backend
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.physics.threads import resolve_workers
from snakeloco.sim.robot.description import load_model, mjcf_sha256
from snakeloco.sim.world.description import DEFAULT_WORLD

MEMORY_BUDGET = 512 * 2**20
"""Bytes of rollout buffers per chunk; bounds peak memory whatever the dataset size."""


def default_chunk_size(workers: int, cfg: GenerateConfig) -> int:
    """Paper-family records per chunk: all ``workers`` threads busy, the rollout buffers of a chunk
    within the memory budget (the same on every backend, so the file is too)."""
    m = load_model(cfg.robot)
    per_step = 8 * (mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS) + m.nsensordata + 4 * m.nu)
    rate = cfg.excitation.sample_rate
    steps = (cfg.sim.lead_in + cfg.excitation.n_samples) * round(1 / (rate * m.opt.timestep))
    return max(workers, MEMORY_BUDGET // (per_step * steps))


def _chunk_job(simulator: Simulator, job: tuple) -> tuple[int, int, dict, dict | None]:
    """Simulate (or rebuild from its log) one chunk of records: (start, count, log, arrays), arrays
    None where this process wrote them into the writer's folder itself (``write_rows``)."""
    cfg, start, stop, known, target = job
    idx = np.arange(start, stop)
    if known is not None:
        chunk = rebuild_chunk(cfg, simulator, idx, known)
    elif cfg.family == "structured":
        chunk = simulate_structured(cfg, simulator, idx)
    else:
        chunk = simulate_samples(cfg, simulator, idx)
    log = {"failures": chunk.failures, **chunk.log}
    arrays = {
        "commands": chunk.commands,
        "joint_angles": chunk.joint_angles,
        "body": chunk.body,
        "body_ds": chunk.body[:, ::BODY_DOWNSAMPLE],
        "phases": chunk.phases,
        "amplitude": chunk.amplitude,
        "attempts": chunk.attempts,
        "shape": joint_shape(chunk.joint_angles, cfg.excitation),
    }
    if target is not None and write_rows(target, start, arrays):
        return start, len(idx), log, None
    return start, len(idx), log, arrays


STRUCTURED_CHUNK = 16
"""Records per chunk of the structured family: each costs 2-4 replays per draw and about two draws,
so a chunk is a few minutes of physics on 2 cores, the most an interrupted run loses."""


def generate_dataset(
    cfg: GenerateConfig,
    out: str | Path,
    *,
    workers: int | None = None,
    chunk_size: int | None = None,
    progress: Callable[[int], None] | None = None,
    screened: str | Path | None = None,
    backend: BackendConfig | None = None,
) -> Path:
    """Generate a dataset and write it atomically to ``out`` (a partial run never leaves a file there).

    Resumable: an interrupted run keeps its finished chunks in ``out``'s work folder
    (``DatasetWriter``), and the same call continues from there to the same file.

    Args:
        cfg: what to generate (its ``family``: the paper's multisines or structured gaits).
        out: destination: an ``.npz`` file, or a zarr store where it ends in ``.zarr``.
        workers: simulation threads (default: all cores; with a Ray instance started here, its CPUs).
        chunk_size: records per chunk (default: the paper family's by a 512 MiB rollout-buffer budget,
            the structured family's ``STRUCTURED_CHUNK``); a resumed run keeps its first run's.
        progress: called with the number of records finished: those a resumed run already had, then
            after each chunk.
        backend: where to simulate (``sim.physics.backend``; default: this machine's cores).
        screened: the ``progress.json`` of an earlier run of the same config and physics (or a copy,
            such as the one shipped for the structured dataset): its chunks are rebuilt from their
            logged decisions with one replay per record (``rebuild_chunk``), the rest simulated.

    Returns:
        The written path.
    """
    structured = cfg.family == "structured"
    chunk_size = chunk_size or (
        STRUCTURED_CHUNK if structured else default_chunk_size(resolve_workers(workers), cfg)
    )
    physics = {"mujoco_version": mujoco.__version__, "mjcf_sha256": mjcf_sha256(cfg.robot)}
    if cfg.world != DEFAULT_WORLD:  # the ground too (default: left out, as every dataset before worlds)
        physics["world"] = cfg.world.model_dump(mode="json")
    known: dict[int, dict] = {}
    if screened is not None:
        chunk_size, known = read_progress(screened, cfg, physics)
    runner = open_backend(backend, workers, cfg.excitation, cfg.sim, cfg.robot, cfg.world)
    try:
        with open_writer(cfg, out, chunk_size, physics) as writer:
            if known and writer.chunk_size != chunk_size:
                raise DatasetError(
                    f"{writer.work} holds chunks of {writer.chunk_size} records, {screened} of {chunk_size}"
                )
            done = sum(min(writer.chunk_size, cfg.num_samples - s) for s in writer.chunks)
            if progress is not None and done:
                progress(done)
            # A Ray worker that sees the writer's folder writes its chunk there itself.
            target = writer.target if runner.name == "ray" else None
            jobs = (
                (cfg, s, min(cfg.num_samples, s + writer.chunk_size), known.get(s), target)
                for s in writer.starts()
            )
            for _, (start, n, log, arrays) in runner.map(_chunk_job, jobs):
                if arrays is None:
                    writer.done(start, log)
                else:
                    writer.write(start, log, **arrays)
                if progress is not None:
                    progress(n)
            logs = writer.logs()
            meta = {
                **physics,
                "failures": [f for log in logs for f in log["failures"]],
            }
            if structured:
                draws = sum(log["draws"] for log in logs)
                meta |= {
                    "family": "structured",
                    "draws": draws,
                    "rejection_rate": 1.0 - cfg.num_samples / draws,
                    "spreads": [s for log in logs for s in log["spreads"]],
                    "drawn": [d for log in logs for d in log["drawn"]],
                }
                if all("replayed_s" in log for log in logs):
                    meta["replayed_s"] = sum(log["replayed_s"] for log in logs)
            return writer.finish(meta)
    finally:
        runner.close()
