"""Open-loop simulation of joint commands in MuJoCo: batched rollouts and measurement.

Commands become servo targets by the command rule (``sim.physics.command_rule``); the measured body states
are those of ``sim.physics.body``. A rollout that diverges, is reset by MuJoCo or throws the snake counts
as broken (``CommandRule`` holds the limits) and is named, never returned as data.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from snakeloco.sim.gaits.excitation import ExcitationConfig
from snakeloco.sim.physics import ground_contact
from snakeloco.sim.physics.body import SensorColumns, body_states
from snakeloco.sim.physics.command_rule import CommandRule, expand_commands, why_broken
from snakeloco.sim.physics.results import (
    BatchResult,
    Dropped,
    Paused,
    ReplayResult,
    SimulationError,
)
from snakeloco.sim.physics.scheduler import FairRunner
from snakeloco.sim.physics.stream import STATE_SPEC as _STATE_SPEC
from snakeloco.sim.physics.stream import stream
from snakeloco.sim.physics.threads import FifoLock, RolloutThreads, resolve_workers
from snakeloco.sim.robot.description import BODY_SITE, Robot, resolve_robot
from snakeloco.sim.world.description import DEFAULT_WORLD, World

VARIATION_MODELS_KEPT = 64
"""Compiled variation models a simulator keeps (the default set is 12; a fit's candidates come and go)."""


class Simulator:
    """Batched open-loop rollouts of the snake on ``workers`` threads (``RolloutThreads``: MuJoCo's
    rollout with the GIL released), on ``world`` (default: the flat plane; off the plane the ground
    contacts keep the links' anisotropic friction, ``sim.physics.ground_contact``).

    ``nice`` > 0 runs the rollouts on threads at that much lower CPU priority (Linux), leaving the
    calling thread's own priority alone: an interactive server keeps physics out of the way of
    slider decoding. Those threads hold the GIL only to enter and leave a rollout (the wrapper's
    argument checks), never during the physics. One Simulator is not for concurrent use from
    several Python threads; make one per thread.
    """

    def __init__(
        self,
        workers: int | None = 1,
        excitation: ExcitationConfig | None = None,
        config: CommandRule | None = None,
        nice: int = 0,
        max_batch: int | None = None,
        robot: Robot | None = None,
        world: World | None = None,
    ) -> None:
        self.excitation = excitation or ExcitationConfig()
        self.config = config or CommandRule()
        self.robot = resolve_robot(robot)
        self.world = world or DEFAULT_WORLD
        self.model = self.compile(self.robot)
        self._variation_models: OrderedDict[Robot, mujoco.MjModel] = OrderedDict()
        self.workers = resolve_workers(workers)
        # Records per rollout call (each keeps every step, ~16 MB): 2 per thread keeps both busy.
        self.max_batch = max(1, int(max_batch or 2 * self.workers))
        self._data = mujoco.MjData(self.model)
        self._pool = None  # one worker at the caller's priority: roll out on the calling thread
        if self.workers > 1 or nice > 0:
            self._pool = RolloutThreads(self.workers, int(nice), name="physics")
        self._closed = False
        self._lock = FifoLock()  # callers sharing one simulator roll out in the order they came
        dt = self.model.opt.timestep
        self.substeps = round(1.0 / (self.excitation.sample_rate * dt))
        if abs(self.substeps * dt * self.excitation.sample_rate - 1.0) > 1e-9:
            raise ValueError(f"timestep {dt} s does not divide the command period")
        self.n_steps = (self.config.lead_in + self.excitation.n_samples) * self.substeps
        self.delay = self.latency_steps(self.robot)
        data = mujoco.MjData(self.model)  # reset state: straight snake resting on the floor
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, _STATE_SPEC))
        mujoco.mj_getState(self.model, data, self.initial_state, _STATE_SPEC)
        self.columns = SensorColumns.of(self.model, self.robot.n_joints)
        assert self.model.site(BODY_SITE).id >= 0

    stream = stream
    """``sim.physics.stream.stream``: one record replayed in chunks, each yielded as it is done."""

    @property
    def closed(self) -> bool:
        """Whether ``close`` was called (no more rollouts)."""
        return self._closed

    def rollout(
        self,
        ctrl: np.ndarray,
        wanted: Callable[[], bool] | None = None,
        start: Paused | None = None,
        warm_out: np.ndarray | None = None,
        runner: FairRunner | None = None,
        models: list[mujoco.MjModel] | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Raw rollouts from the resting state (or from ``start``): ctrl (B, n_steps, n_joints) -> (state,
        sensordata).

        state is (B, n_steps, nstate) after each step; sensordata (B, n_steps, nsensordata) is
        measured at the start of each step (about 16 MB per record: callers keep only samples).
        ``wanted``: asked when the batch gets its turn; False: nothing is rolled out (None).
        ``warm_out`` (B, nv): filled with each row's warm start after its last step. ``runner``: run
        the rows on a shared pool's turns (``FairPhysics.runner``; None where one was dropped).
        ``models``: one model per row (variations of this robot: one size signature), else this one.
        """
        batch = ctrl.shape[0]
        if start is None:
            initial = np.broadcast_to(self.initial_state, (batch, self.initial_state.size))
            warm = np.zeros((batch, self.model.nv))  # as mj_resetData: no thread's history in it
        else:
            initial, warm = start.state, start.warm
        m, n_steps = self.model, ctrl.shape[1]
        state = np.empty((batch, n_steps, mujoco.mj_stateSize(m, _STATE_SPEC)))
        sens = np.empty((batch, n_steps, m.nsensordata))
        if runner is not None:
            if self._closed:
                raise SimulationError("the simulator was closed (the server is stopping)")
            rows = runner.rollout(models or m, initial, ctrl, warm, state, sens, warm_out=warm_out)
            return None if any(f.cancelled() for f in rows) else (state, sens)
        with self._lock:
            if self._closed:
                raise SimulationError("the simulator was closed (the server is stopping)")
            if wanted is not None and not wanted():
                return None  # left while it waited for the callers before it
            if self._pool is None and warm_out is None:
                ground_contact.rollout(
                    models or m,
                    self._data,
                    initial,
                    ctrl,
                    initial_warmstart=warm,
                    state=state,
                    sensordata=sens,
                )
            elif self._pool is None:  # one row at a time, each one's final warm start kept
                for i in range(batch):
                    ground_contact.rollout(
                        m if models is None else models[i],
                        self._data,
                        initial[i : i + 1],
                        ctrl[i : i + 1],
                        initial_warmstart=warm[i : i + 1],
                        state=state[i : i + 1],
                        sensordata=sens[i : i + 1],
                    )
                    warm_out[i] = self._data.qacc_warmstart
            else:
                self._pool.rollout(models or m, initial, ctrl, warm, state, sens, warm_out=warm_out)
        return state, sens

    def poses(self, sens: np.ndarray) -> np.ndarray:
        """The body frame's world pose (..., 3): x, y (m) and yaw (rad), from sensordata rows (..., n)."""
        if sens.ndim == 1:  # one row, each control period of a closed loop: plain floats are faster
            (px, py, _), (w, x, y, z) = sens[self.columns.pos].tolist(), sens[self.columns.quat].tolist()
            return np.array([px, py, math.atan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)])
        pos, q = sens[..., self.columns.pos], sens[..., self.columns.quat]
        w, x, y, z = np.moveaxis(q, -1, 0)  # yaw of R(q) is scale-free: no normalising needed
        yaw = np.arctan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)
        return np.stack([pos[..., 0], pos[..., 1], yaw], axis=-1)

    def healthy(self, state: np.ndarray, sens: np.ndarray, first: int) -> bool:
        """A cheap check that steps ``first``.. (``state``, ``sens`` rows) are sound: where it says
        False, ``diagnose_steps`` names the problem (a closed loop checks every period)."""
        dt = self.model.opt.timestep
        return bool(
            np.isfinite(state[-1]).all()
            and abs(state[-1, 0] - (first + len(state)) * dt) <= 0.5 * dt
            and sens[:, self.columns.com[2]].max() <= self.config.max_com_height
            and (sens[:, self.columns.vel] ** 2).sum(axis=1).max() <= self.config.max_com_speed**2
        )

    def initial_sensors(self) -> np.ndarray:
        """Sensordata (nsensordata,) at the resting start state (what a loop reads before its first step)."""
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        return data.sensordata.copy()

    @property
    def pool(self):
        """The rollout threads (``RolloutThreads``), or None where rollouts run on the caller's thread."""
        return self._pool

    def compile(self, robot: Robot) -> mujoco.MjModel:
        """``robot`` on this simulator's world (the default world: the robot's own model, bit for bit)."""
        return robot.compile() if self.world == DEFAULT_WORLD else self.world.compile(robot)

    def latency_steps(self, robot: Robot) -> int:
        """A robot's command latency in whole physics steps of this simulator."""
        return round(robot.latency / self.model.opt.timestep)

    def variation_model(self, robot: Robot) -> mujoco.MjModel:
        """The compiled model of ``robot``, a variation of this simulator's robot (kept: a variation
        set is a few models used again and again); ValueError where it changes more than physics."""
        if robot == self.robot:
            return self.model
        model = self._variation_models.get(robot)
        if model is None:
            fixed = ("n_joints", "link_length", "link_radius", "joint_pattern", "timestep")
            changed = [f for f in fixed if getattr(robot, f) != getattr(self.robot, f)]
            if changed:
                raise ValueError(f"a variation changes physics, not {', '.join(changed)}")
            model = self._variation_models[robot] = self.compile(robot)
            while len(self._variation_models) > VARIATION_MODELS_KEPT:  # a fit's candidates: each new
                self._variation_models.popitem(last=False)
        self._variation_models.move_to_end(robot)
        return model

    def close(self) -> None:
        """Stop the rollout threads, if there are any (then the Simulator cannot roll out)."""
        with self._lock:
            self._closed = True
            if self._pool is not None:
                self._pool.close()

    def simulate(
        self,
        commands: np.ndarray,
        wanted: Callable[[], bool] | None = None,
        samples: int | None = None,
        resume: Paused | None = None,
        runner: FairRunner | None = None,
        robots: Sequence[Robot] | None = None,
    ) -> BatchResult | None:
        """Simulate a batch of records under the command rule and measure them.

        Args:
            commands: (B, T, n_joints) rad.
            samples: simulate only the lead-in and the record's first this many samples (None: all
                T); the results are then (B, samples, ...), the prefixes of the whole records',
                and ``paused`` says where the rollouts stopped.
            resume: carry on from an earlier call's ``paused`` (same commands, same rows) to
                ``samples``: the results are the whole series from the record's start, bit-identical
                to one uninterrupted call's (tested); only the steps after the pause are simulated.
            wanted: asked each time a part of the batch gets its turn (callers sharing the
                simulator roll out first come, first served); False: the rest is not simulated (None).
            runner: on a shared pool's turns (``rollout``); None where a row was dropped.
            robots: one description per record, each a variation of this simulator's robot (the
                same geometry: ``variation_model``), e.g. one gait on a set of variations in one
                batch; None: this robot.

        Returns:
            BatchResult with (B, T, n_joints) joint angles and (B, T, 6) body states; a failed row's
            ``failures`` entry names the problem (its measurements are then meaningless).
            Records are independent (same start, zero warm start): rolled out ``max_batch`` at a
            time, the results are one call's.
        """
        commands = np.asarray(commands, dtype=np.float64)
        expected = (self.excitation.n_samples, self.robot.n_joints)
        if commands.ndim != 3 or commands.shape[1:] != expected:
            raise ValueError(f"expected (B, {expected[0]}, {expected[1]}) commands, got {commands.shape}")
        samples = expected[0] if samples is None else int(samples)
        first = 0 if resume is None else resume.samples
        if not first < samples <= expected[0]:
            raise ValueError(f"samples must be {first + 1}-{expected[0]}, got {samples}")
        if resume is not None and len(resume.state) != len(commands):
            raise ValueError(f"resuming {len(resume.state)} paused rollouts with {len(commands)} records")
        if robots is not None and len(robots) != len(commands):
            raise ValueError(f"{len(robots)} robots for {len(commands)} records")
        parts = []
        for i in range(0, len(commands), self.max_batch):
            rows = slice(i, i + self.max_batch)
            start = None if resume is None else resume.rows(rows)
            part_robots = None if robots is None else robots[rows]
            parts.append(self._simulate(commands[rows], wanted, samples, start, runner, part_robots))
            if parts[-1] is None:
                return None
        if len(parts) == 1:
            return parts[0]
        paused = None
        if samples < expected[0]:
            paused = Paused(
                samples,
                np.concatenate([r.paused.state for r in parts]),
                np.concatenate([r.paused.warm for r in parts]),
                tuple(np.concatenate(a) for a in zip(*(r.paused.measured for r in parts), strict=True)),
                [f for r in parts for f in r.paused.failures],
            )
        return BatchResult(
            joint_angles=np.concatenate([r.joint_angles for r in parts]),
            body=np.concatenate([r.body for r in parts]),
            failures=[f for r in parts for f in r.failures],
            qpos=np.concatenate([r.qpos for r in parts]),
            paused=paused,
        )

    def _simulate(
        self,
        commands: np.ndarray,
        wanted: Callable[[], bool] | None,
        samples: int,
        start: Paused | None,
        runner: FairRunner | None = None,
        robots: Sequence[Robot] | None = None,
    ) -> BatchResult | None:
        first = 0 if start is None else start.samples
        # Steps [begin, end): a resumed rollout starts where the paused one stopped.
        begin = 0 if start is None else (self.config.lead_in + first) * self.substeps
        end = (self.config.lead_in + samples) * self.substeps
        models = None
        if robots is None:
            ctrl = expand_commands(commands, self.substeps, self.config, (begin, end), self.delay)
        else:
            models = [self.variation_model(r) for r in robots]
            ctrl = np.concatenate(
                [
                    expand_commands(c[None], self.substeps, self.config, (begin, end), self.latency_steps(r))
                    for c, r in zip(commands, robots, strict=True)
                ]
            )
        pause = samples < self.excitation.n_samples
        warm_out = np.empty((len(commands), self.model.nv)) if pause else None
        rolled = self.rollout(ctrl, wanted, start, warm_out, runner, models)
        if rolled is None:
            return None
        state, sens = rolled
        dt = self.model.opt.timestep
        failures = [self.diagnose_steps(st, se, dt, first=begin) for st, se in zip(state, sens, strict=True)]
        # Sample n is measured at the start of step record[n]; rows here are steps from `begin`.
        record = self.config.lead_in * self.substeps + self.substeps * np.arange(first, samples) - begin
        sampled = sens[:, record]  # (B, T, nsensordata), measured at the start of step `record`
        # The state after step record-1: the same instant (the paused state where record is 0).
        before = state[:, np.maximum(record - 1, 0)]
        if start is not None:
            before[:, record == 0] = start.state[:, None]
        qpos = before[..., 1 : 1 + self.model.nq]
        joint_angles = sampled[..., self.columns.q]
        pos = sampled[..., self.columns.pos]
        quat = sampled[..., self.columns.quat]
        quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True).clip(min=1e-12)
        if start is not None:  # the whole series from the record's start: its frame, its unwrapping
            joint_angles, pos, quat, qpos = (
                np.concatenate([a, b], axis=1)
                for a, b in zip(start.measured, (joint_angles, pos, quat, qpos), strict=True)
            )
            failures = [f or g for f, g in zip(start.failures, failures, strict=True)]
        with np.errstate(invalid="ignore"):
            body = body_states(pos, quat)
        paused = None
        if pause:
            paused = Paused(samples, state[:, -1].copy(), warm_out, (joint_angles, pos, quat, qpos), failures)
        return BatchResult(joint_angles=joint_angles, body=body, failures=failures, qpos=qpos, paused=paused)

    def diagnose_steps(self, state: np.ndarray, sens: np.ndarray, dt: float, first: int = 0) -> str | None:
        """Why a rollout's steps (``state``/``sens`` rows are steps ``first``, ``first`` + 1, ...)
        broke the simulation, or None. A stream checks each chunk's new steps once (``first``)."""
        return why_broken(
            self.config,
            state,
            sens[:, self.columns.com[2]],
            np.linalg.norm(sens[:, self.columns.vel], axis=1),
            dt,
            first,
            t0=self.config.lead_in / self.excitation.sample_rate,
        )

    def replay(self, commands: np.ndarray, runner: FairRunner | None = None) -> ReplayResult:
        """Simulate one record exactly as data generation does (on ``runner``'s turns, as
        ``simulate``); raise SimulationError if it breaks."""
        commands = np.asarray(commands, dtype=np.float64)
        result = self.simulate(commands[None], runner=runner)
        if result is None:
            raise Dropped("the replay was dropped: its caller no longer wants it")
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
    """Replay one record of joint commands (T, n_joints) rad through the snake (``Simulator.replay``).
    Raises ValueError (commands of the wrong shape or not finite) or SimulationError (the simulation
    diverged or threw the snake; the message says how and when)."""
    global _default_simulator
    commands = np.asarray(commands, dtype=np.float64)
    if not np.isfinite(commands).all():
        raise ValueError("commands contain NaN or Inf")
    with _default_lock:
        if _default_simulator is None:
            _default_simulator = Simulator(workers=1)
        return _default_simulator.replay(commands)
