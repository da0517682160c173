"""What MuJoCo says of a design's candidates: each replayed (its own replay decides), the best ones'
noisy copies beside it (physics' own scatter), ranked by the replay's miss, and whether one meets
the target (``model.design.search`` proposes them)."""

from __future__ import annotations

import math

import numpy as np

from snakeloco.model.api import GaitModel
from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.design.targets import Candidate, objective, path_end
from snakeloco.model.replays import replay_shapes


def verify(
    model: GaitModel,
    candidates: list[Candidate],
    target: Target,
    cfg: DesignConfig,
    backend,
    members: int | None = None,
) -> list[Candidate]:
    """Replay each candidate as an ensemble of ``members`` (default ``cfg.ensemble``; 1: its own
    replay alone, the spread left for ``measure_spread``); rank by its own replay's error."""
    shapes = np.stack([c.shape for c in candidates])
    bodies, ok = replay_shapes(model, shapes, backend, members or cfg.ensemble, seed=cfg.seed)
    for c, body, fine in zip(candidates, bodies.astype(np.float64), ok, strict=True):
        if not fine[0]:
            c.broken = "its replay broke the simulation"
            continue
        ends = path_end(body[fine])  # (k, 4): its own replay first
        c.simulated = ends[0]
        c.error_m = float(math.hypot(ends[0, 0] - target.forward, ends[0, 1] - target.sideways))
        if target.heading is not None:
            c.heading_error = float(abs(ends[0, 2] - target.heading))
        c.spread_m = _spread(ends[1:], ends[0])
    return rank(candidates, target, cfg)


def measure_spread(model: GaitModel, candidates: list[Candidate], cfg: DesignConfig, backend) -> int:
    """The ``cfg.ensemble - 1`` noisy copies of each verified candidate (own replay already run):
    their ends' RMS distance from its own end, ``spread_m``. Returns the number of replays run."""
    todo = [c for c in candidates if c.simulated is not None]
    if not todo:
        return 0
    shapes = np.stack([c.shape for c in todo])
    bodies, ok = replay_shapes(model, shapes, backend, cfg.ensemble, seed=cfg.seed, own=False)
    for c, body, fine in zip(todo, bodies.astype(np.float64), ok, strict=True):
        c.spread_m = _spread(path_end(body[fine]), c.simulated)
    return len(todo) * (cfg.ensemble - 1)


def _spread(noisy: np.ndarray, own: np.ndarray) -> float:
    """RMS distance (m) of the noisy replays' ends (k, 4) from the own replay's end (NaN: none ran)."""
    offsets = noisy[:, :2] - own[:2]
    return float(np.sqrt((offsets**2).sum(axis=1).mean())) if len(offsets) else float("nan")


def rank(candidates: list[Candidate], target: Target, cfg: DesignConfig) -> list[Candidate]:
    """Verified candidates best first: by ``simulated_cost``, broken ones last."""
    return sorted(candidates, key=lambda c: (c.broken is not None, simulated_cost(c, target, cfg)))


def simulated_cost(c: Candidate, target: Target, cfg: DesignConfig) -> float:
    """What ranks verified candidates: the search's objective on the replay's end (no prior term)."""
    if c.simulated is None:
        return float("inf")
    return float(objective(c.simulated[None], target, cfg)[0])


def meets(c: Candidate, target: Target, cfg: DesignConfig) -> bool:
    """Whether a verified candidate's own replay meets the target within the tolerances."""
    if c.simulated is None or c.error_m > cfg.tolerance_for(target):
        return False
    if target.heading is not None and (c.heading_error is None or c.heading_error > cfg.heading_tolerance):
        return False
    return target.max_roll is None or abs(float(c.simulated[3])) <= target.max_roll
