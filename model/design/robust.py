"""Robust inverse design: gaits that end at the target on other robots too (``design --robust``).

The nominal search (``model.design.search``) proposes and verifies candidates on the nominal robot; here
each verified candidate is replayed on every variation of the default set (``sim.robot.variations``: one
batch of varied models per candidate, on the same backend) and the candidates are ranked again by
their *worst-case* error: the largest distance from the target of the nominal replay's and every
variation's end (a variation that breaks the simulation counts as missing by its nominal error plus
the target's distance), those that meet the target on the nominal robot first. Every reported
candidate's worst case was replayed: none is ranked on a prediction. The report gives each
candidate's nominal error, its worst and p90 errors over the set and which variation is worst.

With a checkpoint that has a physics head (``model.heads.physics_head``), the search itself minimises
the predicted worst (or p90) miss over the variations beside the nominal one (``PredictedFan``:
the fan predicted for every z_B the search decodes, no replay), so the verified optima are
already the gaits the model expects to hold; the replays then confirm it. The nominal search's
answer (``design`` with the same config) is verified and replayed beside them, so where it meets the
target the robust answer's replayed worst case is never worse than it. Without a physics head, it
ranks the nominal search's verified optima.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.design.search import Candidate, DesignResult, design
from snakeloco.model.design.targets import DesignProgress
from snakeloco.sim.physics.backend import open_backend
from snakeloco.sim.robot.variations import DEFAULT_SET, Variation

PREDICT_ROWS = 2048
"""Physics-head rows predicted at a time (each a (500, 6) path: 24 MB in float64)."""


@dataclass
class PredictedFan:
    """The search's ``FanCost`` from the physics head: where each z_B's member ends on each robot."""

    model: object
    robots: list
    score: str = "worst"
    weight: float = 1.0
    features: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        from snakeloco.model.heads.physics_head import physics_features

        self.features = physics_features(self.robots, self.model.robot)

    def ends(self, z_b: np.ndarray) -> np.ndarray:
        members = self.model.decode_members(np.asarray(z_b), with_stats=False)[0]
        v = len(self.features)
        rows = [m for m in members for _ in range(v)]
        feats = np.tile(self.features, (len(members), 1))
        out = np.zeros((len(rows), 2))
        for s in range(0, len(rows), PREDICT_ROWS):
            paths = self.model.members.predict_physics_paths(
                rows[s : s + PREDICT_ROWS], feats[s : s + PREDICT_ROWS]
            )
            out[s : s + PREDICT_ROWS] = paths[:, -1, 1:3] - paths[:, 0, 1:3]
        return out.reshape(len(members), v, 2)

    def misses(self, ends: np.ndarray, target: Target) -> np.ndarray:
        """(n, V) distances (m) of the predicted ends from ``target``."""
        return np.hypot(ends[..., 0] - target.forward, ends[..., 1] - target.sideways)

    def cost(self, ends: np.ndarray, target: Target) -> np.ndarray:
        miss = self.misses(ends, target)
        return self.weight * (miss.max(axis=1) if self.score == "worst" else np.percentile(miss, 90, axis=1))


def simulate_variations(simulator, job: tuple) -> tuple[np.ndarray, list[str | None]]:
    """A backend job: one gait's commands (T, J) on each variation of the simulator's robot; where
    each replay ends, (V, 2) forward and sideways m at the record's last sample (the end
    ``sim.scores.robustness`` reports, so ``snakeloco robustness`` on the written gait gives the same
    numbers), and each replay's break reason."""
    commands, variations = job
    robots = [v.apply(simulator.robot) for v in variations]
    result = simulator.simulate(np.repeat(commands[None], len(robots), axis=0), robots=robots)
    return result.body[:, -1, 1:3] - result.body[:, 0, 1:3], result.failures


def worst_case(
    candidates: list[Candidate],
    model,
    target: Target,
    runner,
    variations=DEFAULT_SET,
    progress: DesignProgress | None = None,
) -> list[dict]:
    """Each verified candidate's error over ``variations`` (replayed on ``runner``, a backend;
    ``progress`` told of each candidate's replays as they finish)."""
    jobs = [(model.commands(c.shape), tuple(variations)) for c in candidates]
    results = {}
    for i, result in runner.map(simulate_variations, jobs):
        results[i] = result
        if progress is not None:
            progress.step(replays=len(variations))
    base = float(np.hypot(target.forward, target.sideways))
    out = []
    for i, c in enumerate(candidates):
        ends, failures = results[i]
        errors, names = [c.error_m], ["nominal"]
        for v, end, failure in zip(variations, ends, failures, strict=True):
            if failure is not None:
                errors.append(c.error_m + base)
            else:
                errors.append(float(np.hypot(end[0] - target.forward, end[1] - target.sideways)))
            names.append(v.name)
        errors = np.array(errors)
        worst = int(np.argmax(errors))
        out.append(
            {
                "worst_m": float(errors.max()),
                "p90_m": float(np.percentile(errors, 90)),
                "worst_variation": names[worst],
                "broken": [v.name for v, f in zip(variations, failures, strict=True) if f is not None],
                "replayed": len(variations),
            }
        )
    return out


def rank_by_worst(
    candidates: list, scores: list[dict], nominal: list[float], tolerance: float, n: int, key: str = "worst_m"
):
    """The best ``n`` candidates, those that meet the target on the nominal robot (``nominal`` m within
    ``tolerance``) first, then by ``scores[i][key]``: (candidates, their scores, met), met where the
    best one's nominal error and worst case are both within the tolerance."""
    order = sorted(range(len(candidates)), key=lambda i: (nominal[i] > tolerance, scores[i][key]))[:n]
    ranked, robust = [candidates[i] for i in order], [scores[i] for i in order]
    met = bool(ranked) and nominal[order[0]] <= tolerance and robust[0]["worst_m"] <= tolerance
    return ranked, robust, met


def _among(c: Candidate, others: list[Candidate]) -> bool:
    return any(np.array_equal(c.z_b, o.z_b) for o in others)


def robust_design(
    model,
    target: Target,
    cfg: DesignConfig | None = None,
    *,
    backend=None,
    workers: int | None = None,
    robot=None,
    variations: tuple[Variation, ...] = DEFAULT_SET,
    score: str = "worst",
    runner=None,
    cancelled=None,
    progress: DesignProgress | None = None,
    predicted: bool = True,
    world=None,
) -> DesignResult:
    """Design for ``target`` (twice the candidates; searching with the physics head's predicted fan
    over ``variations`` where the checkpoint has one and ``predicted``), then rank the verified
    candidates by their ``score`` ("worst" or "p90") error over ``variations`` (every one
    replayed), those whose nominal error is within the tolerance first. ``met``: the best one's
    nominal and worst-case errors both within the tolerance. ``runner``: an open backend to replay
    on (the designer's turns; left open), else one opened here (on ``world``); ``cancelled`` and ``progress`` as
    ``design``'s."""
    cfg = cfg or DesignConfig()
    progress = progress or DesignProgress()
    wide = cfg.model_copy(update={"candidates": min(2 * cfg.candidates, 32)})
    own = runner is None
    robot = robot or model.robot
    fan = None
    if predicted and getattr(model, "physics_head", None) is not None:
        fan = PredictedFan(model, [v.apply(robot) for v in variations], score)
    runner = runner or open_backend(backend, workers, robot=robot, world=world)
    # Every candidate the searches may verify, replayed on each variation (given back once known).
    on_others = progress.plan(
        (wide.candidates + (cfg.candidates if fan is not None else 0)) * len(variations)
    )
    try:
        result = design(model, target, wide, runner=runner, cancelled=cancelled, progress=progress, fan=fan)
        verified = [c for c in result.candidates if c.simulated is not None]
        searches = [result]
        if fan is not None and not (cancelled is not None and cancelled()):
            # The nominal search's answer competes too: asking for robustness never returns a gait
            # whose replayed worst case is worse than the answer the nominal design gives.
            searches.append(design(model, target, cfg, runner=runner, cancelled=cancelled, progress=progress))
            verified += [
                c for c in searches[-1].candidates if c.simulated is not None and not _among(c, verified)
            ]
        if cancelled is not None and cancelled():
            verified = []
        progress.settle(on_others - len(verified) * len(variations))
        progress.step(f"replaying {len(verified)} candidates on {len(variations)} other robots")
        scores = worst_case(verified, model, target, runner, variations, progress) if verified else []
    finally:
        if own:
            runner.close()
    key = "worst_m" if score == "worst" else "p90_m"
    # Those that reach the target on the nominal robot first: robustness is not bought with the
    # nominal error.
    ranked, robust, met = rank_by_worst(
        verified, scores, [c.error_m for c in verified], result.tolerance_m, cfg.candidates, key
    )
    if fan is not None and ranked:  # what the search expected of each, beside what the replays said
        misses = fan.misses(fan.ends(np.stack([c.z_b for c in ranked])), target)
        for r, m in zip(robust, misses, strict=True):
            r["predicted_worst_m"] = float(m.max())
            r["predicted_p90_m"] = float(np.percentile(m, 90))
    return DesignResult(
        target=target,
        tolerance_m=result.tolerance_m,
        candidates=ranked,
        met=met,
        search_s=sum(s.search_s for s in searches),
        physics_s=sum(s.physics_s for s in searches),
        replays=sum(s.replays for s in searches) + len(verified) * len(variations),
        rounds=result.rounds,
        extra={
            **result.extra,
            "robust": robust,
            "score": score,
            "nominal_best": searches[-1].candidates[:1],
            "searched_with": "predicted variations fan" if fan is not None else "nominal path",
        },
    )
