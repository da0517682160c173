"""Inverse design: from where the snake should go to gaits that get there, verified in MuJoCo.

A target is a final position over the 100 s record in the frame of the start (forward, sideways,
metres), optionally a heading change (degrees) and a bound on the net roll (rad). The model proposes:
CMA-ES (the ``cma`` library) over z_B, z_k = 0, minimises the distance of the decoded path's end from
the target plus ``prior_weight`` x the negative log prior (so the search stays where the model was
trained), from several starts at once (the best of a screen of prior draws, each population decoded
in one batch). The best distinct optima are replayed as small ensembles (``sim.backend``: here or on
Ray) and MuJoCo decides: candidates are ranked again by the distance of their own replay's end from
the target, each reported beside its ensemble spread, so where physics cannot promise the end
("the paper family") it says so. ``met`` is true only if the best simulated end is within the
tolerance (and the heading and roll bounds, where asked).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.model.api import GaitModel
from snakeloco.model.replays import replay_shapes
from snakeloco.sim.backend import BackendConfig, open_backend

FORWARD, SIDEWAYS, ROLL, YAW = 1, 2, 3, 5  # body channels (sim.BODY_CHANNELS)
OUTSIDE_COST = 10.0
"""Metres of error per unit of z_B radius beyond the prior's bulk (``DesignConfig.prior_margin``)."""
VERIFY_ENSEMBLE = 4
"""Replays per verified candidate: its own and 3 with 1e-3 relative command noise."""


class Target(BaseModel):
    """Where the gait should take the snake in the 100 s record, in the frame of its start."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    forward: float = Field(description="Final forward displacement (m).")
    sideways: float = Field(description="Final sideways displacement (m; positive to the left).")
    heading: float | None = Field(None, description="Heading change (degrees, positive to the left).")
    max_roll: float | None = Field(None, gt=0, description="Largest |net roll| allowed (rad).")

    @property
    def distance(self) -> float:
        return math.hypot(self.forward, self.sideways)


class DesignConfig(BaseModel):
    """How the search and the verification run."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    candidates: int = Field(4, ge=1, le=32, description="Candidates verified in MuJoCo and reported.")
    seed: int = Field(
        0, ge=0, description="Seed of the search (prior screen, CMA-ES) and the ensemble noise."
    )
    tolerance: float | None = Field(
        None,
        gt=0,
        description="Distance (m) within which a target counts as met (default: 10% of the "
        "target distance, at least 0.25 m).",
    )
    heading_tolerance: float = Field(
        15.0, gt=0, description="Heading error (deg) within which it counts as met."
    )
    screen: int = Field(512, ge=1, description="Prior draws decoded to pick the starts of the search.")
    starts: int = Field(8, ge=1, description="CMA-ES runs, from the best distinct draws of the screen.")
    generations: int = Field(40, ge=1, description="CMA-ES generations per run.")
    population: int = Field(12, ge=4, description="CMA-ES population per generation.")
    sigma0: float = Field(0.5, gt=0, description="CMA-ES initial step (prior units).")
    prior_weight: float = Field(
        0.05, ge=0, description="Metres of error one unit of negative log prior (|z|^2 / 2) costs."
    )
    prior_margin: float = Field(
        3.0,
        gt=0,
        description="z_B farther than sqrt(D_b) + this from the prior's mean (beyond ~99.9% of "
        "its mass, where the model saw no data) costs OUTSIDE_COST metres per unit.",
    )
    heading_weight: float = Field(0.05, ge=0, description="Metres of error one degree of heading costs.")
    roll_weight: float = Field(
        2.0, ge=0, description="Metres of error one radian of roll over the bound costs."
    )
    ensemble: int = Field(VERIFY_ENSEMBLE, ge=2, description="Replays per verified candidate.")

    @model_validator(mode="after")
    def _enough_starts(self) -> DesignConfig:
        if self.screen < self.starts:
            raise ValueError(f"screen ({self.screen}) must hold at least the {self.starts} starts")
        return self

    def tolerance_for(self, target: Target) -> float:
        return self.tolerance if self.tolerance is not None else max(0.1 * target.distance, 0.25)


def path_end(body: np.ndarray) -> np.ndarray:
    """(..., 500, 6) body series -> (..., 4): final forward, sideways (m), heading change (deg) and
    net roll (rad) relative to the start."""
    end, start = body[..., -1, :], body[..., 0, :]
    return np.stack(
        [
            end[..., FORWARD] - start[..., FORWARD],
            end[..., SIDEWAYS] - start[..., SIDEWAYS],
            np.degrees(end[..., YAW] - start[..., YAW]),
            end[..., ROLL] - start[..., ROLL],
        ],
        axis=-1,
    )


def objective(ends: np.ndarray, z_b: np.ndarray, target: Target, cfg: DesignConfig) -> np.ndarray:
    """What the search minimises (m), per row of ``ends`` (``path_end``) and z_B."""
    cost = np.hypot(ends[:, 0] - target.forward, ends[:, 1] - target.sideways)
    if target.heading is not None:
        cost = cost + cfg.heading_weight * np.abs(ends[:, 2] - target.heading)
    if target.max_roll is not None:
        cost = cost + cfg.roll_weight * np.maximum(np.abs(ends[:, 3]) - target.max_roll, 0.0)
    radius = np.linalg.norm(z_b, axis=1)
    outside = np.maximum(radius - (math.sqrt(z_b.shape[1]) + cfg.prior_margin), 0.0)
    return cost + cfg.prior_weight * 0.5 * radius**2 + OUTSIDE_COST * outside


@dataclass
class Candidate:
    """A proposed gait and, once verified, what MuJoCo did with it."""

    z_b: np.ndarray  # (Db,)
    predicted: np.ndarray  # (4,) path_end of the decoded path
    cost: float  # the search's objective
    shape: np.ndarray  # (8, L, 2) rad, z_k = 0
    simulated: np.ndarray | None = None  # (4,) path_end of its own replay
    spread_m: float = float("nan")  # RMS distance of the perturbed replays' ends from its own
    broken: str | None = None
    error_m: float = float("inf")
    heading_error: float | None = None

    def report(self) -> dict:
        ends = {"predicted": self.predicted, "simulated": self.simulated}
        return {
            "z_b": self.z_b.tolist(),
            **{
                k: None
                if v is None
                else {"forward": float(v[0]), "sideways": float(v[1]), "heading": float(v[2])}
                for k, v in ends.items()
            },
            "net_roll": None if self.simulated is None else float(self.simulated[3]),
            "error_m": float(self.error_m),
            "heading_error_deg": self.heading_error,
            "ensemble_spread_m": float(self.spread_m),
            "broken": self.broken,
        }


@dataclass
class DesignResult:
    target: Target
    tolerance_m: float
    candidates: list[Candidate]  # best first (by simulated error)
    met: bool
    search_s: float
    physics_s: float
    extra: dict = field(default_factory=dict)


def search(
    model: GaitModel, target: Target, cfg: DesignConfig, cancelled: Callable[[], bool] | None = None
) -> list[Candidate]:
    """CMA-ES over z_B from ``cfg.starts`` starts; the ``cfg.candidates`` best distinct optima by
    predicted cost. ``cancelled`` is polled every generation (True: stop and return what there is)."""
    import cma

    rng = np.random.default_rng(cfg.seed)
    dim = model.z_b_dim
    screen = rng.standard_normal((cfg.screen, dim))
    _, body = model.decode(screen)
    cost = objective(path_end(body), screen, target, cfg)
    starts: list[np.ndarray] = []
    for i in np.argsort(cost):  # the best draws that are not next to one already taken
        if all(np.linalg.norm(screen[i] - s) > cfg.sigma0 for s in starts):
            starts.append(screen[i])
        if len(starts) == cfg.starts:
            break
    runs = [
        cma.CMAEvolutionStrategy(
            s, cfg.sigma0, {"popsize": cfg.population, "seed": cfg.seed + 1 + k, "verbose": -9}
        )
        for k, s in enumerate(starts)
    ]
    seen_z, seen_cost = [screen], [cost]
    for _ in range(cfg.generations):
        if cancelled is not None and cancelled():
            break
        live = [r for r in runs if not r.stop()]
        if not live:
            break
        asked = [np.asarray(r.ask()) for r in live]
        z = np.concatenate(asked)
        _, body = model.decode(z)  # every run's population in one batch
        c = objective(path_end(body), z, target, cfg)
        seen_z.append(z)
        seen_cost.append(c)
        for k, r in enumerate(live):
            part = slice(k * cfg.population, (k + 1) * cfg.population)
            r.tell(list(asked[k]), c[part].tolist())
    z_all, c_all = np.concatenate(seen_z), np.concatenate(seen_cost)
    chosen: list[int] = []
    for i in np.argsort(c_all):
        if all(np.linalg.norm(z_all[i] - z_all[j]) > 0.1 for j in chosen):
            chosen.append(int(i))
        if len(chosen) == cfg.candidates:
            break
    z_best = z_all[chosen]
    shape, body = model.decode(z_best)
    ends = path_end(body)
    return [
        Candidate(z_b=z_best[k], predicted=ends[k], cost=float(c_all[i]), shape=shape[k])
        for k, i in enumerate(chosen)
    ]


def verify(
    model: GaitModel, candidates: list[Candidate], target: Target, cfg: DesignConfig, backend
) -> list[Candidate]:
    """Replay each candidate as an ensemble of ``cfg.ensemble``; rank by its own replay's error."""
    shapes = np.stack([c.shape for c in candidates])
    bodies, ok = replay_shapes(model, shapes, backend, cfg.ensemble, seed=cfg.seed)
    for c, body, fine in zip(candidates, bodies.astype(np.float64), ok, strict=True):
        if not fine[0]:
            c.broken = "its replay broke the simulation"
            continue
        ends = path_end(body[fine])  # (k, 4): its own replay first
        c.simulated = ends[0]
        c.error_m = float(math.hypot(ends[0, 0] - target.forward, ends[0, 1] - target.sideways))
        if target.heading is not None:
            c.heading_error = float(abs(ends[0, 2] - target.heading))
        offsets = ends[1:, :2] - ends[0, :2]
        c.spread_m = float(np.sqrt((offsets**2).sum(axis=1).mean())) if len(offsets) else float("nan")
    return sorted(candidates, key=lambda c: (c.broken is not None, simulated_cost(c, target, cfg)))


def simulated_cost(c: Candidate, target: Target, cfg: DesignConfig) -> float:
    """What ranks verified candidates: the search's objective on the replay's end (no prior term)."""
    if c.simulated is None:
        return float("inf")
    return float(
        objective(c.simulated[None], np.zeros((1, 1)), target, cfg.model_copy(update={"prior_weight": 0.0}))[
            0
        ]
    )


def meets(c: Candidate, target: Target, cfg: DesignConfig) -> bool:
    """Whether a verified candidate's own replay meets the target within the tolerances."""
    if c.simulated is None or c.error_m > cfg.tolerance_for(target):
        return False
    if target.heading is not None and (c.heading_error is None or c.heading_error > cfg.heading_tolerance):
        return False
    return target.max_roll is None or abs(float(c.simulated[3])) <= target.max_roll


def design(
    model: GaitModel,
    target: Target,
    cfg: DesignConfig | None = None,
    *,
    backend: BackendConfig | None = None,
    runner=None,
    workers: int | None = None,
    cancelled: Callable[[], bool] | None = None,
    on_verify: Callable[[], None] | None = None,
) -> DesignResult:
    """Search, then verify in MuJoCo (on ``runner``, an open backend, or one opened from ``backend``).
    ``cancelled`` is polled between search generations (True: stop; the result is then not meant to be
    used); ``on_verify`` is called when the search is done and the replays start."""
    cfg = cfg or DesignConfig()
    t0 = time.perf_counter()
    candidates = search(model, target, cfg, cancelled)
    search_s = time.perf_counter() - t0
    if cancelled is not None and cancelled():
        return DesignResult(target, cfg.tolerance_for(target), candidates, False, search_s, 0.0)
    if on_verify is not None:
        on_verify()
    t0 = time.perf_counter()
    own = runner is None
    runner = runner or open_backend(backend, workers)
    try:
        candidates = verify(model, candidates, target, cfg, runner)
    finally:
        if own:
            runner.close()
    physics_s = time.perf_counter() - t0
    met = bool(candidates) and meets(candidates[0], target, cfg)
    return DesignResult(target, cfg.tolerance_for(target), candidates, met, search_s, physics_s)
