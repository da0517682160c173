"""Dataset generation: draw multisine records, simulate them in batches, write them atomically.

Deterministic in (N, seed): sample i, attempt a draws its phases from ``(seed, i, a)``, whatever the
number of threads or the chunk size. A sample whose simulation breaks (diverges, is reset by MuJoCo,
or throws the snake) is regenerated with a fresh phase draw from the same stream, up to
``max_attempts`` times; every failure is logged in ``meta["failures"]`` and counted in ``attempts``.
No NaN is ever written. The file format is ``sim.dataset``'s.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from snakeloco.sim.backend import BackendConfig, open_backend
from snakeloco.sim.command_rule import SimulationError
from snakeloco.sim.consistency import ensemble_spread, perturbed_commands
from snakeloco.sim.dataset import (
    BODY_DOWNSAMPLE,
    N_BODY,
    DatasetError,
    GenerateConfig,
)
from snakeloco.sim.excitation import RECORD, multisine, random_phases
from snakeloco.sim.physics import Simulator
from snakeloco.sim.robot import N_JOINTS, load_model, mjcf_sha256
from snakeloco.sim.spectra import joint_shape, shape_to_commands
from snakeloco.sim.structured import draw_structured, perturbed_shapes
from snakeloco.sim.threads import resolve_workers
from snakeloco.sim.writer import open_writer, read_progress, write_rows

MEMORY_BUDGET = 512 * 2**20
"""Bytes of rollout buffers per chunk; bounds peak memory whatever the dataset size."""


def default_chunk_size(workers: int, cfg: GenerateConfig) -> int:
    """Paper-family records per chunk: all ``workers`` threads busy, the rollout buffers of a chunk
    within the memory budget (the same on every backend, so the file is too)."""
    m = load_model()
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


@dataclass
class _Chunk:
    commands: np.ndarray  # (B, T, 8) float32
    joint_angles: np.ndarray  # (B, T, 8) float32
    body: np.ndarray  # (B, T, 6) float32
    phases: np.ndarray  # (B, 8, L) float64
    amplitude: np.ndarray  # (B,)
    attempts: np.ndarray  # (B,) int32
    failures: list[dict] = field(default_factory=list)
    log: dict = field(default_factory=dict)  # what a family records beside the failures (JSON-ready)

    @classmethod
    def empty(cls, cfg: GenerateConfig, b: int) -> _Chunk:
        t, n_l = cfg.excitation.n_samples, cfg.excitation.n_components
        return cls(
            commands=np.empty((b, t, N_JOINTS), np.float32),
            joint_angles=np.empty((b, t, N_JOINTS), np.float32),
            body=np.empty((b, t, N_BODY), np.float32),
            phases=np.empty((b, N_JOINTS, n_l)),
            amplitude=np.empty(b, np.float32),
            attempts=np.zeros(b, np.int32),
        )


def draw_sample(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Phases (8, L) rad, float32 commands (T, 8) rad and amplitude U of sample ``index``'s attempt."""
    rng = np.random.default_rng([cfg.seed, index, attempt])
    phases = random_phases(rng, cfg.excitation)
    commands, amplitude = multisine(phases, cfg.excitation)
    # The float32 commands are stored; simulate exactly those, so a replay of the file matches.
    return phases, commands.astype(np.float32), amplitude


def draw_record(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """Structured record ``index``'s gait at ``attempt``: float32 commands (T, 8) rad, phases (8, L) of
    its joint shape and what was drawn (``draw_structured``)."""
    shape, drawn = draw_structured(cfg.structured, cfg.seed, index, attempt)
    # The float32 commands are stored; replay exactly those, so a replay of the file matches.
    commands = shape_to_commands(shape, cfg.excitation.freqs).astype(np.float32)
    return commands, np.arctan2(shape[..., 1], shape[..., 0]), drawn


def simulate_samples(cfg: GenerateConfig, simulator: Simulator, indices: np.ndarray) -> _Chunk:
    """Draw, simulate and measure samples ``indices`` (regenerating broken ones)."""
    chunk = _Chunk.empty(cfg, len(indices))
    todo = np.arange(len(indices))
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


def _noise_seed(seed: int, index: int, attempt: int) -> int:
    """Seed of the ensemble noise of record ``index``'s draw ``attempt`` (``perturbed_commands``)."""
    return int(np.random.default_rng([seed, index, attempt, 1]).integers(2**31))


def _spread(body: np.ndarray, failures: list[str | None]) -> tuple[float, str | None]:
    """Final spread of an ensemble's body series (K, T, 6), member 0 unperturbed, or why it has none
    (the first of ``failures``, its members' break reasons, that is not None)."""
    broken = next((f for f in failures if f is not None), None)
    if broken is not None:
        return float("inf"), broken
    return ensemble_spread(body, RECORD.sample_rate)["final_spread"], None


def _ensemble(cfg: GenerateConfig, index: int, attempt: int, commands: np.ndarray) -> np.ndarray:
    """The commands (T, 8) of a structured draw and its ``members`` - 1 perturbed copies: command
    noise, and where ``coefficient_noise`` is set, the joint shape's coefficients perturbed first."""
    sc, seed = cfg.structured, _noise_seed(cfg.seed, index, attempt)
    ensemble = perturbed_commands(commands.astype(np.float64), sc.members, seed=seed)
    if sc.coefficient_noise > 0:
        shape, _ = draw_structured(sc, cfg.seed, index, attempt)
        shapes = perturbed_shapes(shape, sc.members, sc.coefficient_noise, np.random.default_rng([seed, 1]))
        factors = perturbed_commands(np.ones_like(ensemble[0]), sc.members, seed=seed)  # 1 + noise, once
        for m, noisy in enumerate(shapes[1:], start=1):  # the same command noise on the noisy shape
            ensemble[m] = shape_to_commands(noisy, cfg.excitation.freqs) * factors[m]
    return ensemble


def simulate_structured(cfg: GenerateConfig, simulator: Simulator, indices: np.ndarray) -> _Chunk:
    """Draw, screen and measure structured-family records ``indices`` (``sim.structured``).

    Each draw is replayed with ``screen_members`` - 1 noisy copies (the first check). Where
    ``early_seconds`` is set, those replays pause there and a draw whose spread already exceeds
    ``early_max_spread`` is redrawn at once; the rest carry on from where they paused (the same
    numbers as one replay). A draw whose 100 s spread exceeds ``max_spread`` (or any of whose
    replays breaks) is redrawn; one whose spread is within ``sure_spread`` is kept as it is; the
    rest get the remaining ``members`` and are kept only if the whole ensemble's spread is within
    ``max_spread`` too. A kept record stores its unperturbed replay. Every rejection is logged as a
    failure, and the seconds of physics simulated as ``replayed_s``.
    """
    sc, rate = cfg.structured, cfg.excitation.sample_rate
    chunk = _Chunk.empty(cfg, len(indices))
    spreads = np.zeros(len(indices))
    drawn: list[dict] = [{} for _ in indices]
    todo = list(range(len(indices)))
    attempt = np.zeros(len(indices), np.int64)
    draws, replayed = 0, 0.0
    record_s = cfg.excitation.n_samples / rate
    k = sc.screen_members
    while todo:
        commands = {}
        for j in todo:
            commands[j], chunk.phases[j], drawn[j] = draw_record(cfg, int(indices[j]), int(attempt[j]))
        draws += len(todo)
        ensembles = {
            j: _ensemble(cfg, int(indices[j]), int(attempt[j]), commands[j]) for j in todo
        }  # (members, T, 8) each; the first check is its first screen_members
        rejected: dict[int, str] = {}
        first = np.concatenate([ensembles[j][:k] for j in todo])
        rows = {j: list(range(n * k, (n + 1) * k)) for n, j in enumerate(todo)}
        if sc.early_seconds > 0:
            n_early = round(sc.early_seconds * rate)
            early = simulator.simulate(first, samples=n_early)
            replayed += len(first) * n_early / rate
            for j in todo:
                spread, broken = _spread(early.body[rows[j]], [early.failures[r] for r in rows[j]])
                if broken or spread > sc.early_max_spread:
                    rejected[j] = broken or (
                        f"final spread {spread:.3f} > {sc.early_max_spread} at {sc.early_seconds:g} s"
                    )
            going = [j for j in todo if j not in rejected]
            carry = [r for j in going for r in rows[j]]
            screen = simulator.simulate(first[carry], resume=early.paused.rows(carry)) if carry else None
            replayed += len(carry) * (record_s - n_early / rate)
            rows = {j: list(range(n * k, (n + 1) * k)) for n, j in enumerate(going)}
        else:
            going = list(todo)
            screen = simulator.simulate(first)
            replayed += len(first) * record_s
        passed = []
        for j in going:
            spread, broken = _spread(screen.body[rows[j]], [screen.failures[r] for r in rows[j]])
            if broken or spread > sc.max_spread:
                rejected[j] = broken or f"final spread {spread:.3f} > {sc.max_spread} in the first check"
                continue
            chunk.joint_angles[j] = screen.joint_angles[rows[j][0]]
            chunk.body[j] = screen.body[rows[j][0]]
            if spread <= sc.sure_spread or sc.members == k:  # no second check: this is its spread
                spreads[j] = spread
            else:
                passed.append(j)
        extra = sc.members - k
        if passed:
            rest = simulator.simulate(np.concatenate([ensembles[j][k:] for j in passed]))
            replayed += len(passed) * extra * record_s
            for m, j in enumerate(passed):
                body = np.concatenate([screen.body[rows[j]], rest.body[m * extra : (m + 1) * extra]])
                failures = [screen.failures[r] for r in rows[j]] + rest.failures[m * extra : (m + 1) * extra]
                spread, broken = _spread(body, failures)
                if broken or spread > sc.max_spread:
                    rejected[j] = (
                        broken or f"final spread {spread:.3f} > {sc.max_spread} over {sc.members} replays"
                    )
                else:
                    spreads[j] = spread
        for j in todo:
            chunk.attempts[j] = attempt[j] + 1
            if j in rejected:
                chunk.failures.append(
                    {"index": int(indices[j]), "attempt": int(attempt[j]) + 1, "reason": rejected[j]}
                )
            else:
                chunk.commands[j] = commands[j]
                chunk.amplitude[j] = np.abs(commands[j]).max()
        attempt[list(rejected)] += 1
        todo = sorted(rejected)
        stuck = [j for j in todo if attempt[j] >= sc.max_draws]
        if stuck:
            raise SimulationError(
                f"structured records {indices[stuck].tolist()} found no predictable gait in {sc.max_draws} draws; "
                f"last reasons: {[rejected[j] for j in stuck]}"
            )
    chunk.log = {"spreads": spreads.tolist(), "drawn": drawn, "draws": draws}
    if sc.early_seconds > 0 or sc.sure_spread > 0:  # older families' logs stay as they were
        chunk.log["replayed_s"] = replayed
    return chunk


def rebuild_chunk(cfg: GenerateConfig, simulator: Simulator, indices: np.ndarray, log: dict) -> _Chunk:
    """Records ``indices`` as an earlier run of ``cfg`` kept them, from that chunk's ``log``
    (``DatasetWriter``): each record's kept draw is the one after its logged rejections, replayed once
    (physics is deterministic: the arrays are those the run stored). The structured family's ensemble
    screening is what this skips: one replay per record instead of about eight.

    Raises:
        DatasetError: the log does not fit (a record's redraw differs from the one logged, or its kept
            gait breaks): it is not of this config and code.
    """
    structured = cfg.family == "structured"
    chunk = _Chunk.empty(cfg, len(indices))
    rejected = Counter(int(f["index"]) for f in log["failures"])
    drawn = []
    for j, i in enumerate(indices.tolist()):
        attempt = rejected[i]
        if structured:
            chunk.commands[j], chunk.phases[j], d = draw_record(cfg, i, attempt)
            chunk.amplitude[j] = np.abs(chunk.commands[j]).max()
            drawn.append(d)
        else:
            chunk.phases[j], chunk.commands[j], chunk.amplitude[j] = draw_sample(cfg, i, attempt)
        chunk.attempts[j] = attempt + 1
    if structured and json.loads(json.dumps(drawn)) != log["drawn"]:
        raise DatasetError(
            f"records {indices[0]}-{indices[-1]}: the gaits drawn here differ from the logged ones "
            "(another version of the structured family's draw)"
        )
    result = simulator.simulate(chunk.commands)
    broken = [(int(indices[j]), f) for j, f in enumerate(result.failures) if f is not None]
    if broken:
        raise DatasetError(
            f"record {broken[0][0]}'s kept gait breaks on replay ({broken[0][1]}): the log is not of this physics"
        )
    chunk.joint_angles[:], chunk.body[:] = result.joint_angles, result.body
    chunk.failures = list(log["failures"])
    chunk.log = {k: v for k, v in log.items() if k != "failures"}
    return chunk


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
        backend: where to simulate (``sim.backend``; default: this machine's cores).
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
    physics = {"mujoco_version": mujoco.__version__, "mjcf_sha256": mjcf_sha256()}
    known: dict[int, dict] = {}
    if screened is not None:
        chunk_size, known = read_progress(screened, cfg, physics)
    runner = open_backend(backend, workers, cfg.excitation, cfg.sim)
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
