"""``snakeloco design``: run the search and its verification, write candidate_N.csv (gait CSV) and
report.json to the command's OUT, say whether the target was met (or the closest reached)."""

from __future__ import annotations

import json as jsonlib
import time


def write_design(cmd) -> dict:
    """Design, write the candidates' gait CSVs and report.json, say whether the target was met."""
    import sys

    from snakeloco.app.cli.options import OptionError
    from snakeloco.app.cli.robot_commands import world_option
    from snakeloco.app.export.gait_csv import PATH_KEY, STEERING_KEY, write_gait_csv
    from snakeloco.model import load_pretrained
    from snakeloco.model.design.search import design
    from snakeloco.sim.robot.description import RobotError, resolve_robot

    t0 = time.perf_counter()
    world = world_option(cmd.world)
    model = load_pretrained(cmd.checkpoint)
    try:
        robot = resolve_robot(cmd.robot) if cmd.robot is not None else model.robot
    except RobotError as exc:
        raise OptionError(str(exc)) from None
    if robot.n_joints != model.robot.n_joints:
        raise OptionError(
            f"--robot {robot.name} has {robot.n_joints} joints; the checkpoint was trained on "
            f"{model.robot.name} of {model.robot.n_joints}"
        )
    if warning := model.robot_warning(robot):
        print(f"snakeloco: warning: {warning}", file=sys.stderr)
    searched, searched_on = model, "the checkpoint's robot"
    if robot.mjcf_sha256 != model.robot.mjcf_sha256 and model.projects and model.members.covers(robot):
        from snakeloco.model.heads.physics_head import OnRobot

        searched, searched_on = OnRobot(model, robot), f"the physics head's paths on {robot.name}"
    if cmd.robust and cmd.closed_loop:
        raise OptionError("--robust and --closed-loop rank candidates two ways: choose one")
    common = {"backend": cmd.backend, "workers": cmd.workers, "robot": robot, "world": world}
    if cmd.closed_loop:
        from snakeloco.model.design.closed_loop import closed_loop_design

        result = closed_loop_design(searched, cmd.target, cmd.config, **common)
    elif cmd.robust:
        from snakeloco.model.design.robust import robust_design

        result = robust_design(searched, cmd.target, cmd.config, score=cmd.robust_score, **common)
    else:
        result = design(searched, cmd.target, cmd.config, **common)
    robust = result.extra.get("robust")
    cmd.out.mkdir(parents=True, exist_ok=True)
    candidates = []
    for rank, c in enumerate(result.candidates, start=1):
        csv = cmd.out / f"candidate_{rank}.csv"
        comments = {
            "snakeloco gait": "commands (rad) at 20 Hz, replay with `snakeloco` or sim.physics.replay",
            "designed for": _target_text(cmd.target),
            "z_B": "[" + ", ".join(f"{v:.4f}" for v in c.z_b) + "]",
            "z_k mode": "zero",
            "checkpoint sha256": model.hash,
            "simulated": "broke"
            if c.simulated is None
            else f"forward {c.simulated[0]:.3f} m, sideways "
            f"{c.simulated[1]:.3f} m, heading {c.simulated[2]:.1f} deg, error {c.error_m:.3f} m, ensemble "
            f"spread {c.spread_m:.3f} m",
        }
        if robust is not None:
            r = robust[rank - 1]
            loop = " closed loop" if r.get("closed_loop") else ""
            comments["on other robots"] = (
                f"worst{loop} {r['worst_m']:.3f} m from the target ({r['worst_variation']}), p90 {r['p90_m']:.3f} m "
                f"over {r['replayed']} physics variations"
            )
            if "steering" in r:
                comments[STEERING_KEY] = jsonlib.dumps(r["steering"], separators=(",", ":"))
            if "path" in r:
                comments[PATH_KEY] = jsonlib.dumps(r["path"], separators=(",", ":"))
        csv.write_text(write_gait_csv(model.commands(c.shape), comments, model.robot))
        candidates.append({"csv": str(csv), **c.report(), **({"robust": robust[rank - 1]} if robust else {})})
    report = {
        "target": cmd.target.model_dump(),
        "tolerance_m": result.tolerance_m,
        "met": result.met,
        "candidates": candidates,
        "checkpoint": str(model.path),
        "searched_on": searched_on,
        "search_s": result.search_s,
        "physics_s": result.physics_s,
        "replays": result.replays,
        "rounds": result.rounds,
        "seconds": time.perf_counter() - t0,
        "robot": robot.name,
        "world": world.name,
        "robust": None if robust is None else result.extra["score"],
        "closed_loop": bool(result.extra.get("closed_loop")),
        "beyond_reach": result.extra.get("beyond_reach"),
    }
    (cmd.out / "report.json").write_text(jsonlib.dumps(report, indent=1))
    best = result.candidates[0] if result.candidates else None
    if best is not None and robust and best.simulated is not None:
        r = robust[0]
        print(
            f"{result.verdict()}; {len(candidates)} candidates in {cmd.out}"
            + (
                f" ({r['steering_line']}; its path turned {r['path']['turn_deg']:.0f} deg, cut at the target)"
                if "path" in r
                else ""
            )
        )
    elif best is None or best.simulated is None:
        print(f"not met: every candidate broke the simulation; report in {cmd.out / 'report.json'}")
    else:
        where = f"forward {best.simulated[0]:.2f} m, sideways {best.simulated[1]:.2f} m"
        verdict = "met" if result.met else "not met: the closest reached is"
        if (far := result.extra.get("beyond_reach")) is not None:
            verdict = (
                f"not met: the target is {far['distance_m']:.3g} m away, beyond the family's reach (its gaits "
                f"end at most {far['reach_m']:.1f} m from the start), so no search was run; its nearest gait ends at"
            )
        print(
            f"{verdict} {where} ({best.error_m:.2f} m from the target, tolerance {result.tolerance_m:.2f} m; "
            f"ensemble spread {best.spread_m:.2f} m); {len(candidates)} candidates in {cmd.out} "
            f"({result.rounds} rounds; search {result.search_s:.1f} s, physics {result.physics_s:.1f} s for "
            f"{result.replays} replays)"
        )
        if robust:
            r = robust[0]
            loop = f" closed loop ({r['steering_line']})" if r.get("closed_loop") else ""
            print(
                f"on other robots candidate 1{loop} ends at most {r['worst_m']:.2f} m from the target "
                f"({r['worst_variation']}; p90 {r['p90_m']:.2f} m over {r['replayed']} variations)"
            )
    if cmd.json:
        print(jsonlib.dumps(report))
    return report


def _target_text(t) -> str:
    text = f"forward {t.forward} m, sideways {t.sideways} m"
    if t.heading is not None:
        text += f", heading {t.heading} deg"
    if t.max_roll is not None:
        text += f", |net roll| <= {t.max_roll} rad"
    return text
