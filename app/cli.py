"""``snakeloco``: one console script, one subcommand per job. Each parses, then calls a plain function."""

from __future__ import annotations

import dataclasses
import json as jsonlib
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class Generate:
    """Generate a training dataset of multisine rollouts (deterministic in N and seed, written atomically)."""

    out: Path
    """Destination .npz file."""
    num_samples: int = 4096
    """Number of 100 s records N."""
    seed: int = 0
    """Seed of the phase draws: the same N and seed give identical arrays."""
    workers: int | None = None
    """Simulation threads (default: all cores). Does not change the result."""


@dataclass
class Train:
    """Train the hierarchical VAE; writes the best-on-validation checkpoint and metrics.jsonl to OUT."""

    data: Path
    """Dataset .npz from `snakeloco generate`."""
    out: Path
    """Checkpoint directory (model.safetensors, config.json, metrics.jsonl)."""
    epochs: int = 300
    """Training epochs."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Torch device; cuda only when present."""
    seed: int = 0
    """Seed of the split, initialisation and batches."""
    batch_size: int = 128
    """Samples per step."""
    cycle_epochs: float = 50.0
    """Period of the cyclical learning rate (epochs); the paper's 800 scaled to a shorter run."""
    alpha: float = 4.0
    """Weight of the body-path reconstruction (eq. 15's alpha); 4 (shipped) uses 5 of 6 z_B units, 1 used 3."""
    beta: float = 10.0
    """Weight of MMD(q(z_k) || p(z_k))."""
    gamma: float = 10.0
    """Weight of MMD(q(z_B) || N(0, I))."""
    body_sees_stats: bool = True
    """Modulate the body decoder by the gait's predicted statistics (README, Model)."""
    z_b_dim: int = 6
    """Body latent dimensions, one designer slider each (1-8; shipped: 6)."""


@dataclass
class Evaluate:
    """Evaluate a checkpoint: reconstruction R^2, latent health, and generated-gait consistency vs physics."""

    data: Path
    """Held-out dataset .npz (generate it with a seed not used for training)."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    prior_samples: int = 256
    """z_B drawn from the prior for the consistency check (0 skips it)."""
    ensemble: int = 8
    """Replays per generated gait: the commands plus ensemble-1 copies with 1e-3 relative noise."""
    seed: int = 0
    """Seed of the prior draws and noise."""
    workers: int | None = None
    """Simulation threads (default: all cores)."""
    json: bool = False
    """Print the figures as one JSON object on the last line."""
    report: Path | None = None
    """Also write the figures, with every generated gait's statistics, to this JSON file."""
    replays: Path | None = None
    """Consistency replays (.npz): reused when the file exists (it must hold this checkpoint's decodes of the same draw), else written there after replaying; re-scores a recalibrated checkpoint without simulating."""


@dataclass
class Calibrate:
    """Fine-tune the statistics head and the body decoder on replays of the model's own prior gaits (model/calibrate.py)."""

    data: Path
    """The dataset .npz the checkpoint was trained on (its training split is mixed in)."""
    out: Path
    """Directory for the calibrated checkpoint (may be the input checkpoint's own)."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    prior_samples: int = 512
    """z_B drawn from the prior; each is decoded with z_k = 0 and sampled at temperatures 0.5 and 1."""
    zero_samples: int | None = None
    """Further z_B decoded with z_k = 0 only (default: 4 x --prior-samples); their own seed, --seed + 1000."""
    sampled_samples: int | None = None
    """Further z_B decoded with z_k sampled at each temperature (default: 2 x --prior-samples); their own seed, --seed + 2000."""
    epochs: int = 40
    """Fine-tuning epochs of each stage (statistics head, then body decoder)."""
    lr: float = 1e-2
    """Peak learning rate of both stages (Adam, cosine decay to 1% of it)."""
    seed: int = 1000
    """Seed of the z_B draws (evaluate's consistency check draws with seed 0)."""
    workers: int | None = None
    """Simulation threads (default: all cores)."""
    gaits: Path | None = None
    """Replayed calibration gaits (.npz): reused when the file exists (it must hold this checkpoint's decodes of the same samples and seed), else written there after replaying."""
    head_loss: Literal["l1", "mse"] = "l1"
    """Loss of the statistics head on normalised statistics: l1 fits each statistic's median (what the consistency check's median relative error rewards), mse its mean (the previous default)."""
    path_fit: Literal["decoder", "film"] = "decoder"
    """What the second stage fits to the replayed body paths: the whole body decoder, or only its FiLM layer (the statistics' modulation; the previous default)."""
    sampled_repeat: int = 1
    """How many times the statistics head sees each sampled-z_k gait per epoch (new sampled draws, --sampled-samples, helped where repeats did not)."""


@dataclass
class Figures:
    """Write PNG figures like the paper's Figs. 5-8 (fit, prior sweep, z_k samples, joint shapes) and, with --report, fig. 9 (consistency)."""

    data: Path
    """Dataset .npz for the fit figure."""
    out: Path
    """Output directory."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    seed: int = 0
    """Seed of the sample choice and latent draws."""
    report: Path | None = None
    """A JSON report from `snakeloco evaluate --report` for the consistency figure (fig9)."""


@dataclass
class BenchModel:
    """Benchmark decoding: latency of one z_B (the slider path) p50/p95 and batch throughput."""

    json: bool = False
    """Print the figures as one JSON object on the last line."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    calls: int = 200
    """Timed single decodes."""


@dataclass
class Serve:
    """Open the browser gait designer (viser) on a checkpoint. The UI has no authentication."""

    host: str = "127.0.0.1"
    """Interface to bind; the default keeps the designer on this machine. Use 0.0.0.0 only on a trusted network."""
    port: int = 8080
    """TCP port."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    ensemble: int = 8
    """Replays per gait for the predictability fan (the gait plus ensemble-1 noisy copies)."""


@dataclass
class BenchApp:
    """Benchmark the designer through a real server: slider -> decoded view / replay ready, vs bare MuJoCo."""

    json: bool = False
    """Print the figures as one JSON object on the last line."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    moves: int = 20
    """Slider moves to time."""


@dataclass
class BenchLoad:
    """Several headless Chromium tabs drag sliders on one server: latency, exceptions, stale draws, RSS."""

    clients: int = 4
    """Browser tabs in the multi-client phase (a single-client phase runs first, side by side)."""
    seconds: float = 60.0
    """Length of each phase."""
    json: bool = False
    """Print the figures as one JSON object on the last line."""
    checkpoint: Path | None = None
    """Checkpoint directory (default: the shipped pretrained model)."""
    ensemble: int = 8
    """Replays per gait (as in `snakeloco serve`)."""
    seed: int = 0
    """Seed of the drag targets."""
    render: bool = False
    """Let the pages draw the 3D view and animate the snake (software WebGL: far fewer slider updates)."""
    pin_cpus: bool = False
    """Pin the server to the first half of the CPUs and the browsers to the second half."""


@dataclass
class BenchSim:
    """Benchmark the simulator: raw mujoco.rollout vs the generator, replay vs a bare mj_step loop."""

    json: bool = False
    """Print the figures as one JSON object on the last line."""
    workers: int | None = None
    """Threads (default: all cores)."""
    samples: int | None = None
    """Records per batch (default: 4 per thread)."""
    repeats: int = 3
    """Runs of each measurement; the best is kept."""


@dataclass
class Bench:
    """Benchmarks measured side by side in one run: `snakeloco bench {sim,model,app,load} --help`."""


COMMANDS: dict[str, type] = {
    "generate": Generate,
    "train": Train,
    "evaluate": Evaluate,
    "calibrate": Calibrate,
    "figures": Figures,
    "serve": Serve,
    "bench": Bench,
}
BENCHES: dict[str, type] = {"sim": BenchSim, "model": BenchModel, "app": BenchApp, "load": BenchLoad}

# The range of every numeric option, wherever it appears: (smallest, largest), None for no bound.
_LIMITS: dict[str, tuple[float | None, float | None]] = {
    "num_samples": (1, None),
    "workers": (1, None),
    "seed": (0, None),  # numpy's generators take no negative seed
    "epochs": (1, None),
    "batch_size": (2, None),  # the MMD and batch statistics need two samples
    "z_b_dim": (1, 8),
    "alpha": (0, None),
    "beta": (0, None),
    "gamma": (0, None),
    "prior_samples": (0, None),
    "zero_samples": (0, None),
    "sampled_samples": (0, None),
    "sampled_repeat": (1, None),
    "ensemble": (2, None),  # the replay and at least one perturbed copy: a spread needs two
    "calls": (1, None),
    "moves": (1, None),
    "clients": (1, None),
    "samples": (1, None),
    "repeats": (1, None),
    "port": (0, 65535),  # 0: any free port
}
_LIMITS_OF: dict[type, dict[str, tuple[float | None, float | None]]] = {
    Calibrate: {
        "prior_samples": (1, None)
    },  # evaluate's 0 skips its consistency check; calibrate needs gaits
}
_POSITIVE = ("cycle_epochs", "lr", "seconds")


# What each command writes: "dir" (a directory it fills) or "file"; a "file" that already exists
# where the option is also an input (--replays, --gaits: reused when present) is not written.
_OUTPUTS: dict[type, dict[str, str]] = {
    Generate: {"out": "file"},
    Train: {"out": "dir"},
    Evaluate: {"report": "file", "replays": "file"},
    Calibrate: {"out": "dir", "gaits": "file"},
    Figures: {"out": "dir"},
}
_REUSED_WHEN_PRESENT = {"replays", "gaits"}


def output_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` (a "dir" to fill or a "file" to write) cannot be written, or None.

    Checked before a command starts, without leaving anything behind (a probe file in the nearest
    existing directory, removed at once), so that an evaluation or a calibration does not run for
    most of an hour only to fail when it saves.
    """
    path = Path(path)
    if kind == "dir" and path.exists() and not path.is_dir():
        return f"{path}: exists and is not a directory"
    if kind == "file" and path.is_dir():
        return f"{path}: is a directory, not a file"
    existing = path if kind == "dir" else path.parent
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f"{path}: {existing} is not a directory"
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".snakeloco-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"{path}: cannot write in {existing} ({exc.strerror})"
    return None


def argument_problem(cmd: object) -> str | None:
    """What is wrong with a parsed command's numeric options or output paths (naming the flag), or None.

    Checked before any work starts, so a value out of range ends the command with one line
    instead of a traceback from deep inside (a negative seed in numpy, a zero ensemble in a
    division, a port number in bind), and an unwritable output before the work it would hold.
    """
    limits = _LIMITS | _LIMITS_OF.get(type(cmd), {})
    for field in dataclasses.fields(cmd):
        value = getattr(cmd, field.name)
        if value is None or isinstance(value, bool) or not isinstance(value, int | float):
            continue
        flag = "--" + field.name.replace("_", "-")
        if not math.isfinite(value):
            return f"{flag} must be a finite number, got {value}"
        if field.name in _POSITIVE and value <= 0:
            return f"{flag} must be positive, got {value}"
        lo, hi = limits.get(field.name, (None, None))
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            span = f"at least {lo:g}" if hi is None else f"between {lo:g} and {hi:g}"
            return f"{flag} must be {span}, got {value:g}"
    for name, kind in _OUTPUTS.get(type(cmd), {}).items():
        path = getattr(cmd, name)
        if path is None or (name in _REUSED_WHEN_PRESENT and Path(path).is_file()):
            continue
        problem = output_problem(path, kind)
        if problem is not None:
            return f"--{name.replace('_', '-')} {problem}"
    return None


def run_generate(cmd: Generate) -> Path:
    """Generate the dataset with a progress bar; returns the written path."""
    from tqdm import tqdm

    from sim import GenerateConfig, generate_dataset

    cfg = GenerateConfig(num_samples=cmd.num_samples, seed=cmd.seed)
    t0 = time.perf_counter()
    with tqdm(total=cfg.num_samples, unit="sample", desc="generate") as bar:
        path = generate_dataset(cfg, cmd.out, workers=cmd.workers, progress=bar.update)
    size = path.stat().st_size / 2**20
    print(f"wrote {path} ({cfg.num_samples} samples, {size:.1f} MiB) in {time.perf_counter() - t0:.1f} s")
    return path


def run_train(cmd: Train):
    """Train with the paper's schedule (model/train.py documents it)."""

    from model import ModelConfig, TrainConfig, train

    # The bounds of these settings are checked before (``argument_problem``), naming the flag.
    train_fields = ("epochs", "device", "seed", "batch_size", "cycle_epochs")
    model_fields = ("alpha", "beta", "gamma", "body_sees_stats", "z_b_dim")
    cfg = TrainConfig(**{k: getattr(cmd, k) for k in train_fields})
    model_cfg = ModelConfig(**{k: getattr(cmd, k) for k in model_fields})
    return train(cmd.data, cmd.out, cfg, model_cfg)


def run_evaluate(cmd: Evaluate) -> dict:
    """Evaluate and print the report."""
    from tqdm import tqdm

    from model.evaluate import evaluate, format_report

    bar = None

    def progress(k: int) -> None:  # the bar appears with the first replays, after the inputs are checked
        nonlocal bar
        if bar is None:
            bar = tqdm(total=2 * cmd.prior_samples, unit="gait", desc="consistency")
        bar.update(k)

    try:
        report = evaluate(
            cmd.checkpoint,
            cmd.data,
            cmd.prior_samples,
            cmd.ensemble,
            cmd.seed,
            cmd.workers,
            progress=progress,
            replays=cmd.replays,
        )
    finally:
        if bar is not None:
            bar.close()
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
    """Replay prior gaits with a progress bar (none when --gaits reuses them), then fine-tune and save."""
    from tqdm import tqdm

    from model.calibrate import calibrate, calibration_gait_count

    # The counts' bounds are checked before (``argument_problem``), naming the flag.
    total = calibration_gait_count(cmd.prior_samples, cmd.zero_samples, cmd.sampled_samples)
    bar = None

    def progress(k: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, unit="gait", desc="replay prior gaits")
        bar.update(k)
        if bar.n >= bar.total:
            bar.close()  # before the fine-tuning's log lines

    try:
        return calibrate(
            cmd.checkpoint,
            cmd.data,
            cmd.out,
            n=cmd.prior_samples,
            seed=cmd.seed,
            epochs=cmd.epochs,
            lr=cmd.lr,
            workers=cmd.workers,
            progress=progress,
            gaits_path=cmd.gaits,
            loss=cmd.head_loss,
            zero_samples=cmd.zero_samples,
            sampled_samples=cmd.sampled_samples,
            path_fit=cmd.path_fit,
            sampled_repeat=cmd.sampled_repeat,
        )
    finally:
        if bar is not None:
            bar.close()


def run_figures(cmd: Figures) -> list[Path]:
    """Write the figures and list them."""
    from model.figures import figures

    paths = figures(cmd.checkpoint, cmd.data, cmd.out, cmd.seed, cmd.report)
    for p in paths:
        print(p)
    return paths


def run_bench_model(cmd: BenchModel) -> dict:
    """Run and print the decode benchmark."""
    from model.bench import bench_model

    r = bench_model(cmd.checkpoint, n=cmd.calls)
    print(
        f"decode one z_B: p50 {r['decode_p50_ms']:.2f} ms, p95 {r['decode_p95_ms']:.2f} ms; "
        f"batch of {r['batch']}: {r['batch_decodes_per_s']:.0f} decodes/s"
    )
    if cmd.json:
        print(jsonlib.dumps(r))
    return r


def run_bench_sim(cmd: BenchSim) -> dict:
    """Run and print the simulator benchmark."""
    from sim.bench import bench_sim

    result = bench_sim(samples=cmd.samples, workers=cmd.workers, repeats=cmd.repeats)
    print(
        f"threads {result['workers']}, {result['samples']} records of {result['steps_per_sample']} steps\n"
        f"raw mujoco.rollout   {result['raw_steps_per_s']:12.0f} steps/s\n"
        f"generator end-to-end {result['generator_steps_per_s']:12.0f} steps/s"
        f"   ratio {result['ratio']:.3f} (generator / raw, goal >= 0.9)\n"
        f"bare mj_step loop    {result['bare_ms']:9.1f} ms\n"
        f"sim.replay           {result['replay_ms']:9.1f} ms"
        f"   replay_ratio {result['replay_ratio']:.3f} (replay time / bare time)"
    )
    if cmd.json:
        print(jsonlib.dumps(result))
    return result


def run_bench_load(cmd: BenchLoad) -> dict:
    """Run and print the multi-client load benchmark."""
    from app.load import bench_load

    r = bench_load(
        cmd.clients,
        cmd.seconds,
        cmd.checkpoint,
        cmd.ensemble,
        cmd.seed,
        render=cmd.render,
        pin_cpus=cmd.pin_cpus,
    )
    where = (
        f"server on CPUs {r['server_cpus']}, browsers on CPUs {r['browser_cpus']}"
        if r["server_cpus"]
        else "server and browsers share the CPUs"
    )
    print(
        f"{where}\n"
        f"1 client: decoded view p50 {r['single_decoded_p50_ms']:.1f} ms, p95 {r['single_decoded_p95_ms']:.1f} ms\n"
        f"{r['clients']} clients: decoded view p95 per client "
        + ", ".join(f"{v:.1f}" for v in r["multi_decoded_p95_ms"])
        + f" ms; worst / single p95 = {r['p95_ratio']:.2f} (goal <= 2)\n"
        "p95 breakdown (ms), 1 client -> each of "
        + f"{r['clients']}: "
        + "; ".join(
            f"{k} {r['single_breakdown_p95_ms'][k]:.1f} -> "
            + "/".join(f"{v:.1f}" for v in r["multi_breakdown_p95_ms"][k])
            for k in ("wait", "decode", "draw")
        )
        + "\n"
        f"updates per client {r['updates']}; server exceptions {r['server_exceptions']}, "
        f"page errors {r['page_errors']}, stale draws {r['stale_draws']}\n"
        f"server RSS {r['rss_start_mb']:.0f} MB at start, {r['rss_multi_start_mb']:.0f} -> "
        f"{r['rss_multi_end_mb']:.0f} MB over the {r['clients']}-client phase "
        f"(slope {r['rss_slope_mb_per_min']:+.1f} MB/min; second half {r['rss_late_start_mb']:.0f} -> "
        f"{r['rss_late_end_mb']:.0f} MB, slope {r['rss_late_slope_mb_per_min']:+.1f} MB/min), "
        f"peak {r['rss_peak_mb']:.0f} MB; tabs idle before / after the drags "
        f"{r['rss_idle_before_mb']:.0f} / {r['rss_idle_after_mb']:.0f} MB"
    )
    for details in r["stale_details"]:
        print("stale:", "; ".join(details))
    for message in r["exception_messages"]:
        print("exception:", message)
    if cmd.json:
        print(jsonlib.dumps(r))
    return r


def run_bench_app(cmd: BenchApp) -> dict:
    """Run and print the single-client latency benchmark."""
    from app.bench import bench_app

    r = bench_app(cmd.checkpoint, cmd.moves)
    print(
        f"{r['moves']} slider moves: decoded view p50 {r['decoded_p50_ms']:.1f} ms, p95 {r['decoded_p95_ms']:.1f} ms; "
        f"replay ready p50 {r['replay_ready_p50_ms']:.0f} ms, p95 {r['replay_ready_p95_ms']:.0f} ms; "
        f"replay_ratio {r['replay_ratio']:.3f} (replay / bare mj_step), "
        f"ensemble_ratio {r['ensemble_ratio']:.3f} (ensemble / bare mujoco.rollout)"
    )
    if cmd.json:
        print(jsonlib.dumps(r))
    return r


def main(args: list[str] | None = None) -> None:
    """Entry point of the ``snakeloco`` console script.

    A bad input file (dataset, checkpoint, evaluate report), a path that cannot be read or written,
    a missing CUDA device, diverged training or a dataset sample that breaks the simulation in every
    phase draw ends the command with a one-line message naming the problem and exit status 2, not
    a traceback.
    """
    from app.load import MissingBrowserError
    from model.checkpoint import CheckpointError
    from model.figures import ReportError
    from model.train import TrainingError
    from sim import DatasetError, SimulationError

    args = list(sys.argv[1:] if args is None else args)
    if args[:1] == ["bench"]:
        cmd = tyro.extras.subcommand_cli_from_dict(
            BENCHES, args=args[1:], prog="snakeloco bench", description=Bench.__doc__
        )
    else:
        cmd = tyro.extras.subcommand_cli_from_dict(COMMANDS, args=args, prog="snakeloco")
    runners = {
        Generate: run_generate,
        Train: run_train,
        Serve: run_serve,
        Evaluate: run_evaluate,
        Calibrate: run_calibrate,
        Figures: run_figures,
        BenchSim: run_bench_sim,
        BenchModel: run_bench_model,
        BenchApp: run_bench_app,
        BenchLoad: run_bench_load,
    }
    problem = argument_problem(cmd)
    if problem is not None:
        print(f"snakeloco: error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    try:
        runners[type(cmd)](cmd)
    except (
        CheckpointError,
        DatasetError,
        ReportError,
        TrainingError,
        SimulationError,
        MissingBrowserError,
    ) as exc:
        print(f"snakeloco: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:  # e.g. --out under a read-only or missing directory, a disk that is full
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"snakeloco: error: {where}{exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(2) from None


def run_serve(cmd: Serve) -> None:
    """Serve the designer until Ctrl-C / SIGTERM."""
    from app.server import serve

    serve(cmd.host, cmd.port, cmd.checkpoint, cmd.ensemble)


if __name__ == "__main__":
    main()
