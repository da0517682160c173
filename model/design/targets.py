"""What inverse design speaks in (``model.design.search``): where a path ends, how far that misses a target,
a candidate gait and what MuJoCo did with it, and a design's result."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from snakeloco.model.design.config import DesignConfig, Target

FORWARD, SIDEWAYS, ROLL, YAW = 1, 2, 3, 5  # body channels (sim.BODY_CHANNELS)


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


def objective(ends: np.ndarray, target: Target, cfg: DesignConfig) -> np.ndarray:
    """The path's miss (m) per row of ``ends`` (``path_end``): distance from the target, plus the
    heading and roll terms where asked."""
    cost = np.hypot(ends[:, 0] - target.forward, ends[:, 1] - target.sideways)
    if target.heading is not None:
        cost = cost + cfg.heading_weight * np.abs(ends[:, 2] - target.heading)
    if target.max_roll is not None:
        cost = cost + cfg.roll_weight * np.maximum(np.abs(ends[:, 3]) - target.max_roll, 0.0)
    return cost


NOMINAL_GUARD = 10.0
"""Metres of cost per metre a robust search's decoded nominal miss exceeds ``GUARD_SHARE`` of the
tolerance: the gait must still reach the target on the robot it was designed for."""
GUARD_SHARE = 0.7
"""Of the tolerance, the nominal miss a robust search trades freely (the rest is the decoded path's
own error against its replay)."""


def fan_cost(
    fan: FanCost, fan_ends: np.ndarray, target: Target, miss: np.ndarray, cfg: DesignConfig
) -> np.ndarray:
    """``fan``'s cost for ``target`` beside the candidates' nominal ``miss`` (``objective``): the
    predicted fan's, plus ``NOMINAL_GUARD`` x the miss beyond ``GUARD_SHARE`` of the tolerance, so
    that the search does not buy robustness with the nominal error (with the fan's cost alone it
    did: nominal misses of 12-38% on the first targets of ``bench robust``)."""
    excess = np.maximum(miss - GUARD_SHARE * cfg.tolerance_for(target), 0.0)
    return fan.cost(fan_ends, target) + NOMINAL_GUARD * excess


class FanCost(Protocol):
    """A cost the search adds for how a gait fares on other robots, as predicted (no replay)."""

    def ends(self, z_b: np.ndarray) -> np.ndarray:
        """Where each z_B's gait ends on each robot of the fan: (n, V, 2) forward, sideways (m)."""

    def cost(self, ends: np.ndarray, target: Target) -> np.ndarray:
        """Those ends' (n, V, 2) cost (m) for ``target``: (n,)."""


@dataclass
class Candidate:
    """A proposed gait and, once verified, what MuJoCo did with it."""

    z_b: np.ndarray  # (Db,)
    predicted: np.ndarray  # (4,) path_end of the decoded path
    cost: float  # the search's objective
    shape: np.ndarray  # (n_joints, L, 2) rad, z_k = 0
    simulated: np.ndarray | None = None  # (4,) path_end of its own replay
    spread_m: float = float("nan")  # RMS distance of the perturbed replays' ends from its own
    broken: str | None = None
    error_m: float = float("inf")
    heading_error: float | None = None
    round: int = 1  # the round of the search that proposed it

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
            "round": self.round,
        }


@dataclass
class DesignResult:
    target: Target
    tolerance_m: float
    candidates: list[Candidate]  # best first (by simulated error)
    met: bool
    search_s: float
    physics_s: float
    replays: int = 0  # MuJoCo replays run: each round's candidates once, the reported ones' noisy copies
    rounds: int = 0  # rounds of search and verification run
    extra: dict = field(default_factory=dict)

    def verdict(self) -> str:
        """The result in one line, the criterion that decided it first: 'met: ...', 'not met: the
        closest reached ends 1.20 m from the target ...', or 'not met on other robots: worst 9.51 m
        (anisotropy 8:1); nominal 0.37 m, within the tolerance 0.50 m'."""
        best = self.candidates[0] if self.candidates else None
        tol = self.tolerance_m
        if best is None or best.simulated is None:
            return "not met: no candidate's replay ran (each broke the simulation)"
        robust = (self.extra.get("robust") or [None])[0]
        nominal = robust.get("nominal_m", best.error_m) if robust else best.error_m
        where = f"ends ({best.simulated[0]:.2f}, {best.simulated[1]:.2f}) m"
        if robust is None:
            if self.met:
                return f"met: candidate 1 {where}, {nominal:.2f} m from the target (tolerance {tol:.2f} m)"
            return f"not met: the closest reached {where}, {nominal:.2f} m from the target (tolerance {tol:.2f} m)"
        loop = " closed loop" if robust.get("closed_loop") else ""
        worst = f"worst {robust['worst_m']:.2f} m ({robust['worst_variation']})"
        if self.met:
            return f"met on other robots{loop}: {worst}; nominal {nominal:.2f} m (tolerance {tol:.2f} m)"
        if nominal > tol:
            return f"not met: the closest reached ends {nominal:.2f} m from the target (tolerance {tol:.2f} m); {worst}{loop}"
        return f"not met on other robots{loop}: {worst}; nominal {nominal:.2f} m, within the tolerance {tol:.2f} m"


class DesignProgress:
    """Where a running design is, for a progress bar: what it is doing, the MuJoCo replays done of at
    most ``planned``, the best miss verified so far. Each search a design runs adds the replays it
    may need (``plan``) and gives back those it did not (``settle``: a round that met the target
    ends the rounds), so ``fraction`` only grows towards 1. ``report(self)`` is called after each
    step (the designer's bar; None: kept for whoever reads it)."""

    def __init__(self, report: Callable[[DesignProgress], None] | None = None) -> None:
        self.doing = "starting"
        self.replays = 0
        self.planned = 0
        self.best_m: float | None = None
        self.started = time.perf_counter()
        self._report = report

    def plan(self, replays: int) -> int:
        self.planned += int(replays)
        return int(replays)

    def settle(self, unused: int) -> None:
        self.planned -= max(int(unused), 0)
        self._step()

    def step(self, doing: str | None = None, replays: int = 0, best_m: float | None = None) -> None:
        """Now ``doing`` (unchanged where None); ``replays`` more done; ``best_m`` the best miss so
        far where a newer one is known."""
        if doing is not None:
            self.doing = doing
        self.replays += int(replays)
        if best_m is not None and np.isfinite(best_m):
            self.best_m = float(best_m)
        self._step()

    def _step(self) -> None:
        if self._report is not None:
            self._report(self)

    @property
    def fraction(self) -> float:
        return min(self.replays / self.planned, 1.0) if self.planned > 0 else 0.0

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.started

    def line(self) -> str:
        """'Replaying 4 candidates (round 2 of at most 6): 12 of at most 40 replays, best miss 0.42 m, 31 s'."""
        best = f", best miss {self.best_m:.2f} m" if self.best_m is not None else ""
        return (
            f"{self.doing[:1].upper()}{self.doing[1:]}: {self.replays} of at most {self.planned} replays"
            f"{best}, {self.seconds:.0f} s"
        )
