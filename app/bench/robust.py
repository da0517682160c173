"""``snakeloco bench robust``: robust design against nominal design on the same targets.

Targets: final positions at distances uniform in ``reach`` (m), directions uniform all round (as
``bench design --reach``). For each, nominal design (``model.design.search``) and robust design
(``model.design.robust``: with a physics head the search minimises the predicted fan's worst miss
too) answer; the nominal design's best candidate is then replayed on every variation of the
default set as the robust one's are, so both are judged by the same replayed worst case. Figures,
relative to the target's distance: each answer's nominal error and worst-case error over the set
(medians, p90), the robust/nominal ratio of the worst cases (median over the targets), the robust
answer's predicted worst beside its replayed one, and the time to an answer (p50, p95).
"""

from __future__ import annotations

import time

import numpy as np

from snakeloco.app.bench.design import _uniform_targets
from snakeloco.model import load_pretrained
from snakeloco.model.design.config import DesignConfig
from snakeloco.model.design.robust import robust_design, worst_case
from snakeloco.model.design.search import design
from snakeloco.sim.physics.backend import open_backend


def _summary(rows: list[dict], key: str) -> dict:
    values = np.array([r[key] for r in rows], np.float64)
    return {"median": float(np.nanmedian(values)), "p90": float(np.nanpercentile(values, 90))}


def bench_robust(
    checkpoint=None,
    targets: int = 20,
    reach: tuple[float, float] = (2.0, 15.0),
    seed: int = 1,
    candidates: int = 2,
    rounds: int = DesignConfig().rounds,
    workers: int | None = None,
    log=print,
) -> dict:
    """Nominal and robust design on ``targets`` uniform targets ``reach`` m away; the figures
    (module docstring)."""
    if not 0 < reach[0] <= reach[1]:
        raise ValueError(f"bench robust: reach must be 0 < min <= max metres, got {reach}")
    model = load_pretrained(checkpoint)
    cfg = DesignConfig(candidates=candidates, seed=seed, rounds=rounds, reach_check=False)
    goals = _uniform_targets(targets, reach, seed)
    runner = open_backend(None, workers, robot=model.robot)
    rows = []
    try:
        for k, target in enumerate(goals):
            d = target.distance
            t0 = time.perf_counter()
            nominal = design(model, target, cfg, runner=runner)
            nominal_s = time.perf_counter() - t0
            best = nominal.candidates[0]
            nominal_worst = (
                worst_case([best], model, target, runner)[0] if best.simulated is not None else None
            )
            t0 = time.perf_counter()
            robust = robust_design(model, target, cfg, runner=runner)
            robust_s = time.perf_counter() - t0
            top, r = (robust.candidates[0], robust.extra["robust"][0]) if robust.candidates else (None, None)
            row = {
                "target": [target.forward, target.sideways],
                "distance_m": d,
                "nominal_error_rel": best.error_m / d if best.simulated is not None else np.nan,
                "nominal_worst_rel": nominal_worst["worst_m"] / d if nominal_worst else np.nan,
                "nominal_s": nominal_s,
                "robust_error_rel": top.error_m / d if top is not None else np.nan,
                "robust_worst_rel": r["worst_m"] / d if r else np.nan,
                "robust_worst_variation": r["worst_variation"] if r else None,
                "robust_predicted_worst_rel": r.get("predicted_worst_m", np.nan) / d if r else np.nan,
                "robust_s": robust_s,
                "searched_with": robust.extra["searched_with"],
            }
            row["worst_ratio"] = row["robust_worst_rel"] / row["nominal_worst_rel"]
            rows.append(row)
            log(
                f"target {k + 1}/{len(goals)} ({target.forward:.2f}, {target.sideways:.2f}) m: nominal design "
                f"{100 * row['nominal_error_rel']:.0f}% off, worst {100 * row['nominal_worst_rel']:.0f}%; robust "
                f"{100 * row['robust_error_rel']:.0f}% off, worst {100 * row['robust_worst_rel']:.0f}% "
                f"(predicted {100 * row['robust_predicted_worst_rel']:.0f}%, {row['robust_worst_variation']}); "
                f"{nominal_s:.0f} s / {robust_s:.0f} s"
            )
    finally:
        runner.close()
    return {
        "checkpoint": str(model.path),
        "targets": len(goals),
        "reach_m": list(reach),
        "candidates": candidates,
        "searched_with": rows[0]["searched_with"] if rows else None,
        "rows": rows,
        **{
            k: _summary(rows, k)
            for k in (
                "nominal_error_rel",
                "nominal_worst_rel",
                "robust_error_rel",
                "robust_worst_rel",
                "robust_predicted_worst_rel",
                "worst_ratio",
            )
        },
        "worst_halved_share": float(np.mean([r["worst_ratio"] <= 0.5 for r in rows])) if rows else None,
        "nominal_s": {
            "p50": float(np.percentile([r["nominal_s"] for r in rows], 50)),
            "p95": float(np.percentile([r["nominal_s"] for r in rows], 95)),
        },
        "robust_s": {
            "p50": float(np.percentile([r["robust_s"] for r in rows], 50)),
            "p95": float(np.percentile([r["robust_s"] for r in rows], 95)),
        },
    }
