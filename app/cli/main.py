"""``snakeloco``: one console script, one subcommand per job. Each parses, then calls a plain function.

The options of each command are the pydantic models of ``commands.py``; ``options.py`` turns them into
flags and their bounds into one-line errors.
"""

from __future__ import annotations

import json as jsonlib
import sys
import time
from pathlib import Path

import tyro

from snakeloco.app.bench import report
from snakeloco.app.bench.options import BENCH_HELP, BENCH_MODULES, BENCHES
from snakeloco.app.cli.commands import (
    COMMANDS,
    ROBOT_COMMANDS,
    WORLD_COMMANDS,
    Build,
    Calibrate,
    Design,
    Evaluate,
    Export,
    Figures,
    FitRobot,
    Gait,
    Generate,
    Robot,
    RobotMjcf,
    RobotShow,
    Robustness,
    Serve,
    Train,
    World,
    WorldMjcf,
    WorldShow,
)
from snakeloco.app.cli.options import Command, OptionError, parse, parse_one
from snakeloco.app.cli.outputs import outputs_problem
from snakeloco.app.cli.progress import Progress
from snakeloco.app.cli.robot_commands import (
    _robot,
    run_build,
    run_export,
    run_fit_robot,
    run_robot_mjcf,
    run_robot_show,
    run_robustness,
    run_world_mjcf,
    run_world_show,
)
from snakeloco.model.options import PRESETS


def run_generate(cmd: Generate) -> Path:
    """Generate the dataset with a progress bar; returns the written path. Ctrl-C says what was kept."""

    from snakeloco.sim.data.generate import generate_dataset
    from snakeloco.sim.gaits.structured import DEFAULT_PRESET, STRUCTURED_PRESETS

    cfg = cmd.config
    if cmd.structured_preset is not None and cfg.family != "structured":
        raise OptionError(f"--structured-preset {cmd.structured_preset} needs --family structured")
    if cfg.family == "structured":
        cfg = cfg.model_copy(
            update={"structured": STRUCTURED_PRESETS[cmd.structured_preset or DEFAULT_PRESET]}
        )
    if cmd.robot is not None:
        from snakeloco.sim.robot.description import RobotError, load_robot

        try:
            cfg = cfg.model_copy(update={"robot": load_robot(cmd.robot)})
        except RobotError as exc:
            raise OptionError(str(exc)) from None
    from snakeloco.app.cli.robot_commands import world_option

    cfg = cfg.model_copy(update={"world": world_option(cmd.world)})
    t0 = time.perf_counter()
    progress = Progress(cfg.num_samples, "generate", unit="sample")
    try:
        with progress:
            path = generate_dataset(
                cfg,
                cmd.out,
                workers=cmd.workers,
                progress=progress,
                screened=cmd.screened,
                backend=cmd.backend,
            )
    except KeyboardInterrupt:
        partial = cmd.out.with_name(cmd.out.name + ".partial")
        done = progress.n
        kept = f": {done} of {cfg.num_samples} records are kept in {partial}; the same command resumes from there"
        print(
            "snakeloco: interrupted"
            + (f"{kept} (delete it to start over)" if partial.is_dir() else "; nothing was written"),
            file=sys.stderr,
        )
        raise SystemExit(130) from None
    size = _size(path) / 2**20
    print(f"wrote {path} ({cfg.num_samples} samples, {size:.1f} MiB) in {time.perf_counter() - t0:.1f} s")
    return path


def _size(path: Path) -> int:
    """Bytes of a file, or of every file in a folder (a zarr store)."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def run_design(cmd: Design) -> dict:
    """Design for the target, write the candidates and report.json (``app/cli/design_report.py``)."""
    from snakeloco.app.cli.design_report import write_design

    return write_design(cmd)


def run_gait(cmd: Gait) -> str:
    """Print the library (--list) and/or write one library gait as a gait CSV; returns what it printed."""
    from snakeloco.app.export.gait_csv import library_gait_csv
    from snakeloco.sim.gaits.library import library_table
    from snakeloco.sim.robot.description import DEFAULT_ROBOT

    if cmd.search_robust:
        from snakeloco.model.design.library import search_robust, write_library

        found = search_robust(cmd.checkpoint, cmd.gaits, cmd.top, cmd.workers, print, cmd.draws)
        if cmd.write_library:
            print(f"wrote {', '.join(write_library(found)) or 'no gait'} into the library")
        if cmd.json:
            print(jsonlib.dumps(found))
        return jsonlib.dumps(found)
    if not cmd.list and cmd.name is None:
        raise OptionError("name a library gait to write (NAME --out FILE.csv), or pass --list")
    if cmd.name is not None and cmd.out is None:
        raise OptionError(f"--out FILE.csv is needed to write the {cmd.name} gait")
    text = library_table() if cmd.list else ""
    if cmd.name is not None:
        cmd.out.parent.mkdir(parents=True, exist_ok=True)
        cmd.out.write_text(library_gait_csv(cmd.name, DEFAULT_ROBOT))
        text += f"wrote {cmd.out} (library gait {cmd.name}: 2000 rows at 20 Hz, rad)"
    print(text.rstrip())
    return text


def run_train(cmd: Train):
    """Train with the paper's schedule (model/vae/train.py documents it)."""
    from snakeloco.model.vae.train import train

    return train(cmd.data, cmd.out, cmd.train, cmd.model)


def run_evaluate(cmd: Evaluate) -> dict:
    """Evaluate and print the report."""
    from snakeloco.app.cli.evaluate_report import format_report
    from snakeloco.model.evaluate import ZK_MODES, evaluate

    with Progress(len(ZK_MODES) * cmd.consistency.prior_samples, "consistency") as progress:
        report = evaluate(
            cmd.checkpoint,
            cmd.data,
            cmd.consistency,
            cmd.workers,
            progress,
            cmd.replays,
            backend=cmd.backend,
            floor_records=cmd.floor_records,
            robustness=cmd.robustness,
            closed_loop=cmd.closed_loop,
        )
    print(format_report(report))
    if cmd.report is not None:
        cmd.report.parent.mkdir(parents=True, exist_ok=True)
        cmd.report.write_text(jsonlib.dumps(report, indent=1))
    if cmd.json:
        summary = {k: v for k, v in report.items() if k != "consistency"}
        summary["consistency"] = {
            mode: {k: v for k, v in c.items() if k != "gaits"}
            for mode, c in report.get("consistency", {}).items()
        }
        print(jsonlib.dumps(summary))
    return report


def run_calibrate(cmd: Calibrate) -> dict:
    """Replay prior gaits with a progress bar (none when --gaits reuses them), then fine-tune and save;
    with --sampler, fit the slider density and the member path head (``model.heads.sampler``); with
    --physics-head, the physics head (``model.heads.physics_head``)."""
    from snakeloco.model.heads.calibrate import calibrate
    from snakeloco.model.heads.sampler import fit_sampler
    from snakeloco.model.replays import Fit

    if cmd.physics_head:
        from snakeloco.model.heads.physics_fit import fit_physics_head, replay_count

        pc = cmd.physics_head_config
        with Progress(replay_count(pc), "replay members on other robots") as progress:
            fit = Fit(cmd.checkpoint, cmd.data, cmd.out, cmd.gaits, cmd.workers, cmd.backend, progress)
            return fit_physics_head(fit, pc)
    if cmd.data is None:
        raise OptionError("--data is needed: the dataset the checkpoint was trained on")
    sc = cmd.sampler_config
    if cmd.sampler:
        total, label = 0 if sc.density_only else 2 * sc.samples, "replay sampler members"
    else:
        total, label = cmd.config.gait_count, "replay prior gaits"
    with Progress(total, label) as progress:
        fit = Fit(cmd.checkpoint, cmd.data, cmd.out, cmd.gaits, cmd.workers, cmd.backend, progress)
        return fit_sampler(fit, sc) if cmd.sampler else calibrate(fit, cmd.config)


def run_figures(cmd: Figures) -> list[Path]:
    """Write the figures and list them."""
    from snakeloco.model.figures import figures

    paths = figures(cmd.checkpoint, cmd.data, cmd.out, cmd.seed, cmd.report)
    for p in paths:
        print(p)
    return paths


def run_serve(cmd: Serve) -> None:
    """Serve the designer until Ctrl-C / SIGTERM."""
    from snakeloco.app.cli.robot_commands import world_option
    from snakeloco.app.server.lifecycle import serve

    serve(
        cmd.host,
        cmd.port,
        tuple(cmd.checkpoint),
        cmd.ensemble,
        robot=None if cmd.robot is None else _robot(cmd.robot),
        variations=cmd.variations,
        closed_loop=cmd.closed_loop,
        world=world_option(cmd.world),
    )


def run_bench(cmd: Command) -> dict:
    """Run a benchmark (``BENCH_MODULES[NAME]``), print its summary (``app/bench/report.py``) and, with
    --json, its figures as one JSON object on the last line."""
    import importlib

    name = next(n for n, command in BENCHES.items() if command is type(cmd))
    bench = getattr(importlib.import_module(BENCH_MODULES[name]), f"bench_{name}")
    result = bench(**report.options(cmd))
    getattr(report, name)(result)
    if cmd.json:
        print(jsonlib.dumps(result))
    return result


RUNNERS = {
    Generate: run_generate,
    Design: run_design,
    Gait: run_gait,
    Train: run_train,
    Evaluate: run_evaluate,
    Calibrate: run_calibrate,
    Figures: run_figures,
    Serve: run_serve,
    RobotShow: run_robot_show,
    Robustness: run_robustness,
    Export: run_export,
    FitRobot: run_fit_robot,
    RobotMjcf: run_robot_mjcf,
    WorldShow: run_world_show,
    WorldMjcf: run_world_mjcf,
    Build: run_build,
    **dict.fromkeys(BENCHES.values(), run_bench),
}


def _preset(args: list[str]) -> str | None:
    """The name after ``--preset`` (or in ``--preset=NAME``), if the arguments give one."""
    for i, arg in enumerate(args):
        if arg == "--preset" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--preset="):
            return arg.split("=", 1)[1]
    return None


def parse_args(args: list[str]) -> Command:
    """The command ``args`` ask for (``OptionError`` when a value is out of its bounds)."""
    if args[:1] == ["bench"]:
        return parse(BENCHES, args[1:], "snakeloco bench", BENCH_HELP)
    if args[:1] == ["robot"]:
        return parse(ROBOT_COMMANDS, args[1:], "snakeloco robot", Robot.__doc__)
    if args[:1] == ["world"]:
        return parse(WORLD_COMMANDS, args[1:], "snakeloco world", World.__doc__)
    name = _preset(args) if args[:1] == ["train"] else None
    if name in PRESETS:
        # The preset supplies the defaults; the flags given beside it still override them. (An unknown
        # name is left to the parser below, which lists the choices.)
        preset = PRESETS[name]
        start = Train.model_construct(
            data=tyro.MISSING, out=tyro.MISSING, preset=name, train=preset.train, model=preset.model
        )
        return parse_one(Train, args[1:], "snakeloco train", start)
    return parse(COMMANDS, args, "snakeloco")


USER_ERRORS = (
    ("snakeloco.app.cli.options", "OptionError"),
    ("snakeloco.model.checkpoint", "CheckpointError"),
    ("snakeloco.sim.data.dataset", "DatasetError"),
    ("snakeloco.model.figures", "ReportError"),
    ("snakeloco.model.vae.train", "TrainingError"),
    ("snakeloco.sim.physics.results", "SimulationError"),
    ("snakeloco.sim.physics.backend", "BackendError"),
    ("snakeloco.app.bench.users.load_browser", "MissingBrowserError"),
)
"""Errors that mean bad input, not a bug: a one-line message and exit status 2 (module, class)."""


def _user_error(exc: Exception) -> bool:
    """Whether ``exc`` is one of ``USER_ERRORS``. Only modules already imported are looked in (an
    error of a module never imported cannot have been raised), so the command line imports no
    torch, MuJoCo or viser to answer ``--help``."""
    return any(
        isinstance(exc, getattr(sys.modules[module], name))
        for module, name in USER_ERRORS
        if module in sys.modules
    )


def main(args: list[str] | None = None) -> None:
    """Entry point of the ``snakeloco`` console script.

    An option out of its range, a bad input file (dataset, checkpoint, evaluate report), a path that
    cannot be read or written, a missing CUDA device, diverged training or a dataset sample that
    breaks the simulation in every phase draw ends the command with a one-line message naming the
    problem and exit status 2, not a traceback.
    """
    args = list(sys.argv[1:] if args is None else args)
    try:
        cmd = parse_args(args)
        problem = outputs_problem(cmd)
        if problem is not None:
            raise OptionError(problem)
        RUNNERS[type(cmd)](cmd)
    except OSError as exc:  # e.g. --out under a read-only or missing directory, a disk that is full
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"snakeloco: error: {where}{exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except Exception as exc:
        if not _user_error(exc):
            raise
        print(f"snakeloco: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
