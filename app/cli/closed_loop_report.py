"""``snakeloco robustness GAIT.csv --closed-loop``: the gait played with its steering loop over a
variation set, printed as a table (``sim.scores.closed_loop``) beside what open loop did."""

from __future__ import annotations

import json as jsonlib
import time

import numpy as np


def closed_loop_report(cmd, text: str, commands: np.ndarray, robot, variations, world=None) -> dict:
    """Run and print the closed-loop table; returns the report (JSON-ready, ``runs`` dropped)."""
    from snakeloco.app.export.controller import gait_steering
    from snakeloco.sim.physics.backend import open_backend
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.scores.closed_loop import closed_loop_robustness
    from snakeloco.sim.scores.terrain import terrain_closed_loop

    simulator = Simulator(workers=cmd.workers, robot=robot, world=world)
    runner = (
        None
        if cmd.backend.backend == "local"
        else open_backend(cmd.backend, cmd.workers, robot=robot, world=world)
    )
    t0 = time.perf_counter()
    try:
        steering, origin = gait_steering(text, commands, simulator)
        if variations is None:  # --set terrain: the worlds, each following the flat ground's path
            report = terrain_closed_loop(commands, simulator, steering, end=cmd.end)
        else:
            report = closed_loop_robustness(
                commands, variations, simulator, steering, end=cmd.end, runner=runner
            )
    finally:
        simulator.close()
        if runner is not None:
            runner.close()
    report.pop("runs")
    report["steering_from"] = origin
    report["seconds"] = round(time.perf_counter() - t0, 2)
    on = f" on {report['world']}" if "world" in report else ""
    print("\n".join(closed_loop_lines(report, f"{cmd.gait} on {robot.name}{on}", cmd.set)))
    if cmd.json:
        print(jsonlib.dumps(report))
    return report


def closed_loop_lines(report: dict, title: str, set_name: str) -> list[str]:
    """The table a person reads: one row per variation."""
    n, terrain = len(report["variations"]), report.get("set") == "terrain"
    kind, nominal, other = (
        ("worlds", "flat ground", "ground") if terrain else ("variations", "nominal", "robots")
    )
    lines = [
        f"{title}, closed loop ({report['end']}), {n} {kind} ({set_name} set), {report['seconds']:.1f} s",
        f"{report['steering_line']} ({report['steering_from']}); path {report['distance_m']:.2f} m to "
        f"({report['reference_end'][0]:.2f}, {report['reference_end'][1]:.2f})",
        f"{'':<28}{'forward m':>10}{'sideways m':>11}{'end error m':>12}{'rel':>7}{'arrival s':>10}"
        f"{'max xtrack m':>13}{'at limit':>9}",
    ]
    for r in [{"name": nominal, **report["nominal"]}, *report["variations"]]:
        if r["failure"] is not None:
            lines.append(f"{r['name']:<28}  broke: {r['failure']}")
            continue
        arrival = f"{r['arrival_s']:.1f}" if r["arrival_s"] is not None else "late"
        lines.append(
            f"{r['name']:<28}{r['forward']:>10.2f}{r['sideways']:>11.2f}{r['end_error_m']:>12.2f}"
            f"{100 * r['rel']:>6.1f}%{arrival:>10}{r['max_cross_track_m']:>13.2f}{100 * r['saturated']:>8.0f}%"
        )
    if report["worst_end_error_m"] is not None:
        late = f"; did not arrive by the cap: {', '.join(report['late'])}" if report["late"] else ""
        lines.append(
            f"closed loop on other {other}: ends within {report['worst_end_error_m']:.2f} m "
            f"({100 * report['worst_rel']:.0f}%); worst: {report['worst']}{late}"
        )
    return lines
