"""``snakeloco fit-robot``: read the gait and measured-run pairs, fit (``sim.fit.fit_robot``), write the fitted
robot description, a plot of the paths and the report."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from snakeloco.app.cli.options import OptionError
from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv
from snakeloco.sim.fit.measured import MeasuredRunError, load_measured_run
from snakeloco.sim.robot.description import Robot


def read_pairs(measured: tuple[Path, ...], gaits: tuple[Path, ...], robot: Robot) -> list:
    """(commands, MeasuredRun) for each run; OptionError names the file and the problem."""
    if gaits and len(gaits) != len(measured):
        raise OptionError(
            f"--gait names {len(gaits)} gaits for {len(measured)} --measured runs: one each, in order"
        )
    pairs = []
    for i, path in enumerate(measured):
        try:
            run = load_measured_run(path)
        except MeasuredRunError as exc:
            raise OptionError(str(exc)) from None
        gait = gaits[i] if gaits else None
        if gait is None:
            if run.gait is None:
                raise OptionError(f"{path}: no '# gait:' line names the gait it ran; give --gait")
            gait = (Path(path).parent / run.gait).resolve()
        try:
            commands = read_gait_csv(Path(gait).read_bytes(), robot).commands
        except GaitCSVError as exc:
            raise OptionError(f"{gait}: {exc}") from None
        except OSError as exc:
            raise OptionError(f"{gait}: cannot read the gait ({exc.strerror})") from None
        if run.joints is not None and run.joints.shape[1] != commands.shape[1]:
            raise OptionError(
                f"{path}: {run.joints.shape[1]} measured joints, the gait {gait} has {commands.shape[1]}"
            )
        pairs.append((commands, run))
    return pairs


def plot_fit(pairs, robot: Robot, fitted: Robot, path: Path, simulator) -> Path:
    """Measured, nominal-replay and fitted-replay paths of each run, side by side, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from snakeloco.sim.gaits.excitation import RECORD

    n = len(pairs)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4.2), squeeze=False)
    cmds = np.stack([c for c, _ in pairs for _ in range(2)])
    result = simulator.simulate(cmds, robots=[r for _ in pairs for r in (robot, fitted)])
    for i, (ax, (_, run)) in enumerate(zip(axes[0], pairs, strict=True)):
        t = np.arange(RECORD.n_samples) / RECORD.sample_rate
        for k, (label, color) in enumerate((("nominal robot", "0.6"), ("fitted robot", "tab:blue"))):
            body = result.body[2 * i + k]
            keep = t <= run.times[-1]
            if not result.failures[2 * i + k]:
                ax.plot(body[keep, 1], body[keep, 2], color=color, lw=1.5, label=f"{label} (MuJoCo)")
        ax.plot(run.xy[:, 0], run.xy[:, 1], color="tab:red", lw=1.5, ls="--", label="measured")
        ax.plot(0, 0, "ko", ms=4)
        ax.set_title(Path(run.source).name, fontsize=9)
        ax.set_xlabel("forward (m)")
        ax.set_ylabel("sideways (m)")
        ax.set_aspect("equal", "datalim")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def format_fit(report: dict) -> str:
    lines = [
        f"fitted {len(report['params'])} fields on {len(report['before'])} runs: {report['replays']} replays, "
        f"{report['seconds']:.0f} s",
        f"{'field':<18}{'start':>10}{'fitted':>10}{'interval':>22}  determined",
    ]
    for name, p in report["params"].items():
        interval = f"{p['low']:.4g}-{p['high']:.4g}" if np.isfinite(p["high"]) else "not bounded"
        why = "yes" if p["determined"] else "no"
        if not p["determined"] and p.get("would_determine", {}).get("gait"):
            w = p["would_determine"]
            why += f" (a run of the {w['gait']} gait would: its end moves {100 * w['end_change_rel']:.0f}% when it doubles)"
        lines.append(f"{name:<18}{p['start']:>10.4g}{p['fitted']:>10.4g}{interval:>22}  {why}")
    lines.append("path error (RMS / end point, m):")
    for b, a in zip(report["before"], report["after"], strict=True):
        fmt = lambda e: "broke" if e.get("broke") else f"{e['rms_m']:.3f} / {e['end_m']:.3f}"  # noqa: E731
        lines.append(f"  {Path(b['run']).name}: nominal {fmt(b)} -> fitted {fmt(a)}")
    return "\n".join(lines)


def fit_from_files(cmd, robot: Robot) -> dict:
    """Run ``snakeloco fit-robot`` (``app.cli.commands.FitRobot``)."""
    from tqdm import tqdm

    from snakeloco.sim.fit.fit_robot import FitConfig, fit_robot
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.robot.variations import PHYSICAL_FIELDS

    bad = [p for p in cmd.params if p not in PHYSICAL_FIELDS]
    if bad:
        raise OptionError(f"--params {' '.join(bad)}: fit physical fields only: {', '.join(PHYSICAL_FIELDS)}")
    pairs = read_pairs(cmd.measured, cmd.gait, robot)
    cfg = FitConfig(
        params=tuple(cmd.params), generations=cmd.generations, seed=cmd.seed, joint_weight=cmd.joint_weight
    )
    simulator = Simulator(workers=cmd.workers, robot=robot)
    try:
        with tqdm(total=cfg.generations, desc="fit", unit="generation") as bar:
            try:
                report = fit_robot(pairs, robot, cfg, simulator, bar.update)
            except MeasuredRunError as exc:
                raise OptionError(str(exc)) from None
        fitted: Robot = report.pop("robot")
        cmd.out.parent.mkdir(parents=True, exist_ok=True)
        cmd.out.write_text(
            f"# fitted by snakeloco fit-robot to {', '.join(str(m) for m in cmd.measured)}\n"
            + fitted.to_yaml()
        )
        report["plot"] = str(plot_fit(pairs, robot, fitted, cmd.out.with_suffix(".png"), simulator))
    finally:
        simulator.close()
    report["out"] = str(cmd.out)
    print(format_fit(report))
    print(
        f"wrote {cmd.out} and {report['plot']}; serve on it: snakeloco serve --robot {cmd.out}",
        file=sys.stderr,
    )
    if cmd.json:
        print(json.dumps(finite(report)))
    return report


def finite(obj):
    """``obj`` with every non-finite float as None (JSON has no infinity)."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
