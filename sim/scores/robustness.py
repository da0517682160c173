"""How a gait fares on robots other than the nominal one: its replays over a variation set.

A gait's end point is where the body frame ends after the 100 s record, in the start frame
(forward, sideways in m; ``sim.physics.body``), with ``sim.physics.body.travel``'s figures. A
variation's end error is the distance between its end point and the nominal replay's, and its
relative error that distance over max(nominal distance, ``MIN_DISTANCE``): a gait that barely moves
is not a base for a percentage.

A variation that breaks the simulation (MuJoCo reset it, the snake was thrown) is reported with its
``failure`` and left out of the worst case; it never raises. Only the nominal replay breaking
raises ``SimulationError``: then there is no gait to compare with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from snakeloco.sim.physics.body import travel
from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.robot.variations import Variation
from snakeloco.sim.world.description import DEFAULT_WORLD

MIN_DISTANCE = 0.5
"""Metres: below this nominal distance the relative error is taken against 0.5 m."""


def relative_change(end, reference) -> np.ndarray:
    """|end - reference| / max(|reference|, ``MIN_DISTANCE``) over the last axis (x, y): how far an end
    point moved, relative to the distance the reference travelled (a gait that barely moves is
    judged against half a metre)."""
    end, reference = np.asarray(end, np.float64), np.asarray(reference, np.float64)
    return np.linalg.norm(end - reference, axis=-1) / np.maximum(
        np.linalg.norm(reference, axis=-1), MIN_DISTANCE
    )


def end_point(body: np.ndarray) -> dict[str, float]:
    """Where a body series (T, 6) ends: forward, sideways (m) and ``sim.physics.body.travel``'s
    distance, direction of travel, heading change and turns."""
    return {"forward": float(body[-1, 1]), "sideways": float(body[-1, 2]), **travel(body)}


def robustness(
    commands: np.ndarray,
    variations: Sequence[Variation],
    simulator=None,
    robot: Robot | None = None,
) -> dict:
    """Replay ``commands`` (T, J) rad on the nominal robot and on each variation of it, in one batch.

    ``simulator``: a ``sim.physics.simulator.Simulator`` of ``robot`` (one is made where None). Returns
    ``{"nominal": {forward, sideways, distance_m, direction_deg, heading_change_deg, turns},
    "variations": [{name, params, forward, sideways, ..., end_error_m, rel, failure}], "worst_end_error_m", "worst_rel",
    "worst"}`` (on a world other than the flat default also ``"world"`` and ``"flat"``: the flat replay's
    end, the nominal's ``end_error_m`` and ``rel`` from it), the body series under ``"bodies"`` ((1 + V, T, 6), nominal first; NaN rows where a
    variation broke) for drawing.
    """
    if simulator is None:
        from snakeloco.sim.physics.simulator import Simulator

        simulator = Simulator(workers=None, robot=robot)
    nominal = simulator.robot
    robots = [nominal, *(v.apply(nominal) for v in variations)]
    commands = np.asarray(commands, np.float64)
    batch = np.broadcast_to(commands, (len(robots), *commands.shape))
    result = simulator.simulate(batch, robots=robots)
    if result.failures[0] is not None:
        raise SimulationError(f"the nominal replay broke: {result.failures[0]}")
    report = summarise(result.body[0], variations, result.body[1:], result.failures[1:])
    if on_world(simulator):
        report["world"] = simulator.world.name
        report["flat"] = off_the_flat(report["nominal"], flat_replay(commands, simulator))
    return report


def on_world(simulator) -> bool:
    """Whether ``simulator`` replays on a world other than the default flat plane."""
    world = getattr(simulator, "world", None)
    return world is not None and world != DEFAULT_WORLD


def flat_simulator(simulator):
    """A simulator of ``simulator``'s robot on the default flat ground (close it after use)."""
    from snakeloco.sim.physics.simulator import Simulator

    return Simulator(simulator.workers, simulator.excitation, simulator.config, robot=simulator.robot)


def flat_replay(commands: np.ndarray, simulator) -> np.ndarray:
    """The body series (T, 6) of ``commands`` on ``simulator``'s robot on the default flat ground: the
    path a gait replayed on a world is measured from."""
    flat = flat_simulator(simulator)
    try:
        return flat.replay(commands).body
    finally:
        flat.close()


def off_the_flat(nominal: dict, flat_body: np.ndarray) -> dict:
    """Where the flat ground's replay ends, and the world's nominal end error from it: ``nominal``
    gains ``end_error_m`` and ``rel`` (from the flat end, over the flat distance)."""
    flat = end_point(flat_body)
    flat_xy = np.array([flat["forward"], flat["sideways"]])
    xy = np.array([nominal["forward"], nominal["sideways"]])
    nominal["end_error_m"] = float(np.hypot(*(xy - flat_xy)))
    nominal["rel"] = float(relative_change(xy, flat_xy))
    return flat


def summarise(
    nominal: np.ndarray,
    variations: Sequence[Variation],
    bodies: Sequence[np.ndarray],
    failures: Sequence[str | None],
) -> dict:
    """The report of ``robustness`` from the nominal replay's body (T, 6) and each variation's body
    and failure (None: it ran cleanly), in the order of ``variations``."""
    home = end_point(nominal)
    home_xy = np.array([home["forward"], home["sideways"]])
    rows = []
    for v, body, failure in zip(variations, bodies, failures, strict=True):
        row: dict = {"name": v.name, "params": v.params()}
        if failure is not None:
            row.update(forward=None, sideways=None, end_error_m=None, rel=None)
        else:
            end = end_point(body)
            xy = np.array([end["forward"], end["sideways"]])
            err = float(np.hypot(*(xy - home_xy)))
            row.update(end, end_error_m=err, rel=float(relative_change(xy, home_xy)))
        row["failure"] = failure
        rows.append(row)
    scored = [r for r in rows if r["failure"] is None]
    worst = max(scored, key=lambda r: r["end_error_m"], default=None)
    bodies = np.array([nominal, *bodies])
    for i, failure in enumerate(failures, start=1):
        if failure is not None:
            bodies[i] = np.nan
    return {
        "nominal": home,
        "variations": rows,
        "worst_end_error_m": None if worst is None else worst["end_error_m"],
        "worst_rel": None if worst is None else worst["rel"],
        "worst": None if worst is None else worst["name"],
        "broken": [r["name"] for r in rows if r["failure"] is not None],
        "bodies": bodies,
    }


def readout_line(report: dict) -> str:
    """The designer's one line: 'on other robots: ends within 1.3 m (18%); worst: floor friction x0.5'."""
    other = "on other ground" if report.get("set") == "terrain" else "on other robots"
    if report["worst_end_error_m"] is None:
        return f"{other}: every variation broke the simulation"
    distance = float(np.hypot(report["nominal"]["forward"], report["nominal"]["sideways"]))
    rel = f" ({100 * report['worst_rel']:.0f}%)" if distance >= MIN_DISTANCE else ""
    broken = f"; broke: {', '.join(report['broken'])}" if report["broken"] else ""
    return f"{other}: ends within {report['worst_end_error_m']:.1f} m{rel}; worst: {report['worst']}{broken}"


def prediction_errors(predicted: dict, replayed: dict) -> np.ndarray:
    """How far each variation's predicted end (a ``summarise`` report of predicted paths) is from
    its replayed end, over the replay's distance (floored at ``MIN_DISTANCE``): (V,), NaN where the
    replay broke."""
    out = []
    for p, r in zip(predicted["variations"], replayed["variations"], strict=True):
        if r["failure"] is not None or p["failure"] is not None:
            out.append(np.nan)
            continue
        out.append(relative_change([p["forward"], p["sideways"]], [r["forward"], r["sideways"]]))
    return np.array(out)


def prediction_line(predicted: dict, replayed: dict) -> str:
    """'predicted within 6% (median; worst 14%: servo kp x0.5)': how the predicted fan's ends met
    the replays'."""
    errors = prediction_errors(predicted, replayed)
    if not np.isfinite(errors).any():
        return "no variation replayed to check the prediction"
    worst = int(np.nanargmax(errors))
    return (
        f"predicted within {100 * np.nanmedian(errors):.0f}% (median; worst "
        f"{100 * errors[worst]:.0f}%: {predicted['variations'][worst]['name']})"
    )


def change_table(kinds: Sequence[str], ends: dict[str, np.ndarray], floor: str | None = None) -> dict:
    """How far each variation moves many gaits' end points, per kind: the issue's table for sampler
    positions.

    ``ends``: per replay name, each gait's end point (N, 2) m in its start frame (NaN where that
    replay broke), ``"nominal"`` among them; ``kinds``: each gait's kind (N,). A gait's change is
    |end - nominal end| / max(|nominal end|, ``MIN_DISTANCE``), as ``summarise``'s ``rel``. Returns
    per kind and for ``"all"``: ``n`` (gaits whose nominal replay ran), the median change per
    replay name (``"median"``), the share of gaits each broke (``"broken"``), and with ``floor`` (the
    name of the noise replay) ``"times_floor"``: each median over the floor's median.
    """
    home = np.asarray(ends["nominal"], np.float64)
    rel = {name: relative_change(e, home) for name, e in ends.items() if name != "nominal"}
    kinds = np.asarray(kinds)
    ran = np.isfinite(home).all(axis=-1)
    out = {}
    for kind in ["all", *dict.fromkeys(kinds.tolist())]:
        mine = ran & ((kinds == kind) if kind != "all" else True)
        if not mine.any():
            continue
        median = {
            n: float(np.nanmedian(r[mine])) if np.isfinite(r[mine]).any() else None for n, r in rel.items()
        }
        row = {
            "n": int(mine.sum()),
            "distance_m_median": float(np.median(np.linalg.norm(home[mine], axis=-1))),
            "median": median,
            "broken": {n: float(np.mean(~np.isfinite(r[mine]))) for n, r in rel.items()},
        }
        if floor is not None and median.get(floor):
            row["times_floor"] = {n: None if m is None else m / median[floor] for n, m in median.items()}
        out[kind] = row
    return out
