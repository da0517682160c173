"""Dataset generation: draw multisine records, simulate them in batches, write them atomically.

Deterministic in (N, seed): sample i, attempt a draws its phases from ``(seed, i, a)``, whatever the
number of threads or the chunk size. A sample whose simulation breaks (diverges, is reset by MuJoCo,
or throws the snake) is regenerated with a fresh phase draw from the same stream, up to
``max_attempts`` times; every failure is logged in ``meta["failures"]`` and counted in ``attempts``.
No NaN is ever written. The file format is ``sim.dataset``'s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from snakeloco.sim.command_rule import SimulationError
from snakeloco.sim.dataset import BODY_DOWNSAMPLE, N_BODY, DatasetWriter, GenerateConfig
from snakeloco.sim.excitation import multisine, random_phases
from snakeloco.sim.physics import Simulator, resolve_workers
from snakeloco.sim.robot import N_JOINTS, mjcf_sha256
from snakeloco.sim.spectra import joint_shape

MEMORY_BUDGET = 512 * 2**20
"""Bytes of rollout buffers per chunk; bounds peak memory whatever the dataset size."""


def default_chunk_size(simulator: Simulator) -> int:
    """Samples per rollout call: all threads busy, rollout buffers within the memory budget."""
    m = simulator.model
    per_step = 8 * (mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS) + m.nsensordata + 4 * m.nu)
    per_sample = per_step * simulator.n_steps
    return max(simulator.workers, MEMORY_BUDGET // per_sample)


@dataclass
class _Chunk:
    commands: np.ndarray  # (B, T, 8) float32
    joint_angles: np.ndarray  # (B, T, 8) float32
    body: np.ndarray  # (B, T, 6) float32
    phases: np.ndarray  # (B, 8, L) float64
    amplitude: np.ndarray  # (B,)
    attempts: np.ndarray  # (B,) int32
    failures: list[dict] = field(default_factory=list)


def draw_sample(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Phases (8, L) rad, float32 commands (T, 8) rad and amplitude U of sample ``index``'s attempt."""
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
            chunk.phases[j], chunk.commands[j], chunk.amplitude[j] = draw_sample(
                cfg, int(indices[j]), attempt
            )
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
    simulator = Simulator(resolve_workers(workers), cfg.excitation, cfg.sim)
    chunk_size = chunk_size or default_chunk_size(simulator)
    failures: list[dict] = []
    with DatasetWriter(cfg, out) as writer:
        for start in range(0, cfg.num_samples, chunk_size):
            idx = np.arange(start, min(cfg.num_samples, start + chunk_size))
            chunk = simulate_samples(cfg, simulator, idx)
            writer.write(
                start,
                commands=chunk.commands,
                joint_angles=chunk.joint_angles,
                body=chunk.body,
                body_ds=chunk.body[:, ::BODY_DOWNSAMPLE],
                phases=chunk.phases,
                amplitude=chunk.amplitude,
                attempts=chunk.attempts,
                shape=joint_shape(chunk.joint_angles, cfg.excitation),
            )
            failures.extend(chunk.failures)
            if progress is not None:
                progress(len(idx))
        meta = {"mujoco_version": mujoco.__version__, "mjcf_sha256": mjcf_sha256(), "failures": failures}
        return writer.finish(meta)
