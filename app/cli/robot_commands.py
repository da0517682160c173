"""The robot's subcommands: ``robot show|mjcf``, ``build``, ``robustness``, ``export`` and ``fit-robot`` (each
parses in ``app.cli.main``, then runs here)."""

from __future__ import annotations

import json as jsonlib
import time
from pathlib import Path

import numpy as np

from snakeloco.app.cli.commands import (
    Build,
    Export,
    FitRobot,
    RobotMjcf,
    RobotShow,
    Robustness,
    WorldMjcf,
    WorldShow,
)
from snakeloco.app.cli.options import OptionError
from snakeloco.sim.physics.body import BODY_CHANNELS, heading_text


def _robot(path: Path | None):
    from snakeloco.sim.robot.description import RobotError, resolve_robot

    try:
        return resolve_robot(path)
    except RobotError as exc:
        raise OptionError(str(exc)) from None


def _show(kind: str, description, json: bool) -> dict:
    """Print a description's figures, one per line (and with ``json`` it and them as one JSON line)."""
    figures = description.figures()
    width = max(map(len, figures))
    print("\n".join(f"{k:<{width}}  {v}" for k, v in figures.items()))
    if json:
        print(jsonlib.dumps({kind: description.model_dump(mode="json"), "figures": figures}))
    return figures


def run_robot_show(cmd: RobotShow) -> dict:
    """Print a robot description's derived figures (refusing a bad file with the field and reason)."""
    return _show("robot", _robot(cmd.robot), cmd.json)


def run_robot_mjcf(cmd: RobotMjcf) -> Path:
    """Write a robot description's MJCF."""
    robot = _robot(cmd.robot)
    cmd.out.parent.mkdir(parents=True, exist_ok=True)
    cmd.out.write_text(robot.mjcf())
    print(
        f"wrote {cmd.out} ({robot.name}: {robot.n_joints} joints, {robot.joint_pattern}, {robot.body_length:.3f} m)"
    )
    return cmd.out


def run_robustness(cmd: Robustness) -> dict:
    """Replay a gait over a variation set and print where each variation ends (``sim.scores.robustness``)."""
    from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.robot.description import RobotError
    from snakeloco.sim.robot.variations import variation_set
    from snakeloco.sim.scores.robustness import readout_line, robustness
    from snakeloco.sim.scores.terrain import terrain_robustness
    from snakeloco.sim.world.description import WorldError

    robot, world = _robot(cmd.robot), world_option(cmd.world)
    try:
        text = cmd.gait.read_text()
        table = read_gait_csv(text, robot)
        variations = None if cmd.set == "terrain" else variation_set(cmd.set)  # None: the worlds
    except (GaitCSVError, RobotError, ValueError) as exc:
        raise OptionError(
            f"{cmd.gait}: {exc}" if isinstance(exc, GaitCSVError) else f"--set: {exc}"
        ) from None
    if cmd.closed_loop:
        from snakeloco.app.cli.closed_loop_report import closed_loop_report

        return closed_loop_report(cmd, text, table.commands, robot, variations, world)
    t0 = time.perf_counter()
    simulator = Simulator(workers=cmd.workers, robot=robot, world=world)
    try:
        if variations is None:
            report = terrain_robustness(table.commands, simulator)
        else:
            report = robustness(table.commands, variations, simulator)
    except WorldError as exc:
        raise OptionError(f"--world: {exc}") from None
    finally:
        simulator.close()
    report.pop("bodies")
    report["seconds"] = round(time.perf_counter() - t0, 2)
    nom = report["nominal"]
    lines = [
        f"{cmd.gait} on {robot.name}{_on(world)} and {len(report['variations'])} "
        f"{'worlds' if variations is None else 'variations'} ({cmd.set} set), "
        f"{report['seconds']:.1f} s",
        f"{'':<28}{'forward m':>10}{'sideways m':>11}{'direction':>10}  {'heading change':<24}{'end error m':>12}{'rel':>7}",
        f"{'nominal' if variations is not None else 'on the flat ground':<28}{_end_cells(nom)}"
        + _off_flat(nom),
    ]
    if "flat" in report:
        lines.insert(2, f"{'on the flat ground':<28}{_end_cells(report['flat'])}")
    for r in report["variations"]:
        if r["failure"] is not None:
            lines.append(f"{r['name']:<28}  broke: {r['failure']}")
        else:
            lines.append(f"{r['name']:<28}{_end_cells(r)}{r['end_error_m']:>12.2f}{100 * r['rel']:>6.0f}%")
    lines.append(readout_line(report))
    print("\n".join(lines))
    if cmd.json:
        print(jsonlib.dumps(report))
    return report


def _on(world) -> str:
    return "" if world.name == "flat" and world.flat else f" on {world.name}"


def _off_flat(nominal: dict) -> str:
    """The nominal row's end error from the flat ground's end, where it was replayed on a world."""
    if "end_error_m" not in nominal:
        return ""
    return f"{nominal['end_error_m']:>12.2f}{100 * nominal['rel']:>6.0f}%"


def _end_cells(end: dict) -> str:
    """An end point's cells: forward, sideways (m), direction of travel and heading change."""
    heading = heading_text(360.0 * end["turns"])
    return f"{end['forward']:>10.2f}{end['sideways']:>11.2f}{end['direction_deg']:>+9.0f}°  {heading:<24}"


def run_export(cmd: Export) -> dict:
    """Write a gait in the chosen format (``app.export.formats``, ``app.export.share``); refuse with the joint, the
    time and the value where it breaks the robot's limits."""
    from snakeloco.app.export import formats as export
    from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv

    robot = _robot(cmd.robot)
    if cmd.closed_loop and cmd.format != "ros2":
        raise OptionError("--closed-loop is for --format ros2 (--format controller writes the whole loop)")
    try:
        text = cmd.gait.read_text()
        table = read_gait_csv(text, robot, limit=np.inf)  # the export checks the limits, saying where
        if cmd.format == "html":
            from snakeloco.app.export.share import share_html

            if cmd.out.exists() and not cmd.out.is_dir():
                raise OptionError(f"--out {cmd.out}: exists and is not a directory (html writes a folder)")
            result = share_html(table.commands, cmd.out, robot, title=cmd.gait.name, workers=cmd.workers)
            print(
                f"wrote {result['path']} ({result['bytes'] / 2**20:.2f} MiB, {result['frames']} frames) in "
                f"{result['seconds']:.1f} s: open it in a browser, no server needed"
            )
            return result
        if cmd.format == "controller":
            from snakeloco.app.export.controller import export_controller

            if cmd.out.exists() and not cmd.out.is_dir():
                raise OptionError(
                    f"--out {cmd.out}: exists and is not a directory (controller writes a folder)"
                )
            export.trajectory(table.commands, robot, clip=cmd.clip)  # refuses, naming the joint and time
            result = export_controller(text, table.commands, cmd.out, robot, str(cmd.gait), cmd.workers)
            print(
                f"wrote {result['path']}/ ({', '.join(result['files'])}): {result['steering_line']} "
                f"({result['steering_from']}); path {result['distance_m']:.2f} m. "
                "Load it with snakeloco.sim.control.PathFollower.load (docs/closed-loop.md)"
            )
            return result
        body, clipped = export.export_gait(
            text,
            cmd.format,
            robot,
            cmd.rate,
            cmd.units,
            cmd.velocities,
            cmd.periods,
            cmd.lead_in,
            cmd.clip,
            source=str(cmd.gait),
        )
    except (GaitCSVError, export.ExportError) as exc:
        raise OptionError(f"{cmd.gait}: {exc}") from None
    cmd.out.parent.mkdir(parents=True, exist_ok=True)
    cmd.out.write_text(body)
    print(f"wrote {cmd.out} ({cmd.format}, {len(body) / 1024:.0f} kB)")
    if cmd.closed_loop:
        if cmd.format != "ros2":
            raise OptionError(
                "--closed-loop is for --format ros2 (--format controller writes the whole loop)"
            )
        from snakeloco.app.export.controller import follower_for, follower_parameters, ros2_path

        follower, origin = follower_for(text, table.commands, robot, cmd.workers)
        path = cmd.out.with_name(cmd.out.stem + ".path.yaml")
        path.write_text(ros2_path(follower.reference, follower_parameters(follower)))
        print(f"wrote {path} (nav_msgs/Path, {follower.steering.line()}, {origin})")
    for line in clipped:
        print(f"clipped {line}")
    return {"path": str(cmd.out), "bytes": len(body), "clipped": clipped}


def run_fit_robot(cmd: FitRobot) -> dict:
    """Fit the robot to measured runs and write the fitted description, its plot and the report."""
    from snakeloco.app.cli.fit_report import fit_from_files

    return fit_from_files(cmd, _robot(cmd.robot))


def run_build(cmd: Build) -> dict:
    """Build a robot's model (``app.cli.build``); print each stage's wall time and the line to serve it."""
    from snakeloco.app.cli.build import QUICK, Build, BuildConfig, BuildError

    robot = _robot(cmd.robot)
    cfg = QUICK if cmd.quick else BuildConfig(records=cmd.records, epochs=cmd.epochs)
    try:
        build = Build(robot, cmd.out, cfg, cmd.workers, cmd.backend, world=world_option(cmd.world))
        state = build.run()
    except BuildError as exc:
        raise OptionError(str(exc)) from None
    f = state["evaluate"]["figures"]
    print(
        f"{robot.name}: held-out joint shape R² {f['shape_r2']:.3f}, body R² "
        f"{f.get('body_r2_reconstruction', f['body_r2']):.3f} (reconstruction; a member's path from its gait "
        f"alone {f['body_r2']:.3f})"
        + repeated_line(f)
        + f"; {f['positions']} sampler positions replayed: xy-path R² median {f['xy_r2_median']:.3f}, "
        f"final-position error median {100 * f['final_error_median']:.1f}% of the distance; end points "
        + ", ".join(f"{k} {v}" for k, v in f["sectors"].items())
    )
    print(
        "stages: "
        + ", ".join(
            f"{k} {state[k]['seconds']:.0f} s" for k in ("generate", "train", "calibrate", "evaluate")
        )
    )
    print(
        f"serve it: snakeloco serve --checkpoint {build.out}"
    )  # a build folder is its model (resolve_checkpoint)
    return state


def repeated_line(f: dict) -> str:
    """Where some body channels are not repeated by physics itself (a planar snake's vertical, roll
    and pitch): the body R² over those that are, named."""
    keep = f.get("body_channels_repeated")
    if not keep or len(keep) == len(BODY_CHANNELS) or f.get("body_r2_reconstruction_repeated") is None:
        return ""
    return (
        f", over the channels physics repeats ({', '.join(keep)}) {f['body_r2_reconstruction_repeated']:.3f} "
        f"(from the gait alone {f['body_r2_repeated']:.3f})"
    )


def world_option(name: str):
    """``--world``'s ground: flat (the default plane), a shipped world's name or a world YAML; a bad
    one is refused naming the file, the field and the reason."""
    from snakeloco.sim.world.description import DEFAULT_WORLD, WorldError, load_world

    if name == "flat":
        return DEFAULT_WORLD
    try:
        return load_world(name)
    except WorldError as exc:
        raise OptionError(str(exc)) from None


def run_world_show(cmd: WorldShow) -> dict:
    """Print a world description's figures (refusing a bad file with the field and reason)."""
    return _show("world", world_option(cmd.world), cmd.json)


def run_world_mjcf(cmd: WorldMjcf) -> Path:
    """Write a robot on a world as MJCF."""
    from snakeloco.sim.world.description import WorldError

    world, robot = world_option(cmd.world), _robot(cmd.robot)
    try:
        text = world.mjcf(robot)
    except WorldError as exc:
        raise OptionError(str(exc)) from None
    cmd.out.parent.mkdir(parents=True, exist_ok=True)
    cmd.out.write_text(text)
    print(
        f"wrote {cmd.out} ({robot.name} on {world.name}: {len(world.ground_geoms())} ground geoms beside the plane)"
    )
    return cmd.out
