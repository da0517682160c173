"""``snakeloco bench design``: inverse design against a baseline with the same physics budget.

Targets are the final positions (and, for every other target, the heading change) of held-out
records: places this robot does reach. For each, ``model.design`` searches and verifies
``candidates`` x ``ensemble`` replays; the baseline spends the same number of replays on gaits of z_B
drawn from the prior (z_k = 0, one replay each) and keeps the best by the same simulated objective.
The design's best after its first round (the model's proposals alone, before physics corrects them)
is reported beside its final best.
Figures: the best verified candidate's distance from the target relative to the target's distance
(median, 90th percentile), its heading error where asked, the share met, the baseline's same
figures, time to an answer (p50, p95) split into search and physics, and one unreachable target.
"""

from __future__ import annotations

import time

import numpy as np

from snakeloco.model import load_pretrained
from snakeloco.model.design import (
    Candidate,
    design,
    meets,
    path_end,
    simulated_cost,
    verify,
)
from snakeloco.model.design_config import DesignConfig, Target
from snakeloco.sim import load_dataset
from snakeloco.sim.backend import open_backend

UNREACHABLE = Target(forward=100.0, sideways=0.0)


def _targets(data, n: int, seed: int) -> list[Target]:
    ds = load_dataset(data)
    rows = np.random.default_rng(seed).choice(len(ds), size=min(n, len(ds)), replace=False)
    ends = path_end(ds.body_ds[np.sort(rows)].astype(np.float64))
    return [
        Target(forward=float(e[0]), sideways=float(e[1]), heading=float(e[2]) if i % 2 else None)
        for i, e in enumerate(ends)
    ]


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
    data,
    targets: int = 50,
    seed: int = 1,
    candidates: int = 4,
    workers: int | None = None,
    rounds: int = DesignConfig().rounds,
    log=print,
) -> dict:
    """Design for ``targets`` held-out ends, and the baseline; returns the figures (module docstring)."""
    model = load_pretrained(checkpoint)
    cfg = DesignConfig(candidates=candidates, seed=seed, rounds=rounds)
    goals = _targets(data, targets, seed)
    runner = open_backend(None, workers)
    designed, first, baseline, seconds, search_s, physics_s, budgets = [], [], [], [], [], [], []
    rng = np.random.default_rng(seed + 1)
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
            z = rng.standard_normal((budget, model.z_b_dim))
            shape, body = model.decode(z)
            draws = [
                Candidate(z_b=z[i], predicted=e, cost=0.0, shape=shape[i])
                for i, e in enumerate(path_end(body))
            ]
            one = cfg.model_copy(update={"ensemble": 1})
            checked = verify(model, draws, target, one, runner)
            baseline.append(min(checked, key=lambda c: simulated_cost(c, target, cfg)))
            log(
                f"target {k + 1}/{len(goals)} ({target.forward:.2f}, {target.sideways:.2f}) m"
                + (f", heading {target.heading:.1f} deg" if target.heading is not None else "")
                + f": design {designed[-1].error_m:.2f} m off (round 1: {first[-1].error_m:.2f} m; "
                f"{result.rounds} rounds, {'met' if result.met else 'not met'}), baseline "
                f"{baseline[-1].error_m:.2f} m off, {budget} replays each ({seconds[-1]:.1f} s: search "
                f"{result.search_s:.1f} s, physics {result.physics_s:.1f} s)"
            )
        far = design(model, UNREACHABLE, cfg, runner=runner)
    finally:
        runner.close()
    closest = far.candidates[0].simulated
    return {
        "checkpoint": str(model.path),
        "targets": len(goals),
        "candidates": cfg.candidates,
        "rounds": cfg.rounds,
        "physics_budget_replays": budgets,
        "design": _figures(designed, goals, cfg),
        # (only the reported candidates get noisy copies: a first round's best has no spread of its own)
        "design_first_round": _figures(first, goals, cfg) | {"spread_m_median": None},
        "baseline": _figures(baseline, goals, cfg),
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
