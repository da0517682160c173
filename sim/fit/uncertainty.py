"""How well measured runs determine each fitted field (``sim.fit.fit_robot``; docs/calibration.md, "The fit").

Around the fit's estimate each field is probed at +/-15% (the others fixed): the loss's slope gives
the half-width in which it rises by the tolerance (its own value at the estimate, i.e. the misfit
doubles, at least ``FitConfig.min_tolerance``), and at least twice the search's final spread. A
field whose half-width is over 15% is *not determined* by the runs; ``most_sensitive_gait`` names
the library gait that would determine it.
"""

from __future__ import annotations

import math

import numpy as np

from snakeloco.sim.robot.description import Robot, robot_from_dict

ADDITIVE = {"slope_deg": (0.0, 10.0), "slope_direction_deg": (-180.0, 180.0), "latency": (0.0, 0.1)}
"""Fields searched on a linear range (they start at 0, where a factor means nothing)."""
PROBE = math.log(1.15)
"""Log step of the uncertainty probe (15%)."""


class FitCancelled(Exception):
    """The fit's replays were dropped (a designer tab moved on): there is no result."""


def uncertainty(fit, x: np.ndarray, loss: float, spread: np.ndarray | None = None) -> dict[str, dict]:
    """Each field's fitted value, the interval in which the loss of ``fit`` (a ``sim.fit.fit_robot.RobotFit``)
    rises by at most the tolerance (at least twice the search's final spread ``spread``, in search
    coordinates), and whether the runs determine it (module docstring)."""
    cfg = fit.cfg
    tolerance = max(loss, cfg.min_tolerance)
    probes, steps = [], []
    for i, name in enumerate(cfg.params):
        if name in ADDITIVE:
            lo, hi = ADDITIVE[name]
            h = 0.15 * 2 / (hi - lo) * max(1.0, 0.1 * (hi - lo))  # 15% of a tenth of the range, in x
        else:
            h = PROBE / math.log(cfg.bound)
        steps.append(h)
        for sign in (1, -1):
            xp = x.copy()
            xp[i] += sign * h
            probes.append(fit.robot(xp))
    around = fit.losses(probes)
    fitted = fit.robot(x)
    out = {}
    for i, name in enumerate(cfg.params):
        up, down = around[2 * i], around[2 * i + 1]
        # An RMS path error grows in proportion to a small change (a V, not a parabola): its slope
        # over the probe's step gives the change that raises the loss by the tolerance.
        slope = (up + down - 2 * loss) / (2 * steps[i])
        half = tolerance / slope if slope > 0 else math.inf  # in x
        if spread is not None:
            half = max(half, 2 * float(spread[i]))
        value = float(getattr(fitted, name))
        if name in ADDITIVE:
            lo_r, hi_r = ADDITIVE[name]
            width = half * (hi_r - lo_r) / 2
            low, high = value - width, value + width
            rel = width / max(abs(value), 1e-9) if math.isfinite(width) else math.inf
            determined = math.isfinite(width) and width <= 0.15 * (hi_r - lo_r) / 10
        else:
            factor = cfg.bound**half if math.isfinite(half) else math.inf
            low, high = value / factor, value * factor
            rel = factor - 1
            determined = rel <= 0.15
        out[name] = {
            "start": float(getattr(fit.start, name)),
            "fitted": value,
            "low": low,
            "high": high,
            "rel_uncertainty": rel,
            "determined": bool(determined),
            "loss_rise": [float(up - loss), float(down - loss)],
        }
    return out


def most_sensitive_gait(robot: Robot, name: str, simulator) -> dict:
    """The library gait whose 100 s end point moves most when ``name`` doubles (or, for a field that
    starts at 0, moves to a tenth of its range) on ``robot``: the run that would determine it."""
    from snakeloco.sim.gaits.library import BASE_GAITS, PRESETS

    values = robot.model_dump()
    if name in ADDITIVE:
        lo, hi = ADDITIVE[name]
        values[name] += 0.1 * (hi - lo)
    else:
        values[name] *= 2
    changed = robot_from_dict(values, f"{robot.name} with {name} changed")
    names = list(BASE_GAITS)
    cmds = np.stack([PRESETS[n].gait.commands(robot) for n in names for _ in range(2)])
    result = simulator.simulate(cmds, robots=[r for _ in names for r in (robot, changed)])
    if result is None:
        raise FitCancelled
    best = {"gait": None, "end_change_rel": 0.0}
    for i, n in enumerate(names):
        if result.failures[2 * i] or result.failures[2 * i + 1]:
            continue
        a, b = result.body[2 * i, -1, 1:3], result.body[2 * i + 1, -1, 1:3]
        rel = float(np.hypot(*(a - b)) / max(np.hypot(*a), 0.5))
        if rel > best["end_change_rel"]:
            best = {"gait": n, "end_change_rel": rel}
    return best
