"""Inverse design: from where the snake should go to gaits that get there, verified in MuJoCo.

A target is a final position over the 100 s record in the frame of the start (forward, sideways,
metres), optionally a heading change (degrees) and a bound on the net roll (rad). The model proposes:
CMA-ES (the ``cma`` library) over z_B, z_k = 0, minimises the distance of the decoded path's end from
the target plus ``prior_weight`` x the negative log density of the shipped slider sampler (so the
search stays on the data, where the member's predicted path was trained; N(0, I) for a checkpoint
without one), from several starts at once (the best of a screen of sampler draws, each population decoded
in one batch). The best distinct optima are replayed (``sim.physics.backend``: here or on Ray) and MuJoCo
decides: candidates are ranked again by the distance of their own replay's end from the target.
Then physics corrects the model: each of the best verified candidates is searched again near its
z_B for the target moved by its own miss (replay end minus decoded end), for up to ``rounds``
rounds, so a model that errs locally by a steady offset still lands its gait. The reported
candidates are then replayed with command noise, each reported beside that ensemble's spread, so
where physics cannot promise the end ("the paper family") it says so. ``met`` is true only if the
best simulated end is within the tolerance (and the heading and roll bounds, where asked).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from snakeloco.model.api import GaitModel
from snakeloco.model.design.config import OUTSIDE_COST, DesignConfig, Target
from snakeloco.model.design.targets import FORWARD as FORWARD  # re-exported: the search's vocabulary
from snakeloco.model.design.targets import ROLL as ROLL
from snakeloco.model.design.targets import SIDEWAYS as SIDEWAYS
from snakeloco.model.design.targets import YAW as YAW
from snakeloco.model.design.targets import (
    Candidate,
    DesignProgress,
    DesignResult,
    FanCost,
    fan_cost,
    objective,
    path_end,
)
from snakeloco.model.design.verify import measure_spread, meets, rank, verify
from snakeloco.sim.physics.backend import BackendConfig, open_backend


def prior_cost(model: GaitModel, z_b: np.ndarray, cfg: DesignConfig) -> np.ndarray:
    """What leaving the data costs (m), per z_B: ``prior_weight`` x its negative log density, plus
    OUTSIDE_COST per unit of "radius" beyond the bulk. With a shipped slider density (the training
    records' posteriors) the bulk is where 99% of them are (``density.threshold``) and the radius
    beyond it sqrt(2 x the log-density deficit), the Gaussian's own; without one, the N(0, I) prior's
    |z| beyond sqrt(D_b) + ``prior_margin``."""
    density = model.config.density
    if density is None:
        radius = np.linalg.norm(z_b, axis=1)
        outside = np.maximum(radius - (math.sqrt(z_b.shape[1]) + cfg.prior_margin), 0.0)
        return cfg.prior_weight * 0.5 * radius**2 + OUTSIDE_COST * outside
    log_p = density.log_density(z_b)
    outside = np.sqrt(2.0 * np.maximum(density.threshold - log_p, 0.0))
    return cfg.prior_weight * (density.peak_log_density - log_p) + OUTSIDE_COST * outside


def _evolve(
    model: GaitModel,
    starts: list[np.ndarray],
    targets: list[Target],
    cfg: DesignConfig,
    sigma: float,
    generations: int,
    seed: int,
    cancelled: Callable[[], bool] | None,
    fan: FanCost | None = None,
    progress: DesignProgress | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """One CMA-ES run per start, run k minimising ``objective`` for ``targets[k]`` (plus ``fan``'s
    cost, where given); every generation decodes all runs' populations in one batch (``progress``
    told of each). Returns each run's (z seen (n, Db), cost (n,))."""
    import cma

    doing = progress.doing if progress is not None else ""

    runs = [
        cma.CMAEvolutionStrategy(s, sigma, {"popsize": cfg.population, "seed": seed + 1 + k, "verbose": -9})
        for k, s in enumerate(starts)
    ]
    seen: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in runs]
    for g in range(generations):
        if cancelled is not None and cancelled():
            break
        if progress is not None:
            progress.step(f"{doing}, generation {g + 1} of {generations}")
        live = [k for k, r in enumerate(runs) if not r.stop()]
        if not live:
            break
        asked = {k: np.asarray(runs[k].ask()) for k in live}
        z = np.concatenate([asked[k] for k in live])
        _, body = model.decode(z)
        ends, prior = path_end(body), prior_cost(model, z, cfg)  # all runs' populations at once
        fan_ends = fan.ends(z) if fan is not None else None
        for j, k in enumerate(live):
            part = slice(j * cfg.population, (j + 1) * cfg.population)
            miss = objective(ends[part], targets[k], cfg)
            cost = miss + prior[part]
            if fan is not None:
                cost = cost + fan_cost(fan, fan_ends[part], targets[k], miss, cfg)
            runs[k].tell(list(asked[k]), cost.tolist())
            seen[k].append((z[part], cost))
    return [
        (np.concatenate([z for z, _ in run]), np.concatenate([c for _, c in run]))
        if run
        else (np.zeros((0, model.z_b_dim)), np.zeros(0))
        for run in seen
    ]


def _candidates(model: GaitModel, z: np.ndarray, cost: np.ndarray, n: int, rnd: int) -> list[Candidate]:
    """The ``n`` best distinct (> 0.1 apart) of latents ``z`` by ``cost``, decoded."""
    chosen: list[int] = []
    for i in np.argsort(cost):
        if all(np.linalg.norm(z[i] - z[j]) > 0.1 for j in chosen):
            chosen.append(int(i))
        if len(chosen) == n:
            break
    if not chosen:
        return []
    shape, body = model.decode(z[chosen])
    ends = path_end(body)
    return [
        Candidate(z_b=z[i], predicted=ends[k], cost=float(cost[i]), shape=shape[k], round=rnd)
        for k, i in enumerate(chosen)
    ]


def screen_ends(model: GaitModel, cfg: DesignConfig) -> tuple[np.ndarray, np.ndarray]:
    """The search's screen: ``cfg.screen`` draws of the shipped sampler (where the training records
    are; N(0, I) for a checkpoint without a density) and where each decoded path ends (``path_end``)."""
    screen = model.sample_z_b(cfg.screen, seed=cfg.seed)
    _, body = model.decode(screen)
    return screen, path_end(body)


def search(
    model: GaitModel,
    target: Target,
    cfg: DesignConfig,
    cancelled: Callable[[], bool] | None = None,
    screened: tuple[np.ndarray, np.ndarray] | None = None,
    fan: FanCost | None = None,
    progress: DesignProgress | None = None,
) -> list[Candidate]:
    """CMA-ES over z_B from ``cfg.starts`` starts; the ``cfg.candidates`` best distinct optima by
    predicted cost. ``cancelled`` is polled every generation (True: stop and return what there is);
    ``screened``: ``screen_ends`` already computed; ``fan``: a predicted variations fan's cost added."""
    screen, ends = screened if screened is not None else screen_ends(model, cfg)
    miss = objective(ends, target, cfg)
    cost = miss + prior_cost(model, screen, cfg)
    if fan is not None:
        cost = cost + fan_cost(fan, fan.ends(screen), target, miss, cfg)
    starts: list[np.ndarray] = []
    for i in np.argsort(cost):  # the best draws that are not next to one already taken
        if all(np.linalg.norm(screen[i] - s) > cfg.sigma0 for s in starts):
            starts.append(screen[i])
        if len(starts) == cfg.starts:
            break
    runs = _evolve(
        model,
        starts,
        [target] * len(starts),
        cfg,
        cfg.sigma0,
        cfg.generations,
        cfg.seed,
        cancelled,
        fan,
        progress,
    )
    z_all = np.concatenate([screen, *[z for z, _ in runs]])
    c_all = np.concatenate([cost, *[c for _, c in runs]])
    return _candidates(model, z_all, c_all, cfg.candidates, 1)


REACH_MARGIN, REACH_SLACK_M = 1.5, 2.0
"""A target farther than REACH_MARGIN times the family's reach plus REACH_SLACK_M metres
(``nearest_in_reach``) is answered at once: no search, the nearest gait the family has, replayed,
and ``met`` False. The slack keeps a search for targets a few metres off, where refinement on what
physics did may still get there."""


def nearest_in_reach(
    model: GaitModel,
    target: Target,
    cfg: DesignConfig,
    screened: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[float, Candidate] | None:
    """None where ``target`` may be in the family's reach; else (reach in m, the screen's draw whose
    predicted end is nearest the target): a target more than ``REACH_MARGIN`` times farther than any
    gait of the family goes, plus ``REACH_SLACK_M`` (``design --forward 1e6`` searched 5 min before
    saying not met)."""
    distance = float(np.hypot(target.forward, target.sideways))
    screen, ends = screened if screened is not None else screen_ends(model, cfg)
    farthest = float(np.hypot(ends[:, 0], ends[:, 1]).max())
    if distance <= REACH_MARGIN * farthest + REACH_SLACK_M:
        return None
    cost = objective(ends, target, cfg)
    best = int(np.argmin(cost))
    return farthest, _candidates(model, screen[best : best + 1], cost[best : best + 1], 1, 0)[0]


def corrected(target: Target, c: Candidate) -> Target:
    """``target`` moved by what physics did otherwise than ``c``'s decoded path (replay end minus
    decoded end; heading too where asked): the target to search for near ``c`` so that the replay,
    if the model errs there as it did at ``c``, ends on the real one."""
    assert c.simulated is not None
    miss = c.simulated - c.predicted
    return target.model_copy(
        update={
            "forward": target.forward - float(miss[0]),
            "sideways": target.sideways - float(miss[1]),
            "heading": None if target.heading is None else target.heading - float(miss[2]),
        }
    )


def refine(
    model: GaitModel,
    parents: list[Candidate],
    target: Target,
    cfg: DesignConfig,
    rnd: int,
    cancelled: Callable[[], bool] | None = None,
    fan: FanCost | None = None,
    progress: DesignProgress | None = None,
) -> list[Candidate]:
    """One new candidate per verified parent: the best of a short CMA-ES run from the parent's z_B
    towards ``corrected(target, parent)`` (the decoded end's error still measured against that
    corrected target, the candidate's ``cost``; ``fan``'s too)."""
    goals = [corrected(target, p) for p in parents]
    seed = cfg.seed + 1000 * rnd
    runs = _evolve(
        model,
        [p.z_b for p in parents],
        goals,
        cfg,
        cfg.refine_sigma,
        cfg.refine_generations,
        seed,
        cancelled,
        fan,
        progress,
    )
    out: list[Candidate] = []
    for (z, cost), parent in zip(runs, parents, strict=True):
        if len(z) == 0:
            continue
        fresh = [i for i in np.argsort(cost) if np.linalg.norm(z[i] - parent.z_b) > 1e-6]
        if fresh:
            out += _candidates(model, z[fresh[:1]], cost[fresh[:1]], 1, rnd)
    return out


def design(
    model: GaitModel,
    target: Target,
    cfg: DesignConfig | None = None,
    *,
    backend: BackendConfig | None = None,
    runner=None,
    workers: int | None = None,
    cancelled: Callable[[], bool] | None = None,
    progress: DesignProgress | None = None,
    robot=None,
    fan: FanCost | None = None,
    world=None,
) -> DesignResult:
    """Search, verify in MuJoCo (on ``runner``, an open backend, or one opened from ``backend``), and
    refine the best verified candidates for what physics did, for up to ``cfg.rounds`` rounds.
    ``cancelled`` is polled between search generations (True: stop; the result is then not meant to
    be used); ``progress`` (``DesignProgress``) is told each step, the replays it plans and runs. ``robot``: the
    ``sim.robot.description.Robot`` the candidates are verified on where a backend is opened here (default: the
    checkpoint's robot), on ``world`` (``sim.world``; default: the flat plane). ``fan``: the search also minimises a predicted variations fan's miss
    (``model.design.robust.PredictedFan``)."""
    cfg = cfg or DesignConfig()
    progress = progress or DesignProgress()
    search_s = physics_s = 0.0
    own = runner is None
    verified: list[Candidate] = []
    best: list[Candidate] = []
    first: Candidate | None = None
    replays = rounds = 0
    t0 = time.perf_counter()
    screened = screen_ends(model, cfg)  # decoded once: the reach check and the search's starts
    beyond = nearest_in_reach(model, target, cfg, screened) if cfg.reach_check else None
    search_s += time.perf_counter() - t0
    if beyond is not None:  # answered from what the family reaches: its nearest gait, replayed
        reach_m, nearest = beyond
        t0 = time.perf_counter()
        progress.plan(1)
        progress.step("replaying the family's nearest gait (the target is beyond its reach)")
        runner = runner or open_backend(
            backend, workers, robot=robot or model.robot, world=world or model.world
        )
        try:
            verified = verify(model, [nearest], target, cfg, runner, members=1)
        finally:
            if own:
                runner.close()
        progress.step(replays=1, best_m=verified[0].error_m)
        extra = {
            "beyond_reach": {
                "reach_m": reach_m,
                "distance_m": float(np.hypot(target.forward, target.sideways)),
            },
            "first_round_best": None,  # no round was searched
        }
        return DesignResult(
            target,
            cfg.tolerance_for(target),
            verified,
            False,
            search_s,
            time.perf_counter() - t0,
            1,
            0,
            extra,
        )
    planned = progress.plan(cfg.rounds * cfg.candidates + cfg.candidates * (cfg.ensemble - 1))
    try:
        for rnd in range(1, cfg.rounds + 1):
            t0 = time.perf_counter()
            progress.step(f"searching z_B (round {rnd} of at most {cfg.rounds})")
            if rnd == 1:
                proposed = search(model, target, cfg, cancelled, screened, fan, progress)
            else:
                parents = [c for c in verified if c.simulated is not None][: cfg.candidates]
                if not parents:
                    break
                proposed = refine(model, parents, target, cfg, rnd, cancelled, fan, progress)
            search_s += time.perf_counter() - t0
            if (cancelled is not None and cancelled()) or not proposed:
                break
            what = "replaying" if rnd == 1 else "corrected for what physics did: replaying"
            progress.step(f"{what} {len(proposed)} candidates (round {rnd} of at most {cfg.rounds})")
            t0 = time.perf_counter()
            runner = runner or open_backend(
                backend, workers, robot=robot or model.robot, world=world or model.world
            )
            verified = rank(verified + verify(model, proposed, target, cfg, runner, members=1), target, cfg)
            physics_s += time.perf_counter() - t0
            replays += len(proposed)
            rounds = rnd
            progress.step(replays=len(proposed), best_m=verified[0].error_m if verified else None)
            if rnd == 1 and verified:
                first = verified[0]  # what the model alone proposed best, for comparison
            if meets(verified[0], target, cfg):
                break
        best = verified[: cfg.candidates]
        if best and not (cancelled is not None and cancelled()):
            t0 = time.perf_counter()  # physics' own scatter beside each reported error
            progress.step(
                f"measuring physics' scatter: {cfg.ensemble - 1} noisy copies of the {len(best)} best"
            )
            spread = measure_spread(model, best, cfg, runner)
            replays += spread
            physics_s += time.perf_counter() - t0
            progress.step(replays=spread)
    finally:
        if own and runner is not None:
            runner.close()
        progress.settle(planned - replays)
    met = bool(best) and meets(best[0], target, cfg)
    extra = {"first_round_best": first}
    return DesignResult(
        target, cfg.tolerance_for(target), best, met, search_s, physics_s, replays, rounds, extra
    )
