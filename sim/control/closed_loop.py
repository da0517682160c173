"""Closed-loop replays: gaits played by ``PathFollower`` on the simulator, batched over varied robots.

MuJoCo's rollout runs one control period (``Simulator.substeps`` physics steps) for every active row at
a time, on the simulator's threads; between periods each row's follower is given its pose estimate
(``sim.robot.sensing``) and returns its next servo targets, ramped linearly over the period (the command
rule). A row's command latency delays its targets by whole physics steps, as in open loop. With no
steering the rows are bit-identical to ``Simulator.simulate``'s open-loop rollouts (tested).

The pose a follower is given at control step n is the body frame's, measured at the start of the last
physics step before it (2.5 ms before t_n; the first from the resting state): what a plain MuJoCo loop
reads from ``data.sensordata`` after ``mj_step``, so ``PathFollower`` in such a loop reproduces these
runs to the bit (tested).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass

import numpy as np

from snakeloco.sim.control.follower import FollowerConfig, PathFollower
from snakeloco.sim.control.steering import Steering
from snakeloco.sim.physics.results import Dropped, Paused, SimulationError
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.robot.sensing import PoseEstimate


@dataclass
class ClosedLoopRun:
    """One closed-loop run, in the frame of the first pose its follower was given (m, rad, s)."""

    times: np.ndarray  # (n,) s from the first control step
    poses: np.ndarray  # (n, 3) true x, y, yaw at each control step
    averaged: np.ndarray  # (n, 2) the follower's averaged position (NaN before one period)
    steering: np.ndarray  # (n,) input u
    cross_track: np.ndarray  # (n,) m, left + (NaN before one period)
    progress: np.ndarray  # (n,) m along the path of the averaged position
    failure: str | None
    arrived: bool
    limit: float  # the input's limit (0: not steered)

    @property
    def end(self) -> np.ndarray:
        """(2,) m: the averaged position at the last control step."""
        return self.averaged[-1]

    @property
    def duration(self) -> float:
        """Seconds from the first control step to the last."""
        return float(self.times[-1])

    @property
    def saturated(self) -> float:
        """Share of the steered steps at which the input sat at its limit."""
        steered = np.isfinite(self.cross_track)
        if self.limit <= 0 or not steered.any():
            return 0.0
        return float(np.mean(np.abs(self.steering[steered]) >= self.limit * (1 - 1e-9)))

    @property
    def max_cross_track(self) -> float:
        """Largest |cross-track error| (m) once the record started (NaN where never measured)."""
        e = self.cross_track[np.isfinite(self.cross_track)]
        return float(np.abs(e).max()) if e.size else float("nan")


def run_closed_loop(
    simulator,
    followers: Sequence[PathFollower],
    robots: Sequence[Robot] | None = None,
    seeds: Sequence[int] | None = None,
) -> list[ClosedLoopRun]:
    """Run each follower on its robot (a variation of ``simulator.robot``; None: that robot) until it
    is done, in one batch. ``seeds``: each run's pose-noise seed (default its row). A run that breaks
    the simulation stops there with its ``failure`` named; the others go on.

    Rows go at their own pace on the simulator's threads: when one row's period is in, its follower
    steps and its next period is submitted while the others' run, so the followers' Python overlaps
    the physics (rows are independent: the result does not depend on the order)."""
    n_rows = len(followers)
    robots = list(robots) if robots is not None else [simulator.robot] * n_rows
    seeds = list(seeds) if seeds is not None else list(range(n_rows))
    if not (len(robots) == len(seeds) == n_rows):
        raise ValueError(f"{n_rows} followers, {len(robots)} robots, {len(seeds)} seeds")
    rate = simulator.excitation.sample_rate
    for f in followers:
        if abs(f.rate - rate) > 1e-9 or f.n_joints != simulator.robot.n_joints:
            raise ValueError(
                f"a follower at {f.rate} Hz for {f.n_joints} joints on a {rate} Hz, "
                f"{simulator.robot.n_joints}-joint simulator"
            )
        f.reset()
    rows = [
        _Row(
            simulator,
            f,
            simulator.variation_model(r),
            simulator.latency_steps(r),
            PoseEstimate(r.sensing, rate, s),
        )
        for f, r, s in zip(followers, robots, seeds, strict=True)
    ]
    pool = simulator.pool
    if pool is None:  # one thread: the rows in turn
        for row in rows:
            while row.advance(lambda *a: _run_now(simulator, *a)):
                pass
    else:
        pending = {}
        for row in rows:
            future = row.submit(pool)
            pending[future] = row
        while pending:
            done, _ = wait_futures(pending, return_when=FIRST_COMPLETED)
            for future in done:
                row = pending.pop(future)
                if future.cancelled():  # dropped on a shared pool's turns: the caller moved on
                    for other in pending:
                        other.cancel()
                    raise Dropped("the closed-loop replays were dropped")
                future.result()
                if row.finish():
                    pending[row.submit(pool)] = row
    return [row.result() for row in rows]


def _run_now(simulator, model, initial, ctrl, warm, state, sens, warm_out) -> None:
    """One row's period on the calling thread (a simulator without rollout threads), into ``state``,
    ``sens`` and ``warm_out`` as the threads' rollout fills them."""
    state[:], sens[:] = simulator.rollout(
        ctrl, start=Paused(0, initial, warm, (), []), warm_out=warm_out, models=[model]
    )


class _Row:
    """One run in progress: its follower, model, latency queue, pose estimate and log."""

    def __init__(self, simulator, follower: PathFollower, model, delay: int, sensor: PoseEstimate) -> None:
        self.sim, self.f, self.model, self.delay, self.sensor = simulator, follower, model, delay, sensor
        sub, joints = simulator.substeps, simulator.robot.n_joints
        self.state = simulator.initial_state[None].copy()
        self.warm = np.zeros((1, simulator.model.nv))
        self.pose = simulator.poses(simulator.initial_sensors())
        self.origin = self.pose.copy()
        self.prev = np.zeros(joints)  # the rest pose: the first ramp starts there
        self.late = np.zeros((delay, joints))  # targets still on their way
        self.frac = (np.arange(sub) / sub)[:, None]  # (S, 1)
        self.n, self.log, self.failure = 0, [], None
        nstate = self.state.shape[1]
        self.out_state = np.empty((1, sub, nstate))
        self.out_sens = np.empty((1, sub, simulator.model.nsensordata))
        self.warm_out = np.empty((1, simulator.model.nv))

    def _controls(self) -> np.ndarray:
        """Step the follower at this control step; the period's per-physics-step targets (1, S, J)."""
        f, rate = self.f, self.sim.excitation.sample_rate
        target = f.step(self.n / rate, *self.sensor(self.n, self.pose))
        x, y, yaw = f.in_frame(*self.pose)
        avg = f.averaged if f.averaged is not None else (np.nan, np.nan)
        self.log.append((self.n / rate, x, y, yaw, *avg, f.u, f.cross_track, f.progress))
        ctrl = self.prev + (target - self.prev) * self.frac  # (S, J)
        self.prev = target
        if self.delay:
            queue = np.concatenate([self.late, ctrl])
            ctrl, self.late = queue[: len(ctrl)], queue[len(ctrl) :]
        return ctrl[None]

    def submit(self, pool):
        (future,) = pool.rollout(
            [self.model],
            self.state,
            self._controls(),
            self.warm,
            self.out_state,
            self.out_sens,
            wait=False,
            warm_out=self.warm_out,
        )
        return future

    def advance(self, run) -> bool:
        """Synchronously: one period; whether the run goes on."""
        run(self.model, self.state, self._controls(), self.warm, self.out_state, self.out_sens, self.warm_out)
        return self.finish()

    def finish(self) -> bool:
        """Take in a period's rollout; whether the run goes on."""
        st, sens = self.out_state[0], self.out_sens[0]
        self.state, self.warm = st[-1:].copy(), self.warm_out.copy()
        self.pose = self.sim.poses(sens[-1])
        sub = self.sim.substeps
        why = None
        if not self.sim.healthy(st, sens, self.n * sub):
            why = self.sim.diagnose_steps(st, sens, self.sim.model.opt.timestep, first=self.n * sub)
        self.n += 1
        if why is not None:
            self.failure = why
            return False
        return not self.f.done

    def result(self) -> ClosedLoopRun:
        log = np.array(self.log, np.float64)  # (n, 9)
        f = self.f
        return ClosedLoopRun(
            times=log[:, 0],
            poses=log[:, 1:4],
            averaged=log[:, 4:6],
            steering=log[:, 6],
            cross_track=log[:, 7],
            progress=log[:, 8],
            failure=self.failure,
            arrived=f.arrived,
            limit=f.steering.limit if f.steering.steers else 0.0,
        )


def trailing_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last ``window`` samples along axis 0 (NaN before ``window`` samples)."""
    x = np.asarray(x, np.float64)
    c = np.cumsum(np.concatenate([np.zeros((1, *x.shape[1:])), x]), axis=0)
    out = np.full(x.shape, np.nan)
    out[window - 1 :] = (c[window:] - c[:-window]) / window
    return out


def nominal_path(commands: np.ndarray, simulator, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The path a gait follows by default, and where the record's frame sits in the path's frame.

    The path: its unsteered replay on ``simulator``'s robot, the body's position averaged over one
    ``period`` (s), from the record's start (or from the first whole period, where a period outlasts
    the lead-in) to its end, (T', 2) m in the frame of the resting snake's pose (the first pose a
    follower is given). The record frame (``sim.physics.body``): the body's pose at t = 0 in that
    frame, (3,) x, y m and yaw rad."""
    follower = make_follower(commands, np.zeros((2, 2)), Steering(period=period), simulator, "on_time")
    (run,) = run_closed_loop(simulator, [follower])
    if run.failure is not None:
        raise SimulationError(f"the nominal replay broke: {run.failure}")
    w = max(1, round(period * simulator.excitation.sample_rate))
    lead = simulator.config.lead_in
    return trailing_mean(run.poses[:, :2], w)[max(lead, w - 1) :], run.poses[lead].copy()


def nominal_reference(commands: np.ndarray, simulator, period: float) -> np.ndarray:
    """The path of ``nominal_path`` alone."""
    return nominal_path(commands, simulator, period)[0]


def cut_and_turn(reference: np.ndarray, until: int, pivot: np.ndarray, turn: float) -> np.ndarray:
    """A path's first ``until`` + 1 points turned by ``turn`` rad about ``pivot`` (2,)."""
    c, s = math.cos(turn), math.sin(turn)
    return pivot + (reference[: until + 1] - pivot) @ np.array([[c, s], [-s, c]])


def make_follower(
    commands: np.ndarray,
    reference: np.ndarray,
    steering: Steering,
    simulator,
    end: str = "arrive",
    config: FollowerConfig | None = None,
) -> PathFollower:
    """A follower of ``commands`` on ``simulator``'s robot and command rule."""
    cfg = (config or FollowerConfig()).model_copy(update={"end": end})
    return PathFollower(
        commands,
        reference,
        steering,
        simulator.robot.joint_axes,
        simulator.robot.command_limit,
        rate=simulator.excitation.sample_rate,
        lead_in=simulator.config.lead_in,
        ramp=simulator.config.ramp,
        config=cfg,
    )
