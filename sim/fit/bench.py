"""``snakeloco bench fit``: fit robots of known physics from synthetic measured runs (docs/calibration.md).

Each of ``robots`` perturbed robots (friction along and across and servo kp drawn log-uniformly within
x0.6-1.6 of nominal, seeded) runs three library gaits for 100 s (``FIT_GAITS``); the runs are "measured" at 50 Hz
with 1 mm and 0.5 deg noise and fitted from the nominal robot. Reported per robot: each field's error
against the truth and whether the fit calls it determined, the end-point error of every further gait
(``held_out``: the library's other gaits and a slow undulation) replayed on the fitted and on the
nominal robot against the perturbed one's,
the same gaits' error on robots within +-3% of the truth in every field (the floor a fit can reach,
``NEAR``), and the fit's wall time.
"""

from __future__ import annotations

import time

import numpy as np

from snakeloco.sim.fit.fit_robot import FitConfig, fit_robot
from snakeloco.sim.fit.measured import MeasuredRun
from snakeloco.sim.gaits.library import BASE_GAITS, PRESETS, GaitEquation
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT, Robot, robot_from_dict
from snakeloco.sim.scores.robustness import relative_change

FIT_GAITS = ("turn", "sidewind", "undulate")
"""The runs fitted: the turning gait determines all three fields alone (docs/calibration.md, "What one
run determines"), sidewinding servo kp, undulation the friction where it slides."""
SLOW_UNDULATION = GaitEquation(a_yaw=0.5, nu_yaw=0.7, frequency=0.52)


def held_out(fit_gaits: tuple[str, ...]) -> dict[str, GaitEquation]:
    """Gaits not used in the fit: every library gait but ``fit_gaits``, and a slower, smaller
    undulation than the library's."""
    return {n: p.gait for n, p in PRESETS.items() if n not in fit_gaits} | {
        "slow undulation": SLOW_UNDULATION
    }


PARAMS = ("friction_along", "friction_across", "servo_kp")
RANGE = (0.6, 1.6)
RATE_HZ, NOISE_M, NOISE_DEG = 50.0, 0.001, 0.5
NEAR, NEAR_DRAWS = 0.03, 3
"""The held-out floor: robots with every fitted field within +-3% of the truth (random signs, 3
draws) replay the held-out gaits this far from the truth's ends: how near a fit must come. With the
turning gait's run in the fit the fields land within 4% (median 1%), and the held-out gaits beside
this floor (docs/calibration.md)."""


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


def single_runs(
    truths: list[Robot], simulator, generations: int, seed: int = 0, joints: bool = False
) -> dict:
    """What one run determines: each library gait's run alone, fitted, on each robot of ``truths``;
    per gait, per robot, each field's error and whether the fit calls it determined."""
    names = list(BASE_GAITS)
    table: dict[str, list[dict]] = {g: [] for g in names}
    for k, truth in enumerate(truths):
        rng = np.random.default_rng(seed + 99 + k)
        result = simulator.simulate(
            np.stack([PRESETS[g].gait.commands(simulator.robot) for g in names]), robots=[truth] * len(names)
        )
        for g, body, angles in zip(names, result.body, result.joint_angles, strict=True):
            run = synthetic_run(body, rng, g, angles if joints else None)
            report = fit_robot(
                [(PRESETS[g].gait.commands(simulator.robot), run)],
                DEFAULT_ROBOT,
                FitConfig(generations=generations, seed=seed),
                simulator,
                advise=False,
            )
            table[g].append(
                {
                    p: {
                        "error_rel": v["fitted"] / getattr(truth, p) - 1,
                        "determined": v["determined"],
                        "rel_uncertainty": v["rel_uncertainty"],
                    }
                    for p, v in report["params"].items()
                }
            )
            print(f"robot {k + 1}, {g} alone: {report['seconds']:.0f} s", flush=True)
    return table


def bench_fit(
    robots: int = 6,
    seed: int = 0,
    generations: int = 30,
    workers: int | None = None,
    single: bool = False,
    joints: bool = False,
    gaits: tuple[str, ...] = FIT_GAITS,
) -> dict:
    """The benchmark (module docstring); ``joints``: the runs measure the servos' joint angles too;
    ``gaits``: the library gaits whose runs are fitted (the others are held out)."""
    unknown = [g for g in gaits if g not in PRESETS]
    if unknown:
        raise ValueError(f"no library gait named {', '.join(unknown)} (snakeloco gait --list)")
    others = held_out(gaits)
    simulator = Simulator(workers)
    rows = []
    if single:
        try:
            truths = perturbed_robots(robots, seed)
            return {
                "single_runs": single_runs(truths, simulator, generations, seed, joints),
                "truths": [{p: getattr(t, p) for p in PARAMS} for t in truths],
                "joints": joints,
                "workers": simulator.workers,
            }
        finally:
            simulator.close()
    try:
        for k, truth in enumerate(perturbed_robots(robots, seed)):
            rng = np.random.default_rng(seed * 1000 + k)
            cmds = [PRESETS[g].gait.commands(simulator.robot) for g in gaits]
            held = [g.commands(simulator.robot) for g in others.values()]
            result = simulator.simulate(np.stack(cmds + held), robots=[truth] * (len(cmds) + len(held)))
            pairs = [
                (c, synthetic_run(b, rng, g, a if joints else None))
                for c, b, a, g in zip(cmds, result.body, result.joint_angles, gaits, strict=False)
            ]
            t0 = time.perf_counter()
            report = fit_robot(pairs, DEFAULT_ROBOT, FitConfig(generations=generations, seed=seed), simulator)
            seconds = time.perf_counter() - t0
            fitted = report["robot"]
            compared = [fitted, DEFAULT_ROBOT, *near_robots(truth, rng)]
            check = simulator.simulate(
                np.stack(held * len(compared)), robots=[r for r in compared for _ in held]
            )
            ends = check.body[:, -1, 1:3].reshape(len(compared), len(held), 2)
            held_rows = {}
            for i, name in enumerate(others):
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

    def median(key: str, gait: str | None = None) -> float:
        return float(np.median([h[key] for r in rows for g, h in r["held_out"].items() if gait in (None, g)]))

    return {
        "robots": rows,
        "joints": joints,
        "fit_gaits": list(gaits),
        "workers": simulator.workers,
        "determined_within_15pct": int(sum(abs(e) <= 0.15 for e in determined)),
        "determined": len(determined),
        "held_out_fitted_rel_median": median("fitted_rel"),
        "held_out_nominal_rel_median": median("nominal_rel"),
        "held_out_near_rel_median": median("near_rel"),
        "held_out_per_gait": {
            g: {k: median(k, g) for k in ("fitted_rel", "nominal_rel", "near_rel")} for g in others
        },
        "seconds_median": float(np.median([r["seconds"] for r in rows])),
    }
