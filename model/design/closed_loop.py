"""Closed-loop inverse design: gaits whose steering loop stops at the target on other robots too
(``design --closed-loop``).

Two nominal searches (``model.design.search``) propose and verify candidates: one for the target,
one for a target ``FARTHER`` times as far the same way. Each verified candidate is given its steering
input (``sim.control.find``) and its path is its nominal replay's averaged path cut where it passes
nearest the target (farther than the tolerance: not a candidate); played closed loop with *arrive*
on the nominal robot and every variation of the set (``sim.scores.closed_loop``), it stops there.
A run's miss is the distance of its averaged end from the target in the record's frame; a broken
run misses by twice the target's distance. So a faster, stronger gait that would overshoot open
loop is a candidate too: the loop stops it. A candidate no input steers is scored open loop, as
``design --robust`` scores it, where it meets the target nominally. Ranked: those whose nominal
closed-loop run meets the target first, then by the worst miss over the set. Every reported figure
was replayed. The target's heading is not sought (the loop holds the path, not an end heading).
"""

from __future__ import annotations

import math

import numpy as np

from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.design.robust import rank_by_worst, worst_case
from snakeloco.model.design.search import DesignResult, design
from snakeloco.model.design.targets import DesignProgress
from snakeloco.sim.physics.backend import open_backend
from snakeloco.sim.robot.variations import DEFAULT_SET, Variation

FARTHER = 2.0
"""The second search's target: this many times as far, the same way (its gaits are stopped at the target)."""


def closed_loop_misses(commands: np.ndarray, target: Target, simulator, variations) -> dict:
    """One verified candidate's closed-loop misses from ``target`` (m, record frame) over the nominal
    robot and ``variations``, following its own nominal path up to the point nearest the target
    (where it stops: *arrive*). ``{"steering"}`` alone where no input steers it; ``{"steering",
    "misses": None}`` where its path never gets as far as the target."""
    from snakeloco.sim.control.closed_loop import cut_and_turn, nominal_path
    from snakeloco.sim.control.find import find_steering
    from snakeloco.sim.scores.closed_loop import closed_loop_robustness

    steering = find_steering(commands, simulator)
    if not steering.steers:
        return {"steering": steering}
    reference, record = nominal_path(commands, simulator, steering.period)  # rest frame
    window = max(1, round(steering.period * simulator.excitation.sample_rate))
    p0, yaw0 = record[:2], float(record[2])
    rot = np.array([[math.cos(yaw0), math.sin(yaw0)], [-math.sin(yaw0), math.cos(yaw0)]])  # rest -> record

    def in_record(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p) - p0) @ rot.T

    goal = np.array([target.forward, target.sideways])
    reach = np.linalg.norm(in_record(reference), axis=1)
    far = np.flatnonzero(reach >= np.hypot(*goal))
    if not far.size or far[0] < window:
        return {"steering": steering, "misses": None, "reach_m": float(reach.max())}
    stop = int(far[0])
    # Turned about the record's start so that the point where it first gets as far as the target
    # lies on the target: the loop turns the snake onto it at the start.
    there = in_record(reference[stop])
    turn = math.atan2(goal[1], goal[0]) - math.atan2(there[1], there[0])
    path = cut_and_turn(reference, stop, p0, turn)
    report = closed_loop_robustness(commands, variations, simulator, steering, path)
    rows = [{"name": "nominal", **report["nominal"]}, *report["variations"]]
    misses = []
    for row in rows:
        if row["failure"] is not None:
            misses.append(float(np.hypot(*goal)) * 2)  # broken: as far off as going the other way
        else:
            end = path[0] + np.array([row["forward"], row["sideways"]])
            misses.append(float(np.linalg.norm(in_record(end) - goal)))
    return {
        "steering": steering,
        "misses": misses,
        "names": [r["name"] for r in rows],
        "late": report["late"],
        "broken": report["broken"],
        "until": stop,
        "turn_deg": math.degrees(turn),
    }


def closed_loop_design(
    model,
    target: Target,
    cfg: DesignConfig | None = None,
    *,
    backend=None,
    workers: int | None = None,
    robot=None,
    variations: tuple[Variation, ...] = DEFAULT_SET,
    cancelled=None,
    progress: DesignProgress | None = None,
    world=None,
) -> DesignResult:
    """Design for ``target`` (twice the candidates, on ``world``: default the flat plane), then rank the best verified ones by their
    closed-loop worst miss over ``variations`` (module docstring). ``met``: the best one's nominal and
    worst misses within the tolerance. ``cancelled`` and ``progress`` as ``design``'s."""
    from snakeloco.sim.physics.simulator import Simulator

    cfg = cfg or DesignConfig()
    progress = progress or DesignProgress()
    wide = cfg.model_copy(update={"candidates": min(2 * cfg.candidates, 32)})
    robot = robot or model.robot
    runner = open_backend(backend, workers, robot=robot, world=world)
    simulator = Simulator(workers=workers, robot=robot, world=world)
    try:
        result = design(model, target, wide, runner=runner, cancelled=cancelled, progress=progress)
        pool = sorted((c for c in result.candidates if c.simulated is not None), key=lambda c: c.error_m)
        pool = pool[: cfg.candidates]
        # Gaits that go farther the same way: the loop stops them where their path passes the target,
        # so a faster, stronger gait (one that still climbs a slope) is a candidate too.
        farther = Target(forward=FARTHER * target.forward, sideways=FARTHER * target.sideways)
        if not (cancelled is not None and cancelled()):
            longer = design(model, farther, cfg, runner=runner, cancelled=cancelled, progress=progress)
            pool += [c for c in longer.candidates if c.simulated is not None]
        kept, scores = [], []
        progress.plan(len(pool) * (len(variations) + 1))
        for k, c in enumerate(pool):
            if cancelled is not None and cancelled():
                break
            progress.step(
                f"closed loop: steering found and replayed on {len(variations)} robots, candidate {k + 1} of {len(pool)}"
            )
            found = closed_loop_misses(model.commands(c.shape), target, simulator, variations)
            progress.step(replays=len(variations) + 1)
            steering = found["steering"]
            if found.get("misses") is not None:
                errors, names = np.array(found["misses"]), found["names"]
                worst = int(np.argmax(errors))
                scores.append(
                    {
                        "nominal_m": float(errors[0]),
                        "worst_m": float(errors.max()),
                        "p90_m": float(np.percentile(errors, 90)),
                        "worst_variation": names[worst],
                        "broken": found["broken"],
                        "late": found["late"],
                        "replayed": len(variations),
                        "closed_loop": True,
                        "path": {"until": found["until"], "turn_deg": round(found["turn_deg"], 6)},
                        "steering": steering.model_dump(),
                        "steering_line": steering.line(),
                    }
                )
            elif not steering.steers and c.error_m <= result.tolerance_m:
                (open_score,) = worst_case([c], model, target, runner, variations)
                scores.append(
                    open_score
                    | {
                        "nominal_m": c.error_m,
                        "closed_loop": False,
                        "steering": steering.model_dump(),
                        "steering_line": steering.line(),
                    }
                )
            else:
                continue  # steers, but its path passes the target too far off; or overshoots unsteered
            kept.append(c)
    finally:
        runner.close()
        simulator.close()
    nominal = [s["nominal_m"] for s in scores]
    ranked, robust, met = rank_by_worst(kept, scores, nominal, result.tolerance_m, cfg.candidates)
    return DesignResult(
        target=target,
        tolerance_m=result.tolerance_m,
        candidates=ranked,
        met=met,
        search_s=result.search_s,
        physics_s=result.physics_s,
        replays=result.replays + len(pool) * (len(variations) + 1),
        rounds=result.rounds,
        extra={**result.extra, "robust": robust, "score": "worst", "closed_loop": True},
    )
