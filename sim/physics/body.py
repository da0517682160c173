"""Body states: the 6 measured channels of the middle link, in the frame of the snake's start.

Channels (in this order): vertical, forward, sideways position (m) and roll, pitch, yaw (rad) of the
middle link's frame (site ``body_frame`` at the centre of link 5: where an IMU on the central module
of the real robot would be), expressed in the frame of that link's position and heading at t = 0:
positions are R_z(-yaw_0) (p(t) - p(0)), angles are the Z-Y-X (yaw, pitch, roll) Euler angles of
R_z(-yaw_0) R(t). Yaw and roll are unwrapped over time (the snake may roll over and over).
Numpy only (``SensorColumns`` reads a compiled model it is given).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    import mujoco

BODY_CHANNELS = ("vertical", "forward", "sideways", "roll", "pitch", "yaw")
"""Order of the 6 body channels: 3 positions (m), then 3 angles (rad)."""
MIRROR_SIGNS = np.array([1.0, 1.0, -1.0, -1.0, 1.0, -1.0])
"""Per body channel, its sign in the mirror image of a path (y -> -y): sideways, roll and yaw flip."""


def mirror_body(body: np.ndarray) -> np.ndarray:
    """The mirror image (y -> -y) of body series (..., 6): what the mirrored gait does
    (``sim.gaits.members.Member.mirrored``)."""
    return np.asarray(body) * MIRROR_SIGNS


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions wxyz -> (..., 3, 3) rotation matrices (frame to world)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def body_states(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Body channels in the initial heading frame.

    Args:
        pos: (B, T, 3) world position of the body frame (m).
        quat: (B, T, 4) world orientation of the body frame, wxyz.

    Returns:
        (B, T, 6): vertical, forward, sideways (m), roll, pitch, yaw (rad), yaw and roll unwrapped.
    """
    rot = quat_to_matrix(quat)  # (B, T, 3, 3)
    yaw0 = np.arctan2(rot[:, 0, 1, 0], rot[:, 0, 0, 0])  # (B,) heading of the link's x axis at t=0
    c, s = np.cos(yaw0), np.sin(yaw0)
    zero, one = np.zeros_like(c), np.ones_like(c)
    undo = np.stack(
        [np.stack([c, s, zero], -1), np.stack([-s, c, zero], -1), np.stack([zero, zero, one], -1)], -2
    )  # (B, 3, 3) = R_z(-yaw0)
    rel_pos = np.einsum("bij,btj->bti", undo, pos - pos[:, :1])  # (B, T, 3) x fwd, y side, z up
    rel_rot = np.einsum("bij,btjk->btik", undo, rot)  # (B, T, 3, 3)
    yaw = np.arctan2(rel_rot[..., 1, 0], rel_rot[..., 0, 0])
    pitch = np.arcsin(np.clip(-rel_rot[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(rel_rot[..., 2, 1], rel_rot[..., 2, 2])
    return np.stack(
        [
            rel_pos[..., 2],
            rel_pos[..., 0],
            rel_pos[..., 1],
            np.unwrap(roll, axis=1),
            pitch,
            np.unwrap(yaw, axis=1),
        ],
        axis=-1,
    )


def wrap_deg(deg: float) -> float:
    """An angle in (-180, 180] degrees."""
    wrapped = (float(deg) + 180.0) % 360.0 - 180.0
    return 180.0 if wrapped == -180.0 else wrapped


def heading_text(change_deg: float) -> str:
    """A heading change as a person reads it: the heading in (-180, 180] degrees, and where the body
    turned round more than half a turn, the net turn said apart ('+42° (1.1 turns left)')."""
    text = f"{wrap_deg(change_deg):+.0f}°"
    if abs(change_deg) > 180.0:
        text += f" ({abs(change_deg) / 360.0:.1f} turns {'left' if change_deg > 0 else 'right'})"
    return text


def travel(body: np.ndarray) -> dict[str, float]:
    """The one set of figures every place a person reads a path's end uses (readout, CLI tables, CSV
    headers, the html page): ``distance_m`` (straight-line from the start, m), ``direction_deg`` (the
    direction of travel: where the end lies from the start, measured from the initial heading, deg,
    left +, in (-180, 180]), ``heading_change_deg`` (how much the body turned, wrapped to
    (-180, 180]) and ``turns`` (the net turn in whole-and-part turns, left +). ``body`` (T, 6) in the
    start frame (``body_states``)."""
    b = np.asarray(body, np.float64)
    f, s = float(b[-1, 1] - b[0, 1]), float(b[-1, 2] - b[0, 2])
    net = float(np.degrees(b[-1, 5] - b[0, 5]))
    return {
        "distance_m": float(np.hypot(f, s)),
        "direction_deg": wrap_deg(np.degrees(np.arctan2(s, f))),
        "heading_change_deg": wrap_deg(net),
        "turns": net / 360.0,
    }


class SensorColumns(NamedTuple):
    """Where each measurement sits in a sensordata row: joint angles (n_joints,), the body frame's
    position (3,) and quaternion (4,), the centre of mass's position (3,) and velocity (3,)."""

    q: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    com: np.ndarray
    vel: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel, n_joints: int) -> SensorColumns:
        adr = {model.sensor(i).name: model.sensor_adr[i] for i in range(model.nsensor)}
        q = np.array([adr[f"q{k + 1}"] for k in range(n_joints)])
        return cls(q, *(adr[name] + np.arange(n) for name, n in BODY_SENSORS))


BODY_SENSORS = (("body_pos", 3), ("body_quat", 4), ("com_pos", 3), ("com_vel", 3))
