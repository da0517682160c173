"""``PathFollower``: a gait played with a steering loop that follows a path, as a robot's own loop runs it.

Each call of ``step(t, x, y, yaw)`` (at ``rate`` Hz, t in s from the first call, the pose of the body
frame in any fixed world frame) returns the servo targets (rad, n_joints) the robot reaches over the
next 1 / rate s, ramping linearly from the previous ones (the command rule, ``sim.physics.command_rule``:
with the steering at zero the targets are the open-loop gait's, its lead-in fade included).

Guidance is integral line-of-sight (ILOS: Børhaug, Pavlov, Pettersen 2008; on snakes Kelasidi et al.
2016) on the body's averaged pose, over one wave period (Rollinson and Choset's virtual chassis, not
the head's heading): desired course chi_d = gamma - atan((e + sigma y_i) / Delta), e the cross-track
error (m, left +), gamma the path's direction, y_i its integral; the course estimate is the averaged
heading plus the gait's travel offset (a sidewinder travels at +-90 deg to its body). The steering input
(``sim.control.steering``) is u = (chi_d - chi) / (k tau), k the gait's measured turn rate per unit,
tau the response time, clipped to the input's usable range.

Numpy and pydantic only: no MuJoCo, torch or viser, so a robot's computer runs it, and the simulator's
closed-loop replays (``sim.control.closed_loop``) use this very class.
"""

from __future__ import annotations

import json
import math
import warnings
from collections import deque
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.control.steering import Steering, apply, steering_pattern

SCHEMA = 1
"""Version of the controller directory (``controller.json``, ``commands.csv``, ``reference.csv``)."""


TURN_BACK = math.radians(150.0)
"""rad: a heading error beyond this is "facing backwards"; the loop keeps the way round it chose."""
REVERSE_PERIODS = 3
REVERSE_GROWTH = math.radians(30.0)


class FollowerConfig(BaseModel):
    """The follower's parameters (units in each description)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    look_ahead: float = Field(1.0, gt=0, description="ILOS look-ahead Delta (m): about one body length.")
    integral: float = Field(
        0.3, ge=0, le=2.0, description="ILOS integral gain sigma: cancels a steady drift (a slope)."
    )
    response_time: float = Field(
        1.5,
        gt=0,
        description="Time constant of the heading loop (s); at least one wave period is used, since the "
        "averaged heading lags by half of one.",
    )
    end: Literal["arrive", "on_time"] = Field(
        "arrive", description="arrive: stop at the path's end (capped); on_time: run the record's length."
    )
    cap: float = Field(2.0, gt=0, le=10.0, description="arrive: stop after this many records' lengths.")


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class PathFollower:
    """A gait, its steering input and the path it follows (module docstring)."""

    def __init__(
        self,
        commands: np.ndarray,
        reference: np.ndarray,
        steering: Steering,
        joint_axes: tuple[str, ...],
        command_limit: float,
        rate: float = 20.0,
        lead_in: int = 60,
        ramp: int = 40,
        config: FollowerConfig | None = None,
    ) -> None:
        self.commands = np.asarray(commands, np.float64)  # (T, n_joints) rad, one period of the gait
        self.reference = np.asarray(reference, np.float64)  # (n, 2) m, in the frame of the first pose
        if self.commands.ndim != 2 or self.commands.shape[1] != len(joint_axes):
            raise ValueError(f"commands {self.commands.shape} for {len(joint_axes)} joints")
        if self.reference.ndim != 2 or self.reference.shape[1] != 2 or len(self.reference) < 2:
            raise ValueError(f"a reference path is (n >= 2, 2) m, got {self.reference.shape}")
        if not (np.isfinite(self.commands).all() and np.isfinite(self.reference).all()):
            raise ValueError("commands and reference must be finite")
        self.steering = steering
        self.joint_axes = tuple(joint_axes)
        self.command_limit = float(command_limit)
        self.rate = float(rate)
        self.lead_in, self.ramp = int(lead_in), int(ramp)
        self.config = config or FollowerConfig()
        self.n_joints = self.commands.shape[1]
        self._pattern = steering_pattern(steering.kind, self.joint_axes) if steering.steers else None
        j = np.arange(self.lead_in)
        self._fade = np.where(j < self.ramp, 0.5 - 0.5 * np.cos(np.pi * j / self.ramp), 1.0)
        self._window = max(1, round(steering.period * self.rate))
        self._resample()
        self.reset()

    # The path, resampled at even arc length so that "how far along" is an index.

    def _resample(self) -> None:
        ref = self.reference
        seg = np.linalg.norm(np.diff(ref, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(arc[-1])
        self._ds = max(self.length / 4000.0, 0.005)
        s = np.linspace(0.0, self.length, max(2, int(self.length / self._ds) + 1))
        keep = np.concatenate([[True], seg > 0])  # repeated points have no direction
        self._xs, self._ys = (np.interp(s, arc[keep], ref[keep, i]) for i in range(2))  # (m,) m each
        self._s = s

    def reset(self) -> None:
        """Forget the run: the next ``step`` is a first call again."""
        self._origin: tuple[float, float, float] | None = None
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=self._window)
        self._sum = [0.0, 0.0, 0.0]
        self._last_yaw = 0.0
        self._index = 0
        self._y_int = 0.0
        self._way = 0.0  # the way round (+1 left, -1 right) once facing nearly backwards
        self._sign = 1.0  # -1 once the response was found reversed (``_watch``)
        self._errors: deque[tuple[float, bool]] = deque(maxlen=REVERSE_PERIODS * self._window)
        self.reversals = 0
        self._target = np.zeros(self.n_joints)
        self.done = False
        self.arrived = False
        self.u = 0.0  # the steering input of the last step
        self.cross_track = float("nan")  # m, left +, of the averaged pose (NaN before one period)
        self.progress = 0.0  # m along the path
        self.averaged: np.ndarray | None = None  # (x, y) m of the averaged pose, this frame
        self.t = 0.0

    @property
    def record_duration(self) -> float:
        """The gait's record length (s) at ``rate``."""
        return len(self.commands) / self.rate

    @property
    def lead_in_duration(self) -> float:
        return self.lead_in / self.rate

    def base_target(self, n: int) -> np.ndarray:
        """The open-loop servo target at control sample n (0: the first call; the lead-in first)."""
        if n < self.lead_in:
            return self.commands[len(self.commands) - self.lead_in + n] * self._fade[n]
        return self.commands[(n - self.lead_in) % len(self.commands)]

    def in_frame(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """A world pose in the frame of the first pose given (yaw wrapped to [-pi, pi))."""
        x0, y0, yaw0 = self._origin if self._origin is not None else (x, y, yaw)
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy = x - x0, y - y0
        return c * dx + s * dy, -s * dx + c * dy, _wrap(yaw - yaw0)

    def _frame(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        if self._origin is None:
            self._origin = (x, y, yaw)
            self._last_yaw = 0.0
        fx, fy, fyaw = self.in_frame(x, y, yaw)
        # Yaw unwrapped against the last one: the averaged heading never jumps by 2 pi.
        rel = self._last_yaw + _wrap(fyaw - self._last_yaw)
        self._last_yaw = rel
        return fx, fy, rel

    def _remember(self, pose: tuple[float, float, float]) -> None:
        """Add a pose to the last period's, keeping their sums (the averaged pose without a pass)."""
        if len(self._poses) == self._window:
            old = self._poses[0]
            self._sum = [a - b for a, b in zip(self._sum, old, strict=True)]
        self._poses.append(pose)
        self._sum = [a + b for a, b in zip(self._sum, pose, strict=True)]

    def step(self, t: float, x: float, y: float, yaw: float) -> np.ndarray:
        """Servo targets (n_joints,) rad for the next 1 / rate s, from the pose (m, m, rad) at ``t`` s
        after the first call. After ``done`` the last targets are held."""
        if self.done:
            return self._target
        self.t = float(t)
        n = round(t * self.rate)
        self._remember(self._frame(float(x), float(y), float(yaw)))
        record_t = t - self.lead_in_duration
        u = 0.0
        if (
            self._pattern is not None
            and record_t >= self.steering.period
            and len(self._poses) == self._window
        ):
            u = self._guide(1.0 / self.rate)
        elif len(self._poses) == self._window:
            self._track()
        self.u = u
        base = self.base_target(n + 1)
        self._target = (
            base
            if self._pattern is None
            else apply(self.steering.kind, self._pattern, base, u, self.command_limit)
        )
        end = self.lead_in_duration + self.record_duration * (
            self.config.cap if self.config.end == "arrive" else 1.0
        )
        if self.config.end == "arrive" and self.arrived and record_t > self.steering.period:
            self.done = True
        if t + 1.0 / self.rate >= end - 1e-9:
            self.done = True
        return self._target

    def _track(self) -> tuple[float, float]:
        """Update the averaged pose, progress and cross-track error; return (tangent angle, e)."""
        px, py = self._sum[0] / self._window, self._sum[1] / self._window
        self.averaged = np.array([px, py])
        xs, ys, look = self._xs, self._ys, self.config.look_ahead
        # The nearest path point a little behind to a look-ahead ahead of the last one: progress is
        # monotone, so a path that passes near itself later is not jumped to.
        lo = max(self._index - int(0.1 / self._ds), 0)
        hi = min(self._index + int(max(0.5, look) / self._ds) + 1, len(xs))
        d2 = (xs[lo:hi] - px) ** 2 + (ys[lo:hi] - py) ** 2
        k = int(np.argmin(d2))
        if d2[k] > (2 * look) ** 2:  # lost: the nearest point anywhere ahead of where it was
            d2 = (xs[self._index :] - px) ** 2 + (ys[self._index :] - py) ** 2
            self._index += int(np.argmin(d2))
        else:
            self._index = max(self._index, lo + k)
        i = self._index
        j = min(i + max(1, int(0.5 * look / self._ds)), len(xs) - 1)
        a, b = (i, j) if j > i else (max(i - 1, 0), i)
        gamma = math.atan2(ys[b] - ys[a], xs[b] - xs[a])
        c, s = math.cos(gamma), math.sin(gamma)
        rx, ry = px - xs[i], py - ys[i]
        e = c * ry - s * rx
        self.cross_track, self.progress = e, float(self._s[i])
        if i == len(xs) - 1 and c * rx + s * ry >= 0.0:
            self.arrived = True
        return gamma, e

    def _guide(self, dt: float) -> float:
        gamma, e = self._track()
        cfg, look = self.config, self.config.look_ahead
        self._y_int += dt * look * e / ((e + cfg.integral * self._y_int) ** 2 + look**2)
        chi_d = gamma - math.atan((e + cfg.integral * self._y_int) / look)
        heading = self._sum[2] / self._window
        err = _wrap(chi_d - heading - self.steering.travel_offset)
        # Facing nearly backwards either way round is as short: keep the way chosen, or the input
        # flips at the wrap every step and the snake circles on the spot.
        if abs(err) > TURN_BACK and self._way and np.sign(err) != self._way:
            err = self._way * (2 * math.pi - abs(err))
        self._way = float(np.sign(err)) if abs(err) > TURN_BACK else 0.0
        tau = max(cfg.response_time, self.steering.period)
        u = float(
            np.clip(
                err / (self._sign * self.steering.turn_rate * tau), -self.steering.limit, self.steering.limit
            )
        )
        self._watch(err, u)
        return u

    def _watch(self, err: float, u: float) -> None:
        """The way back from a reversed response: on some robots an input turns the gait the other way
        (a soft servo with latency on a slope, measured). Where the input sat at its limit for
        ``REVERSE_PERIODS`` wave periods while the heading error grew by more than ``REVERSE_GROWTH``,
        the loop takes the response as reversed and flips its sign."""
        self._errors.append((abs(err), abs(u) >= self.steering.limit * (1 - 1e-9)))
        if len(self._errors) < self._errors.maxlen:
            return
        first, _ = self._errors[0]
        if (
            all(sat for _, sat in self._errors)
            and abs(err) > first + REVERSE_GROWTH
            and abs(err) > REVERSE_GROWTH
        ):
            self._sign = -self._sign
            self.reversals += 1
            self._errors.clear()

    # A controller directory: what ``snakeloco export --format controller`` writes.

    def save(self, directory: str | Path, about: dict | None = None) -> Path:
        """Write ``controller.json``, ``commands.csv`` (rad, one row per 1 / rate s) and
        ``reference.csv`` (m) into ``directory``."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        spec = {
            "schema": SCHEMA,
            "rate_hz": self.rate,
            "lead_in": self.lead_in,
            "ramp": self.ramp,
            "command_limit_rad": self.command_limit,
            "joint_axes": list(self.joint_axes),
            "steering": self.steering.model_dump(),
            "follower": self.config.model_dump(),
            "about": about or {},
        }
        (out / "controller.json").write_text(json.dumps(spec, indent=2) + "\n")
        head = ",".join(f"q{k + 1}_rad" for k in range(self.n_joints))
        np.savetxt(out / "commands.csv", self.commands, delimiter=",", header=head, comments="", fmt="%.17g")
        np.savetxt(
            out / "reference.csv", self.reference, delimiter=",", header="x_m,y_m", comments="", fmt="%.17g"
        )
        return out

    @classmethod
    def load(cls, directory: str | Path, config: FollowerConfig | None = None) -> PathFollower:
        """The follower saved in ``directory`` (``save``); ValueError names a missing or bad file."""
        d = Path(directory)
        try:
            spec = json.loads((d / "controller.json").read_text())
            with warnings.catch_warnings():  # an empty file is refused below, by its shape
                warnings.simplefilter("ignore", UserWarning)
                commands = np.loadtxt(d / "commands.csv", delimiter=",", skiprows=1, ndmin=2)
                reference = np.loadtxt(d / "reference.csv", delimiter=",", skiprows=1, ndmin=2)
            if spec.get("schema") != SCHEMA:
                raise ValueError(f"controller.json has schema {spec.get('schema')!r}, expected {SCHEMA}")
            return cls(
                commands,
                reference,
                Steering.model_validate(spec["steering"]),
                tuple(spec["joint_axes"]),
                spec["command_limit_rad"],
                rate=spec["rate_hz"],
                lead_in=spec["lead_in"],
                ramp=spec["ramp"],
                config=config or FollowerConfig.model_validate(spec["follower"]),
            )
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{d}: not a controller directory ({exc})") from None
