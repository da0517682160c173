"""Link poses for drawing the robot: from a MuJoCo ``qpos`` to each capsule's pose in the start frame.

The start frame is the one the body channels are expressed in (``sim.physics.body``): the middle link's
position and heading at t = 0, x forward, y left, z up (metres), with the height kept (so the snake
lies on the drawn floor). Each link is a capsule, its axis along the geom frame's z axis, centred
on the geom's position; its radius and length are read from the compiled MJCF (``capsule``), so
the picture cannot drift from the physics.
"""

from __future__ import annotations

import mujoco
import numpy as np

from snakeloco.sim.robot.description import BODY_SITE, Robot, resolve_robot


class LinkPoses:
    """Forward kinematics of the snake on a private MjModel/MjData (one per caller: not thread-safe)."""

    def __init__(self, robot: Robot | None = None) -> None:
        self.robot = resolve_robot(robot)
        self.model = self.robot.compile()
        self.data = mujoco.MjData(self.model)
        self._geoms = np.array([self.model.geom(name).id for name in self.robot.link_geoms])
        self._site = self.model.site(BODY_SITE).id

    def capsule(self) -> tuple[float, float]:
        """The links' capsule (radius, centre-to-centre length) in m, as MuJoCo compiled them (a
        capsule geom's size is its radius and half length); ValueError if the links differ (the
        scene draws every link with one mesh)."""
        sizes = self.model.geom_size[self._geoms, :2]
        types = self.model.geom_type[self._geoms]
        if not (np.all(types == mujoco.mjtGeom.mjGEOM_CAPSULE) and np.allclose(sizes, sizes[0])):
            raise ValueError("the snake's links are not all the same capsule: the scene cannot draw them")
        return float(sizes[0, 0]), float(2 * sizes[0, 1])

    def start_frame(self, qpos0: np.ndarray) -> tuple[np.ndarray, float]:
        """World position (3,) m and heading (rad) of the body frame for the record's first ``qpos``."""
        self.data.qpos[:] = qpos0
        mujoco.mj_kinematics(self.model, self.data)
        xmat = self.data.site_xmat[self._site].reshape(3, 3)
        return self.data.site_xpos[self._site].copy(), float(np.arctan2(xmat[1, 0], xmat[0, 0]))

    def poses(self, qpos: np.ndarray, start: tuple[np.ndarray, float]) -> tuple[np.ndarray, np.ndarray]:
        """Capsule centres (links, 3) m and orientations (links, 4) wxyz in the start frame ``start``
        (``start_frame``'s output), both float32, head first."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        p0, yaw0 = start
        c, s = np.cos(-yaw0), np.sin(-yaw0)
        undo = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # R_z(-yaw0)
        pos = (self.data.geom_xpos[self._geoms] - [p0[0], p0[1], 0.0]) @ undo.T  # (links, 3)
        mats = undo @ self.data.geom_xmat[self._geoms].reshape(-1, 3, 3)  # (links, 3, 3)
        quats = np.empty((len(self._geoms), 4))
        for i, mat in enumerate(mats):
            mujoco.mju_mat2Quat(quats[i], mat.ravel())
        return pos.astype(np.float32), quats.astype(np.float32)
