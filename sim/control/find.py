"""A gait's steering input, found by replays: which input turns it, both ways, in proportion, and does
the loop then follow a path with it (``find_steering``).

Probes: the unsteered gait and each input of ``sim.control.steering`` at its probe amplitude and twice
it, each way, replayed open loop for ``seconds`` (one batch, 13 rows). The turn rate of a probe is the
slope of its averaged heading (over one wave period) against time, less the unsteered gait's. An input
is usable where both signs turn the gait opposite ways, the weaker at least a quarter of the stronger
(``PROPORTION``), at least ``MIN_TURN`` and tightly enough for its speed (``TURN_RADIUS``), and the
steered gait keeps a third of its speed. The usable inputs, fastest first, are then checked in closed
loop on the nominal robot: each must follow its nominal path turned 20 deg either way about the start
and end within 15% of that path's distance of its end; the first that does is kept. A gait none
passes is played open loop, and its ``Steering`` says why.
"""

from __future__ import annotations

import math

import numpy as np

from snakeloco.sim.control.closed_loop import (
    cut_and_turn,
    make_follower,
    nominal_reference,
    run_closed_loop,
    trailing_mean,
)
from snakeloco.sim.control.steering import PROBE, STEERING_KINDS, Steering, apply, steering_pattern
from snakeloco.sim.physics.results import Dropped

MIN_TURN = math.radians(0.5)
"""rad/s: the least turn rate both ways at the probe amplitude for an input to count, whatever the
gait's speed (below it the probes' own scatter, ~0.3 deg/s over 20 s, decides the sign)."""
TURN_RADIUS = 5.0
"""Body lengths: an input must also turn the gait at least as tightly as this at the probe amplitude
both ways (turn rate >= speed / radius), so that it can hold a path against a drift: a slow gait
needs a slow turn, a fast one a fast turn."""
PROPORTION = 4.0
"""The stronger way may turn the gait at most this many times faster than the weaker."""
CHECK_TURN = math.radians(20.0)
CHECK_TOLERANCE = 0.15


def gait_period(commands: np.ndarray, sample_rate: float) -> float:
    """The gait's wave period (s): 1 / the frequency of its largest spectral line over all joints."""
    spectrum = np.abs(np.fft.rfft(np.asarray(commands, np.float64), axis=0)).sum(axis=1)
    spectrum[0] = 0.0
    k = int(np.argmax(spectrum))
    return len(commands) / sample_rate / max(k, 1)


def probe_figures(body: np.ndarray, sample_rate: float, period: float) -> dict[str, float]:
    """Turn rate (rad/s), speed (m/s) and travel offset (rad) of an open-loop probe's body (T, 6)."""
    w = max(1, round(period * sample_rate))
    t = np.arange(len(body)) / sample_rate
    xy, yaw = trailing_mean(body[:, 1:3], w), trailing_mean(body[:, 5], w)
    keep = t >= max(w / sample_rate, t[-1] / 3)  # past the first period and the start's transient
    rate = float(np.polyfit(t[keep], yaw[keep], 1)[0])
    # Speed along the averaged path, a period at a time: a probe that turns in a circle still travels.
    along = xy[keep][::w]
    span = max(t[keep][::w][-1] - t[keep][0], 1e-9)
    speed = float(np.linalg.norm(np.diff(along, axis=0), axis=1).sum() / span)
    step = xy[w:] - xy[:-w]  # displacement over one period
    ok = np.isfinite(step).all(axis=1) & (np.linalg.norm(step, axis=1) > 1e-6)
    course = np.arctan2(step[ok, 1], step[ok, 0])
    offset = float(np.angle(np.mean(np.exp(1j * (course - yaw[w:][ok]))))) if ok.any() else 0.0
    return {"turn_rate": rate, "speed": speed, "travel_offset": offset}


def find_steering(commands: np.ndarray, simulator, seconds: float = 30.0, check: bool = True) -> Steering:
    """The steering input of ``commands`` (T, n_joints) rad on ``simulator``'s robot (module docstring)."""
    commands = np.asarray(commands, np.float64)
    robot, rate = simulator.robot, simulator.excitation.sample_rate
    period = gait_period(commands, rate)
    rows, names = [commands], [("base", 0.0)]
    for kind in STEERING_KINDS:
        pattern = steering_pattern(kind, robot.joint_axes)
        for scale in (1.0, 2.0):
            for sign in (1.0, -1.0):
                u = sign * scale * PROBE[kind]
                rows.append(apply(kind, pattern, commands, u, robot.command_limit))
                names.append((kind, u))
    samples = min(len(commands), round(seconds * rate))
    result = simulator.simulate(np.stack(rows), samples=samples)
    if result is None:  # dropped on a shared pool's turns: the caller moved on
        raise Dropped("the steering probes were dropped")
    if result.failures[0] is not None:
        return Steering(period=period, why=f"its open-loop replay broke ({result.failures[0]})")
    figures = [
        probe_figures(result.body[i], rate, period) if result.failures[i] is None else None
        for i in range(len(rows))
    ]
    base = figures[0]
    if base["speed"] < 0.01:
        return Steering(period=period, why=f"it does not travel ({base['speed']:.3f} m/s)")
    found, notes = [], []
    for kind in STEERING_KINDS:
        turn = {}
        for (name, u), fig in zip(names, figures, strict=True):
            if name == kind:
                turn[u] = None if fig is None else (fig["turn_rate"] - base["turn_rate"], fig["speed"])
        a = PROBE[kind]
        plus, minus = turn[a], turn[-a]
        if plus is None or minus is None:
            notes.append(f"{kind.replace('_', ' ')} broke the simulation")
            continue
        both = plus[0] * minus[0] < 0
        weak, strong = sorted([abs(plus[0]), abs(minus[0])])
        slow = min(plus[1], minus[1]) < base["speed"] / 3
        least = max(MIN_TURN, base["speed"] / (TURN_RADIUS * robot.body_length))
        if not both or weak < max(least, strong / PROPORTION) or slow:
            why = (
                "turns it one way only"
                if not both
                else ("slows it below a third" if slow else "turns it too little")
            )
            notes.append(
                f"{kind.replace('_', ' ')} {why} ({math.degrees(plus[0]):+.0f}/{math.degrees(minus[0]):+.0f} deg/s)"
            )
            continue
        k = (plus[0] - minus[0]) / (2 * a)
        limit = a
        p2, m2 = turn[2 * a], turn[-2 * a]
        if (
            p2 is not None
            and m2 is not None
            and np.sign(k) * p2[0] > abs(plus[0])
            and -np.sign(k) * m2[0] > abs(minus[0])
            and min(p2[1], m2[1]) >= base["speed"] / 3
        ):
            limit = 2 * a
        found.append((weak / a * limit, kind, k, limit))
    found.sort(reverse=True)
    candidates = [
        Steering(
            kind=kind,
            turn_rate=k,
            limit=limit,
            period=period,
            travel_offset=base["travel_offset"],
            speed=base["speed"],
            why=f"{math.degrees(abs(k) * PROBE[kind]):.0f} deg/s at the probe",
        )
        for _, kind, k, limit in found
    ]
    if not candidates:
        return Steering(
            period=period,
            speed=base["speed"],
            travel_offset=base["travel_offset"],
            why="; ".join(notes) or "no input turned it",
        )
    if not check:
        return candidates[0]
    passed, failed = check_in_closed_loop(commands, candidates, simulator)
    if passed is not None:
        return passed
    return Steering(
        period=period,
        speed=base["speed"],
        travel_offset=base["travel_offset"],
        why="; ".join([*notes, *failed]),
    )


def check_in_closed_loop(
    commands: np.ndarray, candidates: list[Steering], simulator
) -> tuple[Steering | None, list[str]]:
    """The first candidate whose loop follows the nominal path turned +-20 deg about its start to
    within ``CHECK_TOLERANCE`` of its distance, and a line per candidate that failed."""
    reference = nominal_reference(commands, simulator, candidates[0].period)
    followers = []
    for steering in candidates:
        for turn in (CHECK_TURN, -CHECK_TURN):
            turned = cut_and_turn(reference, len(reference) - 1, reference[0], turn)
            followers.append(make_follower(commands, turned, steering, simulator, "arrive"))
    runs = run_closed_loop(simulator, followers)
    distance = max(float(np.linalg.norm(reference[-1] - reference[0])), 0.5)
    failed = []
    for i, steering in enumerate(candidates):
        errors = []
        for run, f in zip(runs[2 * i : 2 * i + 2], followers[2 * i : 2 * i + 2], strict=True):
            errors.append(
                np.inf if run.failure else float(np.linalg.norm(run.end - f.reference[-1])) / distance
            )
        if max(errors) <= CHECK_TOLERANCE:
            return steering, failed
        failed.append(
            f"{steering.kind.replace('_', ' ')} lost a path turned 20 deg "
            f"(ended {100 * max(errors):.0f}% of the distance off)"
        )
    return None, failed
