"""``snakeloco bench sim``: the generator and ``replay`` against bare MuJoCo, measured side by side."""

from __future__ import annotations

import time

import mujoco
import numpy as np

from snakeloco.sim import BODY_DOWNSAMPLE, GenerateConfig, expand_commands, joint_shape, load_model
from snakeloco.sim.data.chunks import draw_sample, simulate_samples
from snakeloco.sim.physics.simulator import Simulator, replay


def best_time(fn, repeats: int) -> float:
    """The shortest of ``repeats`` timed calls of ``fn`` (s)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_sim(samples: int | None = None, workers: int | None = None, repeats: int = 3) -> dict:
    """Measure simulation throughput and overheads; returns the figures as a dict.

    - ``raw_steps_per_s``: ``mujoco.rollout`` on a fixed, precomputed control array.
    - ``generator_steps_per_s``: the dataset generator end to end (phase draw, multisine, command
      expansion, rollout, failure checks, measurement, joint shape) on the same number of samples,
      the same model and thread count. ``ratio`` = generator / raw (1.0 = no overhead).
    - ``replay_ms`` vs ``bare_ms``: ``sim.replay`` of one record against a bare single-thread
      ``mj_step`` loop over the same servo targets; ``replay_ratio`` = replay time / bare time
      (1.0 = no overhead).

    Each figure is the best of ``repeats`` runs, raw and generator runs interleaved.
    """
    simulator = Simulator(workers)
    workers = simulator.workers
    samples = samples or 4 * workers
    cfg = GenerateConfig(num_samples=samples, seed=12345)
    indices = np.arange(samples)
    # The generator's own first draws, so both runs simulate the very same trajectories.
    commands = np.stack([draw_sample(cfg, int(i), 0)[1] for i in indices]).astype(np.float64)
    ctrl = expand_commands(commands, simulator.substeps, cfg.sim)  # (B, n_steps, n_joints), fixed
    steps = samples * simulator.n_steps

    def generator() -> None:
        chunk = simulate_samples(cfg, simulator, indices)
        chunk.body[:, ::BODY_DOWNSAMPLE].copy()
        joint_shape(chunk.joint_angles, cfg.excitation)

    raw_t, gen_t = float("inf"), float("inf")
    for _ in range(repeats):
        raw_t = min(raw_t, best_time(lambda: simulator.rollout(ctrl), 1))
        gen_t = min(gen_t, best_time(generator, 1))

    model = load_model()
    data = mujoco.MjData(model)
    one = ctrl[0]

    def bare() -> None:
        mujoco.mj_resetData(model, data)
        for u in one:
            data.ctrl[:] = u
            mujoco.mj_step(model, data)

    replay(commands[0])  # build the cached single-thread simulator outside the timing
    bare_t, replay_t = float("inf"), float("inf")
    for _ in range(repeats):
        bare_t = min(bare_t, best_time(bare, 1))
        replay_t = min(replay_t, best_time(lambda: replay(commands[0]), 1))
    return {
        "workers": workers,
        "samples": samples,
        "steps_per_sample": simulator.n_steps,
        "raw_steps_per_s": steps / raw_t,
        "generator_steps_per_s": steps / gen_t,
        "ratio": raw_t / gen_t,
        "generator_samples_per_s": samples / gen_t,
        "bare_ms": 1e3 * bare_t,
        "replay_ms": 1e3 * replay_t,
        "replay_ratio": replay_t / bare_t,
    }
