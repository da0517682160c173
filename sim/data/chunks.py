"""One chunk of records: drawn, simulated (the structured family's screened) or rebuilt from a
run's log. ``sim.data.generate`` runs chunks on a backend and writes them; this module is what one
chunk job does, the same on every backend.

Deterministic in (N, seed): sample i, attempt a draws its phases (or its structured gait) from
``(seed, i, a)``, whatever the number of threads or the chunk size. A sample whose simulation breaks
is regenerated with a fresh draw from the same stream, up to ``max_attempts`` times; every failure
is logged and counted in ``attempts``.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from snakeloco.sim.data.dataset import N_BODY, DatasetError
from snakeloco.sim.data.generate_config import GenerateConfig
from snakeloco.sim.gaits.excitation import RECORD, multisine, random_phases
from snakeloco.sim.gaits.spectra import shape_to_commands
from snakeloco.sim.gaits.structured import draw_structured
from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.scores.consistency import ensemble_spread, perturbed_commands


@dataclass
class _Chunk:
    commands: np.ndarray  # (B, T, n_joints) float32
    joint_angles: np.ndarray  # (B, T, n_joints) float32
    body: np.ndarray  # (B, T, 6) float32
    phases: np.ndarray  # (B, n_joints, L) float64
    amplitude: np.ndarray  # (B,)
    attempts: np.ndarray  # (B,) int32
    failures: list[dict] = field(default_factory=list)
    log: dict = field(default_factory=dict)  # what a family records beside the failures (JSON-ready)

    @classmethod
    def empty(cls, cfg: GenerateConfig, b: int) -> _Chunk:
        t, n_l, n_joints = cfg.excitation.n_samples, cfg.excitation.n_components, cfg.robot.n_joints
        return cls(
            commands=np.empty((b, t, n_joints), np.float32),
            joint_angles=np.empty((b, t, n_joints), np.float32),
            body=np.empty((b, t, N_BODY), np.float32),
            phases=np.empty((b, n_joints, n_l)),
            amplitude=np.empty(b, np.float32),
            attempts=np.zeros(b, np.int32),
        )


def draw_sample(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Phases (n_joints, L) rad, float32 commands (T, n_joints) rad and amplitude U of sample ``index``'s attempt."""
    rng = np.random.default_rng([cfg.seed, index, attempt])
    phases = random_phases(rng, cfg.excitation, cfg.robot.n_joints)
    commands, amplitude = multisine(phases, cfg.excitation)
    # The float32 commands are stored; simulate exactly those, so a replay of the file matches.
    return phases, commands.astype(np.float32), amplitude


def draw_record(cfg: GenerateConfig, index: int, attempt: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """Structured record ``index``'s gait at ``attempt``: float32 commands (T, n_joints) rad, phases (n_joints, L) of
    its joint shape and what was drawn (``draw_structured``)."""
    shape, drawn = draw_structured(cfg.structured, cfg.seed, index, attempt, cfg.robot)
    # The float32 commands are stored; replay exactly those, so a replay of the file matches.
    commands = shape_to_commands(shape, cfg.excitation.freqs, limit=cfg.robot.command_limit).astype(
        np.float32
    )
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
    """The commands (T, n_joints) of a structured draw and its ``members`` - 1 perturbed copies: command
    noise, and where ``coefficient_noise`` is set, the joint shape's coefficients perturbed first."""
    sc, seed = cfg.structured, _noise_seed(cfg.seed, index, attempt)
    ensemble = perturbed_commands(commands.astype(np.float64), sc.members, seed=seed)
    if sc.coefficient_noise > 0:
        shape, _ = draw_structured(sc, cfg.seed, index, attempt, cfg.robot)
        shapes = perturbed_shapes(shape, sc.members, sc.coefficient_noise, np.random.default_rng([seed, 1]))
        factors = perturbed_commands(np.ones_like(ensemble[0]), sc.members, seed=seed)  # 1 + noise, once
        for m, noisy in enumerate(shapes[1:], start=1):  # the same command noise on the noisy shape
            ensemble[m] = (
                shape_to_commands(noisy, cfg.excitation.freqs, limit=cfg.robot.command_limit) * factors[m]
            )
    return ensemble


def simulate_structured(cfg: GenerateConfig, simulator: Simulator, indices: np.ndarray) -> _Chunk:
    """Draw, screen and measure structured-family records ``indices`` (``sim.gaits.structured``).

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
        }  # (members, T, n_joints) each; the first check is its first screen_members
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
            verdict = "redraw" if broken else sc.verdict(spread, k)
            if verdict == "redraw":
                rejected[j] = broken or f"final spread {spread:.3f} > {sc.max_spread} in the first check"
                continue
            chunk.joint_angles[j] = screen.joint_angles[rows[j][0]]
            chunk.body[j] = screen.body[rows[j][0]]
            if verdict == "keep":  # no second check: this is its spread
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
                if broken or sc.verdict(spread, sc.members) == "redraw":
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


def perturbed_shapes(shape: np.ndarray, k: int, rel_noise: float, rng: np.random.Generator) -> np.ndarray:
    """``shape`` (n_joints, L, 2) and k - 1 copies whose complex coefficients are each multiplied by
    1 + rel_noise * eps (eps complex standard normal): (k, n_joints, L, 2)."""
    c = shape[..., 0] + 1j * shape[..., 1]
    eps = (rng.standard_normal((k - 1, *c.shape)) + 1j * rng.standard_normal((k - 1, *c.shape))) / np.sqrt(2)
    noisy = c[None] * (1.0 + rel_noise * eps)
    return np.concatenate([shape[None], np.stack([noisy.real, noisy.imag], axis=-1)], axis=0)
