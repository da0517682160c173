"""A replay streamed in chunks (``Simulator.stream``): the snake moves in the designer before the
whole record is simulated, and a superseded replay stops at a chunk boundary.

``stream`` reads its simulator through its public face: model, command rule, excitation, initial
state, latency, sensor columns and ``diagnose_steps``."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import wait as wait_futures

import mujoco
import numpy as np

from snakeloco.sim.physics import ground_contact
from snakeloco.sim.physics.command_rule import expand_commands
from snakeloco.sim.physics.results import (
    STREAM_CHUNK,
    STREAM_FIRST,
    STREAM_POLL_S,
    SimulationError,
    StreamedReplay,
)
from snakeloco.sim.physics.scheduler import FairRunner
from snakeloco.sim.physics.threads import RolloutThreads

STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
"""The state a rollout records per step (``mujoco.mj_stateSize``)."""

Runner = RolloutThreads | FairRunner | Callable[[int], RolloutThreads | FairRunner | None] | None


def stream(
    sim,
    commands: np.ndarray,
    chunk_samples: int = STREAM_CHUNK,
    first_samples: int = STREAM_FIRST,
    wanted: Callable[[], bool] | None = None,
    runner: Runner = None,
) -> Iterator[StreamedReplay]:
    """Replay one record (T, n_joints) rad on ``sim`` (a ``Simulator``) in chunks of ``chunk_samples``
    record samples, yielding after each chunk everything simulated so far (the first chunk is the
    lead-in and ``first_samples``).

    The physics state and the solver's warm start carry over from chunk to chunk, so the arrays
    are bit-identical to ``replay``'s (prefixes of them until the last part). The chunks run with
    an ``MjData`` of the stream's own, outside the simulator's lock: a replay never waits behind
    other callers' batches. A caller that stops iterating (a superseded replay) stops the physics
    at that chunk boundary; a chunk that breaks the simulation ends the stream with its
    ``failure`` set. ``runner``: where the chunks run (same results anywhere): a one-thread pool
    (``RolloutThreads``), a shared pool's place (``FairPhysics.runner``), or a function of the
    chunk's index (0 first) that picks one per chunk; None: the calling thread. ``wanted``:
    polled while a runner's chunk is in flight; once False the stream ends at once (a queued
    chunk is cancelled, a running one finishes unread).
    """
    commands = np.asarray(commands, dtype=np.float64)
    n_t = sim.excitation.n_samples
    if commands.shape != (n_t, sim.robot.n_joints):
        raise ValueError(f"expected ({n_t}, {sim.robot.n_joints}) commands, got {commands.shape}")
    if not np.isfinite(commands).all():
        raise ValueError("commands contain NaN or Inf")
    m, n_steps = sim.model, sim.n_steps
    record = sim.config.lead_in * sim.substeps + sim.substeps * np.arange(n_t)
    bounds = [
        *range(record[0] + first_samples * sim.substeps, n_steps, chunk_samples * sim.substeps),
        n_steps,
    ]
    # One chunk's steps, reused: the whole record's were ~17 MB a stream, resident as they filled.
    widest = int(np.diff([0, *bounds]).max())
    state, sens = (np.empty((1, widest, w)) for w in (mujoco.mj_stateSize(m, STATE_SPEC), m.nsensordata))
    sampled, qpos = np.empty((n_t, m.nsensordata)), np.empty((n_t, m.nq))  # the record's samples
    initial, warm, done, n = sim.initial_state[None], np.zeros((1, m.nv)), 0, 0
    data = mujoco.MjData(m)
    for k, end in enumerate(bounds):
        chunk_runner = runner(k) if callable(runner) else runner
        if sim.closed:
            raise SimulationError("the simulator was closed (the server is stopping)")
        out_state, out_sens = state[:, : end - done], sens[:, : end - done]  # steps [done, end)
        ctrl = expand_commands(commands[None], sim.substeps, sim.config, (done, end), sim.delay)
        if chunk_runner is None:
            ground_contact.rollout(
                m, data, initial, ctrl, initial_warmstart=warm, state=out_state, sensordata=out_sens
            )
        else:
            (chunk,) = chunk_runner.rollout(
                m, initial, ctrl, warm, out_state, out_sens, data=data, wait=False
            )
            while wanted is not None and not chunk.done():
                if not wanted():  # queued: never runs; running: finishes unread
                    chunk.cancel()
                    return
                wait_futures([chunk], timeout=STREAM_POLL_S)  # one future: done or the poll's time
            wait_futures([chunk])
            if chunk.cancelled():
                return  # dropped unrun when its turn came: the stream was no longer wanted
            chunk.result()
        warm = data.qacc_warmstart[None].copy()
        # Only this chunk's steps are new to the checks (the same verdict as the whole prefix's).
        failure = sim.diagnose_steps(out_state[0], out_sens[0], m.opt.timestep, first=done)
        new = int(np.searchsorted(record, end))
        rows = record[n:new] - done  # sample i: sensed as step record[i] begins, qpos after the last
        sampled[n:new] = out_sens[0, rows]
        before = out_state[0, np.maximum(rows - 1, 0)]
        before[rows == 0] = initial[0]  # the step before the chunk: the previous chunk's last
        qpos[n:new] = before[:, 1 : 1 + m.nq]
        initial, done, n = out_state[:, -1].copy(), end, new
        quat = sampled[:n, sim.columns.quat]
        yield StreamedReplay(
            samples=n,
            joint_angles=sampled[:n, sim.columns.q],
            qpos=qpos[:n].copy(),
            failure=failure,
            done=done == n_steps,
            pos=sampled[:n, sim.columns.pos],
            quat=quat / np.linalg.norm(quat, axis=-1, keepdims=True).clip(min=1e-12),
        )
        if failure is not None:
            return
