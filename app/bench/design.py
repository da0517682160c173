"""``snakeloco bench design``: inverse design against a baseline with the same physics budget.

Targets are the final positions (and, for every other target, the heading change) of held-out
records, places this robot does reach; or (``reach``) final positions drawn uniformly between two
distances in every direction. For each, ``model.design.search`` searches and verifies; the baseline spends
the same number of replays on random gaits of the data (z_B from the shipped sampler, N(0, I)
without one; z_k = 0, one replay each) and keeps the best by the same simulated objective. The
design's best after its first round (the model's proposals alone, before physics corrects them) is
reported beside its final best, and against the baseline on that round's budget alone.
Figures: the best verified candidate's distance from the target relative to the target's distance
(median, 90th percentile), its heading error where asked, the share met, the baseline's same
figures, time to an answer (p50, p95) split into search and physics, and one unreachable target.
"""

from __future__ import annotations

import time

import numpy as np

from snakeloco.model import load_pretrained
from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.design.search import Candidate, design, path_end
from snakeloco.model.design.verify import meets, simulated_cost, verify
from snakeloco.sim import load_dataset
from snakeloco.sim.physics.backend import open_backend

UNREACHABLE = Target(forward=100.0, sideways=0.0)


def _targets(data, n: int, seed: int) -> list[Target]:
    ds = load_dataset(data)
    rows = np.random.default_rng(seed).choice(len(ds), size=min(n, len(ds)), replace=False)
    ends = path_end(ds.body_ds[np.sort(rows)].astype(np.float64))
    return [
        Target(forward=float(e[0]), sideways=float(e[1]), heading=float(e[2]) if i % 2 else None)
        for i, e in enumerate(ends)
    ]


def _uniform_targets(n: int, reach: tuple[float, float], seed: int) -> list[Target]:
    """n final positions at distances uniform in ``reach`` (m), directions uniform all round."""
    u = np.random.default_rng(seed).random((n, 2))  # row by row: the first k targets of n are those of k
    distance = reach[0] + (reach[1] - reach[0]) * u[:, 0]
    angle = np.pi * (2 * u[:, 1] - 1)
    return [
        Target(forward=float(d * np.cos(a)), sideways=float(d * np.sin(a)))
        for d, a in zip(distance, angle, strict=True)
    ]


def _random_draws(model, runner, target: Target, n: int, cfg: DesignConfig, seed: int) -> list[Candidate]:
    """``n`` random gaits of the data (sampler draws, z_k = 0), one replay each, in draw order."""
    z = model.sample_z_b(n, seed=seed)
    shape, body = model.decode(z)
    draws = [Candidate(z_b=z[i], predicted=e, cost=0.0, shape=shape[i]) for i, e in enumerate(path_end(body))]
    verify(model, draws, target, cfg.model_copy(update={"ensemble": 1}), runner)
    return draws


def _best(draws: list[Candidate], target: Target, cfg: DesignConfig) -> Candidate:
    return min(draws, key=lambda c: simulated_cost(c, target, cfg))


def _figures(best: list[Candidate], targets: list[Target], cfg: DesignConfig) -> dict:
    pairs = list(zip(best, targets, strict=True))
    rel = np.array([c.error_m / max(t.distance, 1e-9) for c, t in pairs])
    heading = np.array(
        [c.heading_error for c, t in pairs if t.heading is not None and c.heading_error is not None]
    )
    return {
        "error_rel_median": float(np.median(rel)),
        "error_rel_p90": float(np.percentile(rel, 90)),
        "met_share": float(np.mean([meets(c, t, cfg) for c, t in pairs])),
        "heading_error_deg_median": float(np.median(heading)) if len(heading) else None,
        "heading_error_deg_p90": float(np.percentile(heading, 90)) if len(heading) else None,
        "spread_m_median": float(np.median(spread))
        if len(spread := [c.spread_m for c in best if c.spread_m == c.spread_m])
        else None,
    }


def bench_design(
    checkpoint,
    data=None,
    targets: int = 50,
    seed: int = 1,
    candidates: int = 4,
    workers: int | None = None,
    rounds: int = DesignConfig().rounds,
    reach: tuple[float, float] | None = None,
    log=print,
) -> dict:
    """Design for ``targets`` held-out ends of ``data`` (or uniform ones ``reach`` m away), and the
    baselines; returns the figures (module docstring)."""
    if (data is None) == (reach is None):
        raise ValueError("bench design: give a held-out dataset or a reach (min, max metres), not both")
    if reach is not None and not 0 < reach[0] <= reach[1]:
        raise ValueError(f"bench design: reach must be 0 < min <= max metres, got {reach}")
    model = load_pretrained(checkpoint)
    cfg = DesignConfig(
        candidates=candidates, seed=seed, rounds=rounds, reach_check=False
    )  # the search itself
    goals = _targets(data, targets, seed) if reach is None else _uniform_targets(targets, reach, seed)
    runner = open_backend(None, workers, robot=model.robot)  # the checkpoint's robot, not the default
    designed, first, baseline, baseline_first = [], [], [], []
    seconds, search_s, physics_s, budgets = [], [], [], []
    try:
        for k, target in enumerate(goals):
            t0 = time.perf_counter()
            result = design(model, target, cfg, runner=runner)
            seconds.append(time.perf_counter() - t0)
            search_s.append(result.search_s)
            physics_s.append(result.physics_s)
            designed.append(result.candidates[0])
            first.append(result.extra["first_round_best"])
            budget = result.replays  # the baseline gets as many replays as the design used
            budgets.append(budget)
            draws = _random_draws(model, runner, target, budget, cfg, 10_000 * (seed + 1) + k)
            baseline.append(_best(draws, target, cfg))
            # the first round's budget (one replay per proposal): the first of the same draws
            baseline_first.append(_best(draws[: cfg.candidates], target, cfg))
            log(
                f"target {k + 1}/{len(goals)} ({target.forward:.2f}, {target.sideways:.2f}) m"
                + (f", heading {target.heading:.1f} deg" if target.heading is not None else "")
                + f": design {designed[-1].error_m:.2f} m off (round 1: {first[-1].error_m:.2f} m; "
                f"{result.rounds} rounds, {'met' if result.met else 'not met'}), random draws "
                f"{baseline[-1].error_m:.2f} m off ({budget} replays; {baseline_first[-1].error_m:.2f} m "
                f"with round 1's {cfg.candidates}) ({seconds[-1]:.1f} s: search "
                f"{result.search_s:.1f} s, physics {result.physics_s:.1f} s)"
            )
        far = design(model, UNREACHABLE, cfg, runner=runner)
    finally:
        runner.close()
    closest = far.candidates[0].simulated
    return {
        "checkpoint": str(model.path),
        "targets": len(goals),
        "target_source": "held-out ends"
        if reach is None
        else f"uniform {reach[0]:g}-{reach[1]:g} m, all round",
        "candidates": cfg.candidates,
        "rounds": cfg.rounds,
        "physics_budget_replays": budgets,
        "design": _figures(designed, goals, cfg),
        # (only the reported candidates get noisy copies: a first round's best has no spread of its own)
        "design_first_round": _figures(first, goals, cfg) | {"spread_m_median": None},
        "baseline": _figures(baseline, goals, cfg),
        "baseline_first_round_budget": _figures(baseline_first, goals, cfg),
        "seconds_p50": float(np.percentile(seconds, 50)),
        "seconds_p95": float(np.percentile(seconds, 95)),
        "search_s_median": float(np.median(search_s)),
        "physics_s_median": float(np.median(physics_s)),
        "unreachable": {
            "target_m": UNREACHABLE.distance,
            "met": far.met,
            "closest_reached_m": None if closest is None else [float(closest[0]), float(closest[1])],
            "error_m": far.candidates[0].error_m,
        },
    }
