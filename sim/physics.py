"""Open-loop simulation of joint commands in MuJoCo: batched rollouts and measurement.

Commands become servo targets by the command rule (``sim.command_rule``); the measured body states
are those of ``sim.body``. A rollout that diverges, is reset by MuJoCo or throws the snake counts
as broken (``SimConfig`` holds the limits) and is named, never returned as data.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from snakeloco.sim.body import body_states
from snakeloco.sim.command_rule import SimConfig, SimulationError, expand_commands
from snakeloco.sim.excitation import ExcitationConfig
from snakeloco.sim.robot import BODY_SITE, N_JOINTS, load_model

_STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS


@dataclass(frozen=True)
class ReplayResult:
    """Measured response to one record of commands at the command rate."""

    commands: np.ndarray
    """(T, 8) commands actually applied (rad, float64)."""
    joint_angles: np.ndarray
    """(T, 8) measured joint angles (rad)."""
    body: np.ndarray
    """(T, 6) body states, channels as in ``BODY_CHANNELS``."""
    times: np.ndarray
    """(T,) sample times (s), 0 at the start of the record."""
    qpos: np.ndarray
    """(T, nq) MuJoCo qpos at the sample times (world frame; for drawing the robot)."""


@dataclass(frozen=True)
class StreamedReplay:
    """What a streamed replay (``Simulator.stream``) has measured so far: its first ``samples``
    record samples (arrays as ``ReplayResult``'s, that long)."""

    samples: int
    joint_angles: np.ndarray  # (samples, 8) rad
    body: np.ndarray  # (samples, 6)
    qpos: np.ndarray  # (samples, nq)
    failure: str | None  # why the simulation broke (then the stream ends), or None
    done: bool  # the whole record is in


STREAM_CHUNK = 100
"""Record samples per chunk of a streamed replay: 5 s of record, ~60 ms of physics on one core."""


@dataclass(frozen=True)
class BatchResult:
    """Measurements of a batch; rows whose ``failures`` entry is not None are invalid."""

    joint_angles: np.ndarray  # (B, T, 8) rad
    body: np.ndarray  # (B, T, 6)
    failures: list[str | None]
    qpos: np.ndarray  # (B, T, nq) at the sample times


def set_thread_nice(value: int | None) -> int | None:
    """Set the calling thread's nice value (Linux: per thread; threads and processes it starts
    inherit it); returns the previous value, or None where that is not possible."""
    if value is None or not hasattr(os, "setpriority"):
        return None
    tid = threading.get_native_id()
    try:
        previous = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, value)
    except OSError:
        return None
    return previous


def lower_thread_priority(increment: int) -> int | None:
    """Raise the calling thread's nice value by ``increment``; returns the previous value or None."""
    if not hasattr(os, "getpriority"):
        return None
    return set_thread_nice(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + increment)


class _FifoLock:
    """A lock granted in request order (``threading.Lock`` lets a thread that just released it win
    again): tabs sharing one simulator each get their turn between the others' batches."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._next_ticket = 0
        self._serving = 0

    def __enter__(self) -> None:
        with self._cond:
            ticket = self._next_ticket
            self._next_ticket += 1
            self._cond.wait_for(lambda: self._serving == ticket)

    def __exit__(self, *exc) -> None:
        with self._cond:
            self._serving += 1
            self._cond.notify_all()


def _start_pool(nthread: int, nice: int) -> mj_rollout.Rollout:
    """A rollout thread pool whose native threads run ``nice`` lower than the caller.

    Threads inherit their creator's nice value, so the pool is created on a short-lived helper
    thread that lowers its own priority first; the caller's priority is untouched (lowering needs
    no privilege, raising it back would).
    """
    if nice <= 0:
        return mj_rollout.Rollout(nthread=nthread)
    made: list = []

    def make() -> None:
        try:
            lower_thread_priority(nice)
            made.append(mj_rollout.Rollout(nthread=nthread))
        except BaseException as exc:  # handed to the caller below
            made.append(exc)

    helper = threading.Thread(target=make, name="rollout-pool-start")
    helper.start()
    helper.join()
    if isinstance(made[0], BaseException):
        raise made[0]
    return made[0]


def replay_runner(nice: int) -> mj_rollout.Rollout:
    """A one-thread rollout pool at ``nice`` below the caller, for ``Simulator.stream`` (close it
    when done): a server runs its tabs' replays below its own threads and above its ensembles."""
    return _start_pool(1, nice) if nice > 0 else mj_rollout.Rollout(nthread=1)


def resolve_workers(workers: int | None) -> int:
    """Simulation threads to use: ``workers``, or one per core of this machine where it is None."""
    return max(1, int(workers)) if workers is not None else (os.cpu_count() or 1)


class Simulator:
    """Batched open-loop rollouts of the snake on ``workers`` native threads (``mujoco.rollout``).

    ``nice`` > 0 runs the rollouts on a pool of native threads at that much lower CPU priority
    (Linux), leaving the calling Python thread's own priority alone: an interactive server keeps
    physics out of the way of slider decoding without the priority inversion of a niced thread
    that holds the GIL. One Simulator is not for concurrent use from several Python threads; make
    one per thread.
    """

    def __init__(
        self,
        workers: int | None = 1,
        excitation: ExcitationConfig | None = None,
        config: SimConfig | None = None,
        nice: int = 0,
        max_batch: int | None = None,
    ) -> None:
        self.excitation = excitation or ExcitationConfig()
        self.config = config or SimConfig()
        self.model = load_model()
        self.workers = resolve_workers(workers)
        # Records rolled out per call: a rollout keeps every physics step (~16 MB per record), so a
        # larger batch runs as consecutive calls of this many (2 per thread keeps both balanced).
        self.max_batch = max(1, int(max_batch or 2 * self.workers))
        self._datas = [mujoco.MjData(self.model) for _ in range(self.workers)]
        self._pool = None
        if self.workers > 1 or nice > 0:
            self._pool = _start_pool(self.workers, int(nice))
        self._closed = False
        self._lock = _FifoLock()  # callers sharing one simulator roll out in the order they came
        dt = self.model.opt.timestep
        self.substeps = round(1.0 / (self.excitation.sample_rate * dt))
        if abs(self.substeps * dt * self.excitation.sample_rate - 1.0) > 1e-9:
            raise ValueError(f"timestep {dt} s does not divide the command period")
        self.n_steps = (self.config.lead_in + self.excitation.n_samples) * self.substeps
        data = mujoco.MjData(self.model)  # reset state: straight snake resting on the floor
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, _STATE_SPEC))
        mujoco.mj_getState(self.model, data, self.initial_state, _STATE_SPEC)
        sensor = {self.model.sensor(i).name: i for i in range(self.model.nsensor)}
        adr = self.model.sensor_adr
        self._q_cols = np.array([adr[sensor[f"q{k + 1}"]] for k in range(N_JOINTS)])
        self._pos_cols = adr[sensor["body_pos"]] + np.arange(3)
        self._quat_cols = adr[sensor["body_quat"]] + np.arange(4)
        self._com_cols = adr[sensor["com_pos"]] + np.arange(3)
        self._vel_cols = adr[sensor["com_vel"]] + np.arange(3)
        assert self.model.site(BODY_SITE).id >= 0

    def rollout(self, ctrl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw rollouts from the resting state: ctrl (B, n_steps, 8) -> (state, sensordata).

        state is (B, n_steps, nstate) after each step; sensordata (B, n_steps, nsensordata) is
        measured at the start of each step (about 16 MB per record: callers keep only samples).
        """
        batch = ctrl.shape[0]
        initial = np.broadcast_to(self.initial_state, (batch, self.initial_state.size))
        # A zero warm start for every rollout, as mj_resetData leaves it: results then do not depend
        # on which thread ran the previous rollout.
        warm = np.zeros((batch, self.model.nv))
        with self._lock:
            if self._closed:
                raise SimulationError("the simulator was closed (the server is stopping)")
            if self._pool is None:
                return mj_rollout.rollout(self.model, self._datas[0], initial, ctrl, initial_warmstart=warm)
            return self._pool.rollout(self.model, self._datas, initial, ctrl, initial_warmstart=warm)

    def close(self) -> None:
        """Stop the native thread pool, if there is one (then the Simulator cannot roll out)."""
        with self._lock:
            self._closed = True
            if self._pool is not None:
                self._pool.close()

    def simulate(self, commands: np.ndarray) -> BatchResult:
        """Simulate a batch of records under the command rule and measure them.

        Args:
            commands: (B, T, 8) rad.

        Returns:
            BatchResult with (B, T, 8) joint angles and (B, T, 6) body states; a failed row's
            ``failures`` entry names the problem (its measurements are then meaningless).
            Records are independent (same start, zero warm start): rolled out ``max_batch`` at a
            time, the results are those of one call.
        """
        commands = np.asarray(commands, dtype=np.float64)
        expected = (self.excitation.n_samples, N_JOINTS)
        if commands.ndim != 3 or commands.shape[1:] != expected:
            raise ValueError(f"expected (B, {expected[0]}, {expected[1]}) commands, got {commands.shape}")
        parts = [
            self._simulate(commands[i : i + self.max_batch]) for i in range(0, len(commands), self.max_batch)
        ]
        if len(parts) == 1:
            return parts[0]
        return BatchResult(
            joint_angles=np.concatenate([r.joint_angles for r in parts]),
            body=np.concatenate([r.body for r in parts]),
            failures=[f for r in parts for f in r.failures],
            qpos=np.concatenate([r.qpos for r in parts]),
        )

    def _simulate(self, commands: np.ndarray) -> BatchResult:
        expected = (self.excitation.n_samples, N_JOINTS)
        ctrl = expand_commands(commands, self.substeps, self.config)
        state, sens = self.rollout(ctrl)
        failures = self._diagnose(state, sens)
        record = self.config.lead_in * self.substeps + self.substeps * np.arange(expected[0])
        sampled = sens[:, record]  # (B, T, nsensordata), measured at the start of step `record`
        qpos = state[:, record - 1, 1 : 1 + self.model.nq]  # state after step record-1: same instant
        joint_angles = sampled[..., self._q_cols]
        quat = sampled[..., self._quat_cols]
        quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True).clip(min=1e-12)
        with np.errstate(invalid="ignore"):
            body = body_states(sampled[..., self._pos_cols], quat)
        return BatchResult(joint_angles=joint_angles, body=body, failures=failures, qpos=qpos)

    def _diagnose(self, state: np.ndarray, sens: np.ndarray) -> list[str | None]:
        dt = self.model.opt.timestep
        failures: list[str | None] = []
        for b in range(state.shape[0]):
            failures.append(self._diagnose_one(state[b], sens[b], dt))
        return failures

    def _diagnose_one(self, state: np.ndarray, sens: np.ndarray, dt: float) -> str | None:
        t0 = self.config.lead_in / self.excitation.sample_rate  # record time = sim time - t0

        def at(step: int) -> str:
            t = step * dt - t0
            return f"t = {t:.2f} s" + (" (in the lead-in before the record)" if t < 0 else "")

        bad = ~np.isfinite(state).all(axis=1)
        if bad.any():
            return f"non-finite physics state at {at(int(np.argmax(bad)))}"
        time = state[:, 0]
        expected = (np.arange(1, state.shape[0] + 1)) * dt
        off = np.abs(time - expected) > 0.5 * dt
        if off.any():
            return (
                f"MuJoCo reset the unstable simulation (time stopped advancing) at {at(int(np.argmax(off)))}"
            )
        height = sens[:, self._com_cols[2]]
        if height.max() > self.config.max_com_height:
            step = int(np.argmax(height > self.config.max_com_height))
            return (
                f"snake thrown into the air: centre of mass {height.max():.2f} m high "
                f"(limit {self.config.max_com_height} m) at {at(step)}"
            )
        speed = np.linalg.norm(sens[:, self._vel_cols], axis=1)
        if speed.max() > self.config.max_com_speed:
            step = int(np.argmax(speed > self.config.max_com_speed))
            return (
                f"simulation diverged: centre of mass moving at {speed.max():.1f} m/s "
                f"(limit {self.config.max_com_speed} m/s) at {at(step)}"
            )
        return None

    def stream(
        self,
        commands: np.ndarray,
        chunk_samples: int = STREAM_CHUNK,
        runner: mj_rollout.Rollout | None = None,
    ) -> Iterator[StreamedReplay]:
        """Replay one record (T, 8) rad in chunks of ``chunk_samples`` record samples, yielding after
        each chunk everything simulated so far (the first chunk also holds the lead-in).

        The physics state and the solver's warm start carry over from chunk to chunk, so the arrays
        are bit-identical to ``replay``'s (prefixes of them until the last part). The chunks run on
        the calling thread with an ``MjData`` of the stream's own, outside the simulator's lock (the
        rollout releases the GIL): a replay never waits in line behind other callers' batches, the
        operating system shares the cores, and a simulator with ``nice`` > 0 runs its batches below
        the streams' priority (an interactive replay preempts ensembles). A caller that stops
        iterating (a superseded replay) stops the physics at that chunk boundary. A chunk that
        breaks the simulation ends the stream with its ``failure`` set. ``runner``: a one-thread
        pool (``replay_runner``) to run the chunks on at its own priority instead of the calling
        thread's (same results).
        """
        commands = np.asarray(commands, dtype=np.float64)
        n_t = self.excitation.n_samples
        if commands.shape != (n_t, N_JOINTS):
            raise ValueError(f"expected ({n_t}, {N_JOINTS}) commands, got {commands.shape}")
        if not np.isfinite(commands).all():
            raise ValueError("commands contain NaN or Inf")
        ctrl = expand_commands(commands[None], self.substeps, self.config)
        m, n_steps = self.model, ctrl.shape[1]
        state = np.empty((n_steps, mujoco.mj_stateSize(m, _STATE_SPEC)))
        sens = np.empty((n_steps, m.nsensordata))
        record = self.config.lead_in * self.substeps + self.substeps * np.arange(n_t)
        bounds = [
            *range(record[0] + chunk_samples * self.substeps, n_steps, chunk_samples * self.substeps),
            n_steps,
        ]
        initial, warm, done = self.initial_state[None], np.zeros((1, m.nv)), 0
        data = mujoco.MjData(m)
        for end in bounds:
            if self._closed:
                raise SimulationError("the simulator was closed (the server is stopping)")
            if runner is None:
                s, se = mj_rollout.rollout(m, data, initial, ctrl[:, done:end], initial_warmstart=warm)
            else:
                s, se = runner.rollout(m, [data], initial, ctrl[:, done:end], initial_warmstart=warm)
            warm = data.qacc_warmstart[None].copy()
            state[done:end], sens[done:end] = s[0], se[0]
            initial, done = s[:, -1], end
            failure = self._diagnose_one(state[:done], sens[:done], m.opt.timestep)
            n = int(np.searchsorted(record, done))  # samples whose step has been simulated
            sampled = sens[record[:n]]
            quat = sampled[:, self._quat_cols]
            quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True).clip(min=1e-12)
            with np.errstate(invalid="ignore"):
                body = body_states(sampled[None, :, self._pos_cols], quat[None])[0]
            yield StreamedReplay(
                samples=n,
                joint_angles=sampled[:, self._q_cols],
                body=body,
                qpos=state[record[:n] - 1, 1 : 1 + m.nq],
                failure=failure,
                done=done == n_steps,
            )
            if failure is not None:
                return

    def replay(self, commands: np.ndarray) -> ReplayResult:
        """Simulate one record exactly as data generation does; raise SimulationError if it breaks."""
        commands = np.asarray(commands, dtype=np.float64)
        result = self.simulate(commands[None])
        if result.failures[0] is not None:
            raise SimulationError(result.failures[0])
        return ReplayResult(
            commands=commands,
            joint_angles=result.joint_angles[0],
            body=result.body[0],
            times=self.excitation.times,
            qpos=result.qpos[0],
        )


_default_lock = threading.Lock()
_default_simulator: Simulator | None = None


def replay(commands: np.ndarray) -> ReplayResult:
    """Replay one record of joint commands (T, 8) rad through the snake; see ``Simulator.replay``.

    Raises:
        ValueError: commands of the wrong shape or not finite.
        SimulationError: the simulation diverged or threw the snake (the message says how and when).
    """
    global _default_simulator
    commands = np.asarray(commands, dtype=np.float64)
    if not np.isfinite(commands).all():
        raise ValueError("commands contain NaN or Inf")
    with _default_lock:
        if _default_simulator is None:
            _default_simulator = Simulator(workers=1)
        return _default_simulator.replay(commands)
