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

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from snakeloco.sim.control.follower import FollowerConfig, PathFollower
from snakeloco.sim.control.steering import Steering
from snakeloco.sim.physics.results import Paused, SimulationError
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
    the simulation stops there with its ``failure`` named; the others go on."""
    b_all = len(followers)
    robots = list(robots) if robots is not None else [simulator.robot] * b_all
    seeds = list(seeds) if seeds is not None else list(range(b_all))
    if not (len(robots) == len(seeds) == b_all):
        raise ValueError(f"{b_all} followers, {len(robots)} robots, {len(seeds)} seeds")
    rate, sub = simulator.excitation.sample_rate, simulator.substeps
    for f in followers:
        if abs(f.rate - rate) > 1e-9 or f.n_joints != simulator.robot.n_joints:
            raise ValueError(
                f"a follower at {f.rate} Hz for {f.n_joints} joints on a {rate} Hz, "
                f"{simulator.robot.n_joints}-joint simulator"
            )
        f.reset()
    models = [simulator.variation_model(r) for r in robots]
    delays = [simulator.latency_steps(r) for r in robots]
    sensors = [PoseEstimate(r.sensing, rate, seed=s) for r, s in zip(robots, seeds, strict=True)]
    state = np.repeat(simulator.initial_state[None], b_all, axis=0)
    warm = np.zeros((b_all, simulator.model.nv))
    pose = np.repeat(simulator.poses(simulator.initial_sensors())[None], b_all, axis=0)  # (B, 3) world
    prev = np.zeros((b_all, simulator.robot.n_joints))  # the rest pose: the first ramp starts there
    late = [np.zeros((d, simulator.robot.n_joints)) for d in delays]  # targets still on their way
    frac = (np.arange(sub) / sub)[None, :, None]  # (1, S, 1)
    logs: list[list[tuple]] = [[] for _ in range(b_all)]
    failures: list[str | None] = [None] * b_all
    active = np.ones(b_all, bool)
    n = 0
    while active.any():
        rows = np.flatnonzero(active)
        targets = np.empty((len(rows), simulator.robot.n_joints))
        for i, b in enumerate(rows):
            f = followers[b]
            est = sensors[b](n, pose[b])
            targets[i] = f.step(n / rate, *est)
            origin = f._origin
            c, s = np.cos(origin[2]), np.sin(origin[2])
            dx, dy = pose[b, 0] - origin[0], pose[b, 1] - origin[1]
            avg = f.averaged if f.averaged is not None else (np.nan, np.nan)
            logs[b].append(
                (
                    n / rate,
                    c * dx + s * dy,
                    -s * dx + c * dy,
                    pose[b, 2] - origin[2],
                    *avg,
                    f.u,
                    f.cross_track,
                )
            )
        ctrl = prev[rows, None] + (targets - prev[rows])[:, None] * frac  # (R, S, J)
        prev[rows] = targets
        for i, b in enumerate(rows):
            if delays[b]:
                queue = np.concatenate([late[b], ctrl[i]])
                ctrl[i], late[b] = queue[:sub], queue[sub:]
        warm_out = np.empty((len(rows), simulator.model.nv))
        start = Paused(0, state[rows], warm[rows], (), [])
        st, sens = simulator.rollout(ctrl, start=start, warm_out=warm_out, models=[models[b] for b in rows])
        state[rows], warm[rows] = st[:, -1], warm_out
        pose[rows] = simulator.poses(sens[:, -1])
        for i, b in enumerate(rows):
            why = simulator.diagnose_steps(st[i], sens[i], simulator.model.opt.timestep, first=n * sub)
            if why is not None:
                failures[b], active[b] = why, False
            elif followers[b].done:
                active[b] = False
        n += 1
    out = []
    for b, f in enumerate(followers):
        log = np.array(logs[b], np.float64)  # (n, 8)
        out.append(
            ClosedLoopRun(
                times=log[:, 0],
                poses=log[:, 1:4],
                averaged=log[:, 4:6],
                steering=log[:, 6],
                cross_track=log[:, 7],
                failure=failures[b],
                arrived=f.arrived,
                limit=f.steering.limit if f.steering.steers else 0.0,
            )
        )
    return out


def trailing_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last ``window`` samples along axis 0 (NaN before ``window`` samples)."""
    x = np.asarray(x, np.float64)
    c = np.cumsum(np.concatenate([np.zeros((1, *x.shape[1:])), x]), axis=0)
    out = np.full(x.shape, np.nan)
    out[window - 1 :] = (c[window:] - c[:-window]) / window
    return out


def nominal_reference(commands: np.ndarray, simulator, period: float) -> np.ndarray:
    """The path a gait follows by default: its unsteered replay on ``simulator``'s robot, the body's
    position averaged over one ``period`` (s), from the record's start to its end (T, 2) m, in the
    frame of the resting snake's pose (the first pose a follower is given)."""
    follower = make_follower(commands, np.zeros((2, 2)), Steering(period=period), simulator, "on_time")
    (run,) = run_closed_loop(simulator, [follower])
    if run.failure is not None:
        raise SimulationError(f"the nominal replay broke: {run.failure}")
    w = max(1, round(period * simulator.excitation.sample_rate))
    return trailing_mean(run.poses[:, :2], w)[simulator.config.lead_in :]


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
