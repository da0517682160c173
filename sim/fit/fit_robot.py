"""Fit a robot's physics to measured runs: ``snakeloco fit-robot`` (docs/calibration.md).

Given gaits the robot ran and where it went (``sim.fit.measured``), the chosen physical fields of the
robot description are searched with CMA-ES so that replays match the measured paths (and joint
angles, where measured). Each generation's candidates x runs replay as one batch of varied models
(``Simulator.simulate(robots=...)``).

Search space: a field that scales (friction, gains, masses ...) is searched as a factor of its start
value in [1/``bound``, ``bound``] on a log scale; ``slope_deg`` in [0, 10] deg,
``slope_direction_deg`` in [-180, 180], ``latency`` in [0, 0.1] s.

Loss of one run: odometry increments (``FitConfig.loss``; or the RMS distance of the replayed from
the measured body position at the measured times over max(measured distance, 0.5 m)), plus
``yaw_weight`` x the heading error (rad), plus ``joint_weight`` x the RMS joint-angle error (rad)
beyond the run's own measurement noise where joints were measured; the loss is the mean over runs. A replay that breaks costs
``BROKEN_LOSS``.

Uncertainty (``sim.fit.uncertainty``): around the optimum the loss is probed at +/-15% of each field (others fixed); its
slope gives the half-width in which the loss rises by ``tolerance`` (the larger of the optimum's own
loss, i.e. doubling the misfit, and ``min_tolerance``): what the runs cannot tell apart. A field whose half-width is
over 15% (or whose loss does not rise) is *not determined* by these runs; the report names the
library gait whose end point moves most when that field doubles (the gait that would determine it).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.fit.measured import MeasuredRun, MeasuredRunError
from snakeloco.sim.fit.uncertainty import ADDITIVE, FitCancelled, most_sensitive_gait, uncertainty
from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.robot.description import Robot, robot_from_dict
from snakeloco.sim.robot.variations import PHYSICAL_FIELDS

BROKEN_LOSS = 100.0


class FitConfig(BaseModel):
    """The search (CMA-ES over the chosen fields)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    params: tuple[str, ...] = ("friction_along", "friction_across", "servo_kp")
    """Physical fields of the robot description to fit."""
    bound: float = Field(4.0, gt=1.0, le=20.0)
    """A scaling field is searched within [start / bound, start x bound]."""
    popsize: int = Field(8, ge=4, le=64)
    """Candidates per CMA-ES generation (each replays every run)."""
    generations: int = Field(30, ge=1, le=500)
    """CMA-ES generations."""
    horizons: tuple[float, ...] = (20.0, 50.0)
    """Seconds of each run the loss reads, in equal shares of the generations: short horizons first,
    where a path depends smoothly on the physics (over 100 s small changes can grow chaotically),
    then longer. The uncertainty is probed on the last horizon; the path errors before and after
    are the whole run's."""
    seed: int = Field(0, ge=0)
    yaw_weight: float = Field(0.1, ge=0)
    """Weight of the RMS heading error (rad) beside the relative path error."""
    loss: Literal["path", "increments"] = "increments"
    """path: the replayed path against the measured one; increments: each window's displacement in
    the body's own heading and its heading change (odometry increments: smooth in the physics where
    a path's heading errors pile up)."""
    window_s: float = Field(5.0, gt=0)
    """Window of the increments (s)."""
    joint_weight: float = Field(10.0, ge=0)
    """Weight of the RMS joint-angle error (rad, beyond the run's own measurement noise:
    ``joint_noise``) where a run has measured joint angles: how the servos tracked their commands,
    which the servo fields and the floor's load set and a path alone hardly shows. At 10, 0.01 rad
    of misfit weighs as a 10% error of the path."""
    min_tolerance: float = Field(0.003, gt=0)
    """Smallest loss rise the uncertainty is measured against (0.3% of the distance)."""


def dominant_frequency(commands: np.ndarray) -> float:
    """The excited frequency (Hz) with the largest command amplitude: one cycle of the gait."""
    spectrum = np.abs(np.fft.rfft(commands, axis=0)).sum(axis=1)  # (T/2 + 1,)
    spectrum[0] = 0.0
    return float(np.argmax(spectrum) / RECORD.duration)


def check_pairs(pairs: Sequence[tuple[np.ndarray, MeasuredRun]], robot: Robot) -> None:
    """Refuse runs that cannot be fitted: MeasuredRunError naming the run and the reason."""
    if not pairs:
        raise MeasuredRunError("no measured runs to fit")
    for commands, run in pairs:
        if commands.shape[1] != robot.n_joints:
            raise MeasuredRunError(
                f"{run.source}: the gait has {commands.shape[1]} joints, the robot {robot.name} {robot.n_joints}"
            )
        if run.joints is not None and run.joints.shape[1] != commands.shape[1]:
            raise MeasuredRunError(
                f"{run.source}: {run.joints.shape[1]} measured joints, the gait has {commands.shape[1]}"
            )
        f = dominant_frequency(commands)
        if f > 0 and run.duration < 1.0 / f:
            raise MeasuredRunError(
                f"{run.source}: the run lasts {run.duration:.2f} s, shorter than one cycle of its gait "
                f"({1 / f:.2f} s at {f:.2f} Hz)"
            )
        if run.times[-1] > RECORD.duration:
            raise MeasuredRunError(
                f"{run.source}: the run goes on to {run.times[-1]:g} s; the replay covers the {RECORD.duration:g} s record"
            )


class RobotFit:
    """The loss of candidate robots on measured runs, replayed in batches on one simulator."""

    def __init__(self, pairs, start: Robot, cfg: FitConfig, simulator) -> None:
        unknown = [p for p in cfg.params if p not in PHYSICAL_FIELDS]
        if unknown:
            raise ValueError(f"cannot fit {unknown}: fit one of {', '.join(PHYSICAL_FIELDS)}")
        check_pairs(pairs, start)
        self.pairs, self.start, self.cfg, self.sim = list(pairs), start, cfg, simulator
        self.full = min(
            RECORD.n_samples, max(math.ceil(r.times[-1] * RECORD.sample_rate) + 2 for _, r in pairs)
        )
        self.samples = self.full
        self.replays = 0
        self.noise = {id(run): joint_noise(run) for _, run in self.pairs}

    def robot(self, x: np.ndarray) -> Robot:
        """The candidate at search coordinates ``x`` (one per field, in [-1, 1])."""
        values = self.start.model_dump()
        for name, xi in zip(self.cfg.params, x, strict=True):
            if name in ADDITIVE:
                lo, hi = ADDITIVE[name]
                values[name] = lo + (hi - lo) * (float(np.clip(xi, -1, 1)) + 1) / 2
            else:
                values[name] = getattr(self.start, name) * self.cfg.bound ** float(np.clip(xi, -1, 1))
        values["name"] = f"{self.start.name} fitted"[:64]
        return robot_from_dict(values, "fitted robot")

    def x_of(self, robot: Robot) -> np.ndarray:
        """Search coordinates of a robot (the inverse of ``robot``)."""
        out = []
        for name in self.cfg.params:
            if name in ADDITIVE:
                lo, hi = ADDITIVE[name]
                out.append(2 * (getattr(robot, name) - lo) / (hi - lo) - 1)
            else:
                out.append(
                    math.log(getattr(robot, name) / getattr(self.start, name)) / math.log(self.cfg.bound)
                )
        return np.array(out)

    def replay(self, robots: Sequence[Robot]) -> list[list[tuple[np.ndarray, np.ndarray] | None]]:
        """Body series (samples, 6) and joint angles (samples, J) of every run on every robot
        ([robot][run]; None where it broke)."""
        cmds = np.stack([c for _ in robots for c, _ in self.pairs])
        rows = [r for r in robots for _ in self.pairs]
        result = self.sim.simulate(cmds, samples=self.samples, robots=rows)
        if result is None:  # a designer's fit whose tab moved on: its replays were dropped
            raise FitCancelled
        self.replays += len(rows)
        n = len(self.pairs)
        return [
            [
                None
                if result.failures[i * n + j]
                else (result.body[i * n + j], result.joint_angles[i * n + j])
                for j in range(n)
            ]
            for i in range(len(robots))
        ]

    def run_loss(self, replayed: tuple[np.ndarray, np.ndarray] | None, run: MeasuredRun) -> float:
        """The loss of one run's replay (body, joint angles); ``BROKEN_LOSS`` where it broke."""
        if replayed is None:
            return BROKEN_LOSS
        body, joints = replayed
        loss = self.increment_loss(body, run) if self.cfg.loss == "increments" else self.path_loss(body, run)
        if run.joints is not None and self.cfg.joint_weight > 0:
            # The misfit beyond the run's own noise (rms^2 = misfit^2 + noise^2): the noise is no
            # misfit a field could remove, and left in it would widen every field's interval.
            misfit2 = joint_rms(joints, run) ** 2 - self.noise[id(run)] ** 2
            loss += self.cfg.joint_weight * math.sqrt(max(misfit2, 0.0))
        return loss

    def path_loss(self, body: np.ndarray, run: MeasuredRun) -> float:
        """RMS distance of the replayed from the measured path over the distance, plus the heading's."""
        t = np.arange(len(body)) / RECORD.sample_rate
        seen = run.times <= t[-1]
        times, measured = run.times[seen], run.xy[seen]
        xy = np.stack([np.interp(times, t, body[:, k]) for k in (1, 2)], axis=1)
        yaw = np.interp(times, t, body[:, 5])
        loss = np.sqrt(np.mean(np.sum((xy - measured) ** 2, axis=1))) / max(
            float(np.hypot(*measured[-1])), 0.5
        )
        loss += self.cfg.yaw_weight * np.sqrt(np.mean((yaw - run.yaw[seen]) ** 2))
        return float(loss)

    def increment_loss(self, body: np.ndarray, run: MeasuredRun) -> float:
        """How each window's displacement, in the body's own heading at the window's start, and its
        heading change differ between replay and run: odometry increments, which do not carry one
        window's heading error into every later position as the path itself does."""
        t = np.arange(len(body)) / RECORD.sample_rate
        edges = np.arange(0.0, min(t[-1], run.times[-1]) + 1e-9, self.cfg.window_s)
        if len(edges) < 2:
            edges = np.array([0.0, min(t[-1], run.times[-1])])

        def increments(times, x, y, yaw):
            px, py, th = (np.interp(edges, times, v) for v in (x, y, yaw))
            dx, dy = np.diff(px), np.diff(py)
            c, s = np.cos(th[:-1]), np.sin(th[:-1])
            return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1), np.diff(th)

        sim_d, sim_turn = increments(t, body[:, 1], body[:, 2], body[:, 5])
        run_d, run_turn = increments(run.times, run.xy[:, 0], run.xy[:, 1], run.yaw)
        scale = max(float(np.mean(np.hypot(*run_d.T))), 0.05 * self.cfg.window_s)
        loss = np.sqrt(np.mean(np.sum((sim_d - run_d) ** 2, axis=1))) / scale
        return float(loss + self.cfg.yaw_weight * np.sqrt(np.mean((sim_turn - run_turn) ** 2)))

    def set_horizon(self, seconds: float) -> None:
        """Replay (and score) only the first ``seconds`` of each run from now on."""
        self.samples = min(self.full, math.ceil(seconds * RECORD.sample_rate) + 2)

    def losses(self, robots: Sequence[Robot]) -> np.ndarray:
        """Mean loss over the runs of each robot."""
        bodies = self.replay(robots)
        return np.array(
            [
                np.mean([self.run_loss(b, r) for b, (_, r) in zip(bs, self.pairs, strict=True)])
                for bs in bodies
            ]
        )

    def path_errors(self, robot: Robot) -> list[dict]:
        """Per run: RMS path error and end-point error (m) of ``robot``'s replay against the run."""
        out = []
        for replayed, (_, run) in zip(self.replay([robot])[0], self.pairs, strict=True):
            if replayed is None:
                out.append({"run": run.source, "rms_m": None, "end_m": None, "broke": True})
                continue
            body, joints = replayed
            t = np.arange(len(body)) / RECORD.sample_rate
            xy = np.stack([np.interp(run.times, t, body[:, k]) for k in (1, 2)], axis=1)
            err = np.hypot(*(xy - run.xy).T)
            row = {
                "run": run.source,
                "rms_m": float(np.sqrt(np.mean(err**2))),
                "end_m": float(err[-1]),
                "distance_m": run.distance,
                "end_rel": float(err[-1] / max(run.distance, 0.5)),
            }
            if run.joints is not None:
                row["joint_rms_rad"] = joint_rms(joints, run)
            out.append(row)
        return out


def joint_rms(joints: np.ndarray, run: MeasuredRun) -> float:
    """RMS difference (rad) of replayed joint angles (samples, J) at the record's rate from the run's
    measured ones, over the run's times the replay covers."""
    t = np.arange(len(joints)) / RECORD.sample_rate
    seen = run.times <= t[-1]
    replayed = np.stack([np.interp(run.times[seen], t, joints[:, k]) for k in range(joints.shape[1])], axis=1)
    return float(np.sqrt(np.mean((replayed - run.joints[seen]) ** 2)))


def joint_noise(run: MeasuredRun) -> float:
    """The measurement noise (rad, RMS) of a run's joint angles, estimated from their third
    differences: white noise of variance s^2 gives third differences of variance 20 s^2, while a
    gait's joint waves (under 1 Hz) barely move them at motion-capture rates (at 50 Hz a 0.7 rad
    wave at 0.93 Hz adds 1e-3 rad against the 0.04 rad of 0.5 deg noise)."""
    if run.joints is None or len(run.joints) < 8:
        return 0.0
    return float(np.sqrt(np.mean(np.diff(run.joints, n=3, axis=0) ** 2) / 20.0))


def fit_robot(
    pairs: Sequence[tuple[np.ndarray, MeasuredRun]],
    robot: Robot,
    cfg: FitConfig | None = None,
    simulator=None,
    progress: Callable[[int], None] | None = None,
    advise: bool = True,
) -> dict:
    """Fit ``cfg.params`` of ``robot`` to measured runs ((commands (T, J) rad, run) pairs).

    Returns {"robot": the fitted Robot, "params": {name: {"start", "fitted", "low", "high", "rel_uncertainty",
    "determined", "would_determine"}}, "loss_start", "loss_fitted", "before", "after" (per-run path
    errors), "replays", "seconds", "generations"}.
    """
    import cma

    from snakeloco.sim.physics.simulator import Simulator

    cfg = cfg or FitConfig()
    own = simulator is None
    simulator = simulator or Simulator(workers=None, robot=robot)
    t0 = time.perf_counter()
    try:
        fit = RobotFit(pairs, robot, cfg, simulator)
        x0 = np.zeros(len(cfg.params))
        es = cma.CMAEvolutionStrategy(
            x0, 0.3, {"popsize": cfg.popsize, "seed": cfg.seed + 1, "bounds": [-1, 1], "verbose": -9}
        )
        stages = np.array_split(np.arange(cfg.generations), len(cfg.horizons))
        for horizon, gens in zip(cfg.horizons, stages, strict=True):
            fit.set_horizon(horizon)
            for _ in gens:
                xs = es.ask()
                es.tell(xs, fit.losses([fit.robot(x) for x in xs]).tolist())
                if progress is not None:
                    progress(1)
        # The search's mean is its estimate: near the truth the loss is rough (a replay's contacts and
        # rolls flip with small changes), and the best single candidate is the luckiest, not the
        # likeliest. Its spread is part of the uncertainty.
        best_x = np.clip(es.mean, -1, 1)
        spread = es.sigma * np.sqrt(np.diag(es.C))
        fitted = fit.robot(best_x)
        loss_start, best_loss = (float(v) for v in fit.losses([robot, fitted]))
        params = uncertainty(fit, best_x, best_loss, spread)
        fit.set_horizon(RECORD.duration)
        if advise:
            for name, p in params.items():
                if not p["determined"]:
                    p["would_determine"] = most_sensitive_gait(fitted, name, simulator)
        return {
            "robot": fitted,
            "params": params,
            "loss_start": loss_start,
            "loss_fitted": best_loss,
            "before": fit.path_errors(robot),
            "after": fit.path_errors(fitted),
            "replays": fit.replays,
            "generations": cfg.generations,
            "seconds": time.perf_counter() - t0,
        }
    finally:
        if own:
            simulator.close()
