"""``snakeloco bench fit``: fit robots of known physics from synthetic measured runs (docs/calibration.md).

Each of ``robots`` perturbed robots (friction along and across and servo kp drawn log-uniformly within
x0.6-1.6 of nominal, seeded) runs three library gaits for 100 s; the runs are "measured" at 50 Hz
with 1 mm and 0.5 deg noise and fitted from the nominal robot. Reported per robot: each field's error
against the truth and whether the fit calls it determined, the end-point error of two further gaits
(not used in the fit) replayed on the fitted and on the nominal robot against the perturbed one's,
the same gaits' error on robots within +-3% of the truth in every field (the floor a fit can reach,
``NEAR``), and the fit's wall time.
"""

from __future__ import annotations

import time

import numpy as np

from snakeloco.sim.fit import FitConfig, fit_robot
from snakeloco.sim.gaits import BASE_GAITS, PRESETS, GaitEquation
from snakeloco.sim.measured import MeasuredRun
from snakeloco.sim.physics import Simulator
from snakeloco.sim.robot import DEFAULT_ROBOT, Robot, robot_from_dict
from snakeloco.sim.robustness import relative_change

FIT_GAITS = ("sidewind", "undulate", "roll")
HELD_OUT: dict[str, GaitEquation] = {
    "turn": PRESETS["turn"].gait,
    "slow undulation": GaitEquation(a_yaw=0.5, nu_yaw=0.7, frequency=0.52),
}
"""Gaits not used in the fit: the library's turning gait and a slower, smaller undulation."""
PARAMS = ("friction_along", "friction_across", "servo_kp")
RANGE = (0.6, 1.6)
RATE_HZ, NOISE_M, NOISE_DEG = 50.0, 0.001, 0.5
NEAR, NEAR_DRAWS = 0.03, 3
"""The held-out floor: robots with every fitted field within +-3% of the truth (random signs, 3
draws) replay the held-out gaits this far from the truth's ends. The loss is a needle at the exact
truth (a 100 s replay's contacts diverge for a 2% change of one field), so a fit cannot be expected
to come nearer than this, and a held-out goal below it is one no fit of these fields can meet."""


def perturbed_robots(n: int, seed: int) -> list[Robot]:
    rng = np.random.default_rng(seed)
    lo, hi = np.log(RANGE[0]), np.log(RANGE[1])
    out = []
    for i in range(n):
        values = DEFAULT_ROBOT.model_dump()
        for name in PARAMS:
            values[name] *= float(np.exp(rng.uniform(lo, hi)))
        values["name"] = f"perturbed {i + 1}"
        out.append(robot_from_dict(values))
    return out


def near_robots(truth: Robot, rng: np.random.Generator) -> list[Robot]:
    """``NEAR_DRAWS`` robots with each of ``PARAMS`` x(1 +- ``NEAR``) of ``truth``'s."""
    out = []
    for i in range(NEAR_DRAWS):
        values = truth.model_dump()
        for name in PARAMS:
            values[name] *= 1 + NEAR * rng.choice([-1.0, 1.0])
        values["name"] = f"{truth.name} near {i + 1}"
        out.append(robot_from_dict(values))
    return out


def synthetic_run(
    body: np.ndarray, rng: np.random.Generator, source: str, joints: np.ndarray | None = None
) -> MeasuredRun:
    """A measured run of a replay's body series (T, 6) at 20 Hz: ``RATE_HZ`` with the noise above;
    with ``joints`` (T, J) the servos' measured angles too (``NOISE_DEG`` noise)."""
    ts = np.arange(len(body)) / 20.0
    t = np.arange(0.0, ts[-1], 1.0 / RATE_HZ)
    xy = np.stack([np.interp(t, ts, body[:, k]) for k in (1, 2)], axis=1) + rng.normal(
        0, NOISE_M, (len(t), 2)
    )
    yaw = np.interp(t, ts, body[:, 5]) + rng.normal(0, np.radians(NOISE_DEG), len(t))
    angles = None
    if joints is not None:
        angles = np.stack([np.interp(t, ts, a) for a in joints.T], axis=1)
        angles += rng.normal(0, np.radians(NOISE_DEG), angles.shape)
    return MeasuredRun(t, xy - xy[0], yaw - yaw[0], angles, None, source)


def single_runs(truth: Robot, simulator, generations: int, seed: int = 0) -> dict:
    """What one run determines: each library gait's run alone, fitted; per gait, each field's error
    and whether the fit calls it determined."""
    rng = np.random.default_rng(seed + 99)
    names = list(BASE_GAITS)
    result = simulator.simulate(
        np.stack([PRESETS[g].gait.commands() for g in names]), robots=[truth] * len(names)
    )
    table = {}
    for g, body in zip(names, result.body, strict=True):
        run = synthetic_run(body, rng, g)
        report = fit_robot(
            [(PRESETS[g].gait.commands(), run)],
            DEFAULT_ROBOT,
            FitConfig(generations=generations, seed=seed),
            simulator,
            advise=False,
        )
        table[g] = {
            p: {
                "error_rel": v["fitted"] / getattr(truth, p) - 1,
                "determined": v["determined"],
                "rel_uncertainty": v["rel_uncertainty"],
            }
            for p, v in report["params"].items()
        }
        print(f"single run {g}: {report['seconds']:.0f} s", flush=True)
    return table


def bench_fit(
    robots: int = 6,
    seed: int = 0,
    generations: int = 30,
    workers: int | None = None,
    single: bool = False,
    joints: bool = False,
) -> dict:
    """The benchmark (module docstring); ``joints``: the runs measure the servos' joint angles too."""
    simulator = Simulator(workers)
    rows = []
    if single:
        try:
            truth = perturbed_robots(1, seed)[0]
            return {
                "single_runs": single_runs(truth, simulator, generations, seed),
                "truth": {p: getattr(truth, p) for p in PARAMS},
                "workers": simulator.workers,
            }
        finally:
            simulator.close()
    try:
        for k, truth in enumerate(perturbed_robots(robots, seed)):
            rng = np.random.default_rng(seed * 1000 + k)
            cmds = [PRESETS[g].gait.commands() for g in FIT_GAITS]
            held = [g.commands() for g in HELD_OUT.values()]
            result = simulator.simulate(np.stack(cmds + held), robots=[truth] * (len(cmds) + len(held)))
            pairs = [
                (c, synthetic_run(b, rng, g, a if joints else None))
                for c, b, a, g in zip(cmds, result.body, result.joint_angles, FIT_GAITS, strict=False)
            ]
            t0 = time.perf_counter()
            report = fit_robot(pairs, DEFAULT_ROBOT, FitConfig(generations=generations, seed=seed), simulator)
            seconds = time.perf_counter() - t0
            fitted = report["robot"]
            others = [fitted, DEFAULT_ROBOT, *near_robots(truth, rng)]
            check = simulator.simulate(np.stack(held * len(others)), robots=[r for r in others for _ in held])
            ends = check.body[:, -1, 1:3].reshape(len(others), len(held), 2)
            held_rows = {}
            for i, name in enumerate(HELD_OUT):
                want = result.body[len(cmds) + i, -1, 1:3]
                rel = relative_change(ends[:, i], want)
                held_rows[name] = {
                    "distance_m": float(np.hypot(*want)),
                    "fitted_rel": float(rel[0]),
                    "nominal_rel": float(rel[1]),
                    "near_rel": float(np.median(rel[2:])),
                }
            rows.append(
                {
                    "robot": truth.name,
                    "truth": {p: getattr(truth, p) for p in PARAMS},
                    "params": {
                        p: {
                            "fitted": v["fitted"],
                            "error_rel": v["fitted"] / getattr(truth, p) - 1,
                            "rel_uncertainty": v["rel_uncertainty"],
                            "determined": v["determined"],
                            "would_determine": v.get("would_determine"),
                        }
                        for p, v in report["params"].items()
                    },
                    "fit_runs": [
                        {"before_end_rel": b["end_rel"], "after_end_rel": a["end_rel"]}
                        for b, a in zip(report["before"], report["after"], strict=True)
                    ],
                    "held_out": held_rows,
                    "seconds": seconds,
                    "replays": report["replays"],
                }
            )
            print(f"robot {k + 1}: {seconds:.0f} s", flush=True)
    finally:
        simulator.close()
    determined = [(p["error_rel"]) for r in rows for p in r["params"].values() if p["determined"]]
    return {
        "robots": rows,
        "joints": joints,
        "workers": simulator.workers,
        "determined_within_15pct": int(sum(abs(e) <= 0.15 for e in determined)),
        "determined": len(determined),
        "held_out_fitted_rel_median": float(
            np.median([h["fitted_rel"] for r in rows for h in r["held_out"].values()])
        ),
        "held_out_nominal_rel_median": float(
            np.median([h["nominal_rel"] for r in rows for h in r["held_out"].values()])
        ),
        "held_out_near_rel_median": float(
            np.median([h["near_rel"] for r in rows for h in r["held_out"].values()])
        ),
        "seconds_median": float(np.median([r["seconds"] for r in rows])),
    }
