"""How a gait fares closed loop: its steering loop's replays over a variation set.

The path a gait follows is its nominal replay's averaged position (over one wave period), in the frame
of the first pose (``nominal_reference``), or a path given with it (the model's prediction for a
member). Each variation's run follows it; its end error is the distance from its averaged end to the
path's end, relative to the path's distance (floored at ``MIN_DISTANCE``, as open loop). An *arrive*
run stops at the path's end or at its cap; one that does not arrive by then is named.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from snakeloco.sim.control.closed_loop import make_follower, nominal_reference, run_closed_loop
from snakeloco.sim.control.follower import FollowerConfig
from snakeloco.sim.control.steering import Steering
from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.robot.variations import Variation
from snakeloco.sim.scores.robustness import MIN_DISTANCE, flat_simulator, on_world


def closed_loop_rows(simulator, job: tuple) -> list:
    """A backend job: rows of a closed-loop batch (``closed_loop_robustness``) on this worker's
    simulator; each row's pose-noise seed is its index in the whole batch, as in one local batch."""
    from snakeloco.sim.robot.description import Robot

    commands, reference, steering_json, config_json, end, robots_json, seeds = job
    steering = Steering.model_validate_json(steering_json)
    config = FollowerConfig.model_validate_json(config_json)
    robots = [Robot.model_validate_json(r) for r in robots_json]
    followers = [make_follower(commands, reference, steering, simulator, end, config) for _ in robots]
    return run_closed_loop(simulator, followers, robots, seeds)


def run_row(run, reference: np.ndarray, lead_in_s: float) -> dict:
    """One run's figures against its path (see ``closed_loop_robustness``)."""
    if run.failure is not None:
        return {
            "forward": None,
            "sideways": None,
            "end_error_m": None,
            "rel": None,
            "arrival_s": None,
            "arrived": False,
            "max_cross_track_m": None,
            "saturated": None,
            "failure": run.failure,
        }
    start, goal = reference[0], reference[-1]
    err = float(np.linalg.norm(run.end - goal))
    distance = max(float(np.linalg.norm(goal - start)), MIN_DISTANCE)
    return {
        "forward": float(run.end[0] - start[0]),
        "sideways": float(run.end[1] - start[1]),
        "end_error_m": err,
        "rel": err / distance,
        "arrival_s": round(run.duration - lead_in_s, 3) if run.arrived else None,
        "arrived": bool(run.arrived),
        "max_cross_track_m": run.max_cross_track,
        "saturated": run.saturated,
        "failure": None,
    }


def closed_loop_robustness(
    commands: np.ndarray,
    variations: Sequence[Variation],
    simulator,
    steering: Steering,
    reference: np.ndarray | None = None,
    end: str = "arrive",
    config: FollowerConfig | None = None,
    runner=None,
) -> dict:
    """Play ``commands`` with ``steering`` on the nominal robot and each variation, following
    ``reference`` (None: ``nominal_reference``, on the flat default ground where ``simulator`` is on
    a world), in one batch (``runner``: a backend, ``sim.physics.backend``,
    whose jobs each run a few rows on its own simulator of the same robot; None: ``simulator``'s threads).

    Returns ``{"steering", "reference_end", "distance_m", "nominal": row, "variations": [row + name,
    params], "worst_end_error_m", "worst_rel", "worst", "broken", "late"}``; a row has the averaged end
    (forward, sideways from the path's start, m), ``end_error_m`` and ``rel`` from the path's end, the
    arrival time (s of record time; None if it did not arrive), the largest cross-track error (m) and
    the share of time the input sat at its limit. A gait without a steering input is played open loop
    (its rows say so through ``steering``)."""
    commands = np.asarray(commands, np.float64)
    if reference is None and on_world(simulator):  # the path it would take on flat ground
        flat = flat_simulator(simulator)
        try:
            reference = nominal_reference(commands, flat, steering.period)
        finally:
            flat.close()
    elif reference is None:
        reference = nominal_reference(commands, simulator, steering.period)
    nominal = simulator.robot
    robots = [nominal, *(v.apply(nominal) for v in variations)]
    if runner is None:
        followers = [make_follower(commands, reference, steering, simulator, end, config) for _ in robots]
        runs = run_closed_loop(simulator, followers, robots)
    else:  # chunks of rows as backend jobs (Ray tasks): the same rows, the same numbers
        per = max(1, getattr(runner, "replays_per_job", 4) // 4)
        spec = (
            commands,
            reference,
            steering.model_dump_json(),
            (config or FollowerConfig()).model_dump_json(),
            end,
        )
        jobs = [
            (
                *spec,
                [r.model_dump_json() for r in robots[i : i + per]],
                list(range(i, min(i + per, len(robots)))),
            )
            for i in range(0, len(robots), per)
        ]
        parts = dict(runner.map(closed_loop_rows, jobs))
        runs = [run for i in range(len(jobs)) for run in parts[i]]
    lead = simulator.config.lead_in / simulator.excitation.sample_rate
    rows = [run_row(r, reference, lead) for r in runs]
    if rows[0]["failure"] is not None:
        raise SimulationError(f"the nominal closed-loop replay broke: {rows[0]['failure']}")
    out_rows = []
    for v, row in zip(variations, rows[1:], strict=True):
        out_rows.append({"name": v.name, "params": v.params(), **row})
    scored = [r for r in out_rows if r["failure"] is None]
    worst = max(scored, key=lambda r: r["end_error_m"], default=None)
    return {
        "steering": steering.model_dump(),
        "steering_line": steering.line(),
        "end": end,
        "reference_end": [
            float(reference[-1, 0] - reference[0, 0]),
            float(reference[-1, 1] - reference[0, 1]),
        ],
        "distance_m": float(np.linalg.norm(reference[-1] - reference[0])),
        "nominal": rows[0],
        "variations": out_rows,
        "worst_end_error_m": None if worst is None else worst["end_error_m"],
        "worst_rel": None if worst is None else worst["rel"],
        "worst": None if worst is None else worst["name"],
        "broken": [r["name"] for r in out_rows if r["failure"] is not None],
        "late": [
            r["name"] for r in out_rows if r["failure"] is None and end == "arrive" and not r["arrived"]
        ],
        "runs": runs,
    } | ({"world": simulator.world.name} if on_world(simulator) else {})


def closed_loop_table(
    commands: np.ndarray, kinds, robot, workers: int | None = None, variations=None
) -> dict:
    """Many gaits closed loop, per kind: ``commands`` (N, T, J) rad, ``kinds`` (N,). Each gait gets its
    steering input (``find_steering``) and, where it has one, its loop over ``variations`` (default:
    the default set) on ``robot`` (``workers`` threads). Per kind and for ``"all"``: ``n``,
    ``steered`` (share with an input), and over the steered gaits the median of each gait's median and
    of its worst relative end error (``closed_median``, ``closed_worst``) and the share of runs that
    arrived."""
    from snakeloco.sim.control.find import find_steering
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.robot.variations import DEFAULT_SET

    variations = DEFAULT_SET if variations is None else variations
    simulator = Simulator(workers=workers, robot=robot)
    rows = []
    try:
        for cmd, kind in zip(np.asarray(commands, np.float64), kinds, strict=True):
            steering = find_steering(cmd, simulator)
            row = {"kind": str(kind), "steering": steering.kind}
            if steering.steers:
                rep = closed_loop_robustness(cmd, variations, simulator, steering)
                rel = [r["rel"] for r in rep["variations"] if r["rel"] is not None]
                arrived = [r["arrived"] for r in rep["variations"]]
                row |= {
                    "median": float(np.median(rel)),
                    "worst": float(max(rel)),
                    "arrived": float(np.mean(arrived)),
                }
            rows.append(row)
    finally:
        simulator.close()
    out = {}
    for kind in ["all", *dict.fromkeys(r["kind"] for r in rows)]:
        mine = [r for r in rows if kind in ("all", r["kind"])]
        steered = [r for r in mine if "median" in r]

        def median(key: str, steered=steered) -> float | None:
            return float(np.median([r[key] for r in steered])) if steered else None

        out[kind] = {
            "n": len(mine),
            "steered": len(steered) / len(mine),
            "closed_median": median("median"),
            "closed_worst": median("worst"),
            "arrived": median("arrived"),
        }
    return out
