"""``snakeloco``: one console script, one subcommand per job. Each parses, then calls a plain function."""

from __future__ import annotations

import json as jsonlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path

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
    """Benchmarks that print ratios measured side by side in one run: `snakeloco bench {sim} --help`."""


COMMANDS: dict[str, type] = {"generate": Generate, "bench": Bench}
BENCHES: dict[str, type] = {"sim": BenchSim}


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


def main(args: list[str] | None = None) -> None:
    """Entry point of the ``snakeloco`` console script."""
    args = list(sys.argv[1:] if args is None else args)
    if args[:1] == ["bench"]:
        cmd = tyro.extras.subcommand_cli_from_dict(
            BENCHES, args=args[1:], prog="snakeloco bench", description=Bench.__doc__
        )
    else:
        cmd = tyro.extras.subcommand_cli_from_dict(COMMANDS, args=args, prog="snakeloco")
    if isinstance(cmd, Generate):
        run_generate(cmd)
    elif isinstance(cmd, BenchSim):
        run_bench_sim(cmd)


if __name__ == "__main__":
    main()
