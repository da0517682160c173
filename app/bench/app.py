"""``snakeloco bench app``: latency through a real running designer server, against bare MuJoCo."""

from __future__ import annotations

import time

import mujoco
import numpy as np

from snakeloco.app.bench.users.headless import HeadlessClient
from snakeloco.app.server.lifecycle import DesignerServer, freeze_started, tune_process
from snakeloco.sim import expand_commands, load_model
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE, perturbed_commands


def bench_app(checkpoint=None, moves: int = 20, ensemble: int = ENSEMBLE_SIZE, seed: int = 0) -> dict:
    """Move a slider ``moves`` times (waiting for each gait to finish) and time every stage.

    Reports slider -> decoded view and slider -> replay ready latency p50/p95 (ms, measured on the
    server from the slider value's arrival to the end of drawing), and for the same gaits the
    replay time over a bare single-thread ``mj_step`` loop of the same steps (``replay_ratio``) and
    the ensemble time over a bare ``mujoco.rollout`` of the same batch (``ensemble_ratio``).
    """
    tune_process()  # as `snakeloco serve` runs it
    # Without the Variations fan: the figures stay comparable with docs/load.md (the fan runs after
    # the ensemble at the pool's lowest turn but design; docs/variations.md has its own timing).
    server = DesignerServer(
        port=0, checkpoint=checkpoint, ensemble=ensemble, verbose=False, variations=False, closed_loop=False
    )
    freeze_started()  # as `snakeloco serve` does
    client = HeadlessClient(server.port)
    try:
        for _ in range(200):
            if server.clients:
                break
            time.sleep(0.05)
        designer = next(iter(server.clients.values()))
        designer.wait_idle(120)
        rng = np.random.default_rng(seed)
        model = load_model()
        data = mujoco.MjData(model)
        bare_sim = Simulator(workers=server.physics.threads)  # the ensemble baseline on as many threads
        rows = []
        for _ in range(moves):
            designer.sliders[int(rng.integers(len(designer.sliders)))].value = float(
                np.round(rng.uniform(-2, 2), 2)
            )
            time.sleep(0.05)
            designer.wait_idle(120)
            t = designer.timings[-1]
            if t.failed or not np.isfinite(t.ensembled):
                continue
            commands = designer.decoded.commands
            ctrl = expand_commands(commands[None], bare_sim.substeps, bare_sim.config)[0]
            t0 = time.perf_counter()
            mujoco.mj_resetData(model, data)
            for u in ctrl:
                data.ctrl[:] = u
                mujoco.mj_step(model, data)
            bare_ms = 1e3 * (time.perf_counter() - t0)
            members = perturbed_commands(commands, ensemble, seed=t.version)[1:]
            batch = expand_commands(members, bare_sim.substeps, bare_sim.config)
            t0 = time.perf_counter()
            bare_sim.rollout(batch)
            bare_ens_ms = 1e3 * (time.perf_counter() - t0)
            rows.append(
                (
                    1e3 * (t.decoded - t.submitted),
                    1e3 * (t.replayed - t.submitted),
                    t.replay_ms / bare_ms,
                    t.ensemble_ms / bare_ens_ms,
                    1e3 * (t.first_motion - t.submitted),
                )
            )
        traffic = _traffic(designer, client, rng)
    finally:
        client.close()
        server.stop()
    a = np.asarray(rows)
    return {
        "moves": len(rows),
        "decoded_p50_ms": float(np.percentile(a[:, 0], 50)),
        "decoded_p95_ms": float(np.percentile(a[:, 0], 95)),
        "replay_ready_p50_ms": float(np.percentile(a[:, 1], 50)),
        "replay_ready_p95_ms": float(np.percentile(a[:, 1], 95)),
        "first_motion_p50_ms": float(np.percentile(a[:, 4], 50)),
        "first_motion_p95_ms": float(np.percentile(a[:, 4], 95)),
        "replay_ratio": float(np.median(a[:, 2])),
        "ensemble_ratio": float(np.median(a[:, 3])),
        **traffic,
    }


def _traffic(designer, client: HeadlessClient, rng, seconds: float = 5.0, moves: int = 5) -> dict:
    """What a tab receives: bytes per second while the snake animates (the gait idle), and bytes
    per slider move (decoded view, streamed replay, ensemble, plots; animation paused)."""
    designer.wait_idle(120)
    time.sleep(0.5)
    b0, t0 = client.bytes_received, time.monotonic()
    time.sleep(seconds)
    animating = (client.bytes_received - b0) / (time.monotonic() - t0)
    designer.playback.toggle()  # pause: only the moves' own messages from here
    time.sleep(0.5)
    b0 = client.bytes_received
    for _ in range(moves):
        designer.sliders[int(rng.integers(len(designer.sliders)))].value = float(
            np.round(rng.uniform(-2, 2), 2)
        )
        time.sleep(0.05)
        designer.wait_idle(120)
    time.sleep(0.5)
    per_move = (client.bytes_received - b0) / moves
    designer.playback.toggle()
    return {"animating_bytes_per_s": float(animating), "bytes_per_move": float(per_move)}
