"""How a robot senses where it is: the pose estimate a steering loop is given (``sim.control``).

Part of the robot description (``Robot.sensing``) and varied like its physics: a position and a heading
from motion capture, odometry or an IMU, refreshed ``pose_rate`` times a second, ``pose_latency`` late,
with white noise and a heading that drifts. The default is a perfect estimate at every control step.
Numpy only: the estimate is simulated here, and a robot's own loop gets its own.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

SENSING_FIELDS = ("pose_noise_m", "pose_noise_deg", "heading_drift_deg_per_min", "pose_rate", "pose_latency")
"""The fields a variation may change (``sim.robot.variations``), flat names as in a Variation."""


class Sensing(BaseModel):
    """The pose estimate's quality. Units: m, deg, deg per minute, Hz, s."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    pose_noise_m: float = Field(0.0, ge=0, le=1.0, description="Position noise, standard deviation (m).")
    pose_noise_deg: float = Field(0.0, ge=0, le=45.0, description="Heading noise, standard deviation (deg).")
    heading_drift_deg_per_min: float = Field(
        0.0, ge=-60.0, le=60.0, description="Heading estimate drift (deg per minute; an IMU's gyro bias)."
    )
    pose_rate: float = Field(
        20.0, gt=0, le=1000.0, description="Pose estimates per second (Hz); at most one per control step."
    )
    pose_latency: float = Field(0.0, ge=0, le=1.0, description="How late each estimate arrives (s).")


class PoseEstimate:
    """The estimates one run's loop is given, from the true poses of the body frame (x, y in m, yaw in
    rad, world frame), one per control step at ``rate`` Hz; deterministic in ``seed``.

    Step n is given the pose of step m - k, m the latest refresh at or before n (every
    ``rate / pose_rate`` steps) and k the latency in steps, plus noise drawn once per refresh and the
    drift accumulated by then. Before the first pose has arrived, step n gets the first pose.
    """

    def __init__(self, sensing: Sensing, rate: float, seed: int = 0) -> None:
        self.sensing = sensing
        self.rate = float(rate)
        self.every = max(1, round(rate / sensing.pose_rate))
        self.delay = round(sensing.pose_latency * rate)
        self._rng = np.random.default_rng(seed)
        self._true: list[np.ndarray] = []
        self._held: np.ndarray | None = None

    def __call__(self, step: int, pose: np.ndarray) -> np.ndarray:
        """The estimate (x, y, yaw) at control step ``step`` (0, 1, ... in order), given the true pose
        (x, y, yaw) at that step."""
        self._true.append(np.asarray(pose, np.float64))
        if self._held is None or step % self.every == 0:
            s = self.sensing
            true = self._true[max(step - self.delay, 0)]
            noise = np.array(
                [
                    self._rng.normal(0.0, s.pose_noise_m) if s.pose_noise_m else 0.0,
                    self._rng.normal(0.0, s.pose_noise_m) if s.pose_noise_m else 0.0,
                    np.radians(self._rng.normal(0.0, s.pose_noise_deg)) if s.pose_noise_deg else 0.0,
                ]
            )
            drift = np.radians(s.heading_drift_deg_per_min) * step / self.rate / 60.0
            self._held = true + noise + np.array([0.0, 0.0, drift])
        return self._held
