"""The structured family's members, as a part ``GaitModel`` holds (``GaitModel.members``): decoded
shapes projected onto exact members, the shapes the servos measure for members, and the paths the
member path head (``model.heads.member_path``) and the physics head predict for them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import torch

from snakeloco.model.heads.member_path import MemberPathHead, member_inputs
from snakeloco.model.heads.physics_head import physics_features
from snakeloco.model.vae.tracing import Graphs
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.gaits.projection import project_many


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` unchanged; a ValueError naming ``name`` if it holds NaN or inf (they would decode to NaN
    joint commands that no simulator can replay)."""
    if not np.isfinite(a).all():
        raise ValueError(f"{name} holds {int((~np.isfinite(a)).sum())} non-finite values (NaN or inf)")
    return a


class MemberHeads:
    """A checkpoint's members and path heads: built by ``GaitModel`` from its config, with the model's
    lock and traced graphs (calls are serialised with the network's), its body normalisation (mean,
    std) and its shape check."""

    def __init__(
        self,
        config,
        robot,
        heads: tuple[MemberPathHead | None, MemberPathHead | None],
        body_norm: tuple[np.ndarray, np.ndarray],
        check_shape: Callable[[np.ndarray], np.ndarray],
        lock: threading.Lock,
        graphs: Graphs,
    ) -> None:
        self.family = config.members
        """The structured family's members the decodes project onto (None: the checkpoint has none)."""
        self.head_config, self.robot = config.member_head, robot
        self.member_head, self.physics_head = heads
        """The member path head and the physics head (``model.heads.physics_head``), where fitted."""
        g = config.servo_response  # (n_joints, L, 2): the servos' measured / commanded coefficient
        self._gain = None if g is None else np.asarray(g, np.float64) @ np.array([1.0, 1j])
        self._body_mean, self._body_std = body_norm
        self._check_shape, self._lock, self._graphs = check_shape, lock, graphs

    def project(self, shape: np.ndarray) -> tuple[list[Member], np.ndarray]:
        """Measured joint shapes (B, n_joints, L, 2) -> the members they project onto (their commanded
        coefficients fitted, ``sim.gaits.projection.project``) and the fits' relative residuals (B,)."""
        if self.family is None:
            raise ValueError("this checkpoint's family has no members to project onto")
        shape = self._check_shape(shape)
        c = shape[..., 0] + 1j * shape[..., 1]
        if self._gain is not None:
            c = c / self._gain
        return project_many(np.stack([c.real, c.imag], axis=-1), self.family, self.robot)

    def member_shapes(self, members: list[Member]) -> np.ndarray:
        """The joint shapes (B, n_joints, L, 2) the servos measure for members (commanded x servo gain)."""
        c = np.stack([m.shape(self.robot) for m in members])
        c = c[..., 0] + 1j * c[..., 1]
        if self._gain is not None:
            c = c * self._gain
        return np.stack([c.real, c.imag], axis=-1)

    def predict_paths(self, members: list[Member], z_b: np.ndarray | None = None) -> np.ndarray:
        """The body series (B, 500, 6) the member path head predicts for members (physical units);
        ``z_b`` (B, Db): the slider positions they were decoded from, for a head that reads them."""
        if self.member_head is None:
            raise ValueError("this checkpoint has no member path head")
        head_cfg = self.head_config
        if head_cfg.z_b_dim and (z_b is None or np.shape(z_b) != (len(members), head_cfg.z_b_dim)):
            raise ValueError(
                f"this checkpoint's member path head reads each member's z_B: pass z_b of shape "
                f"({len(members)}, {head_cfg.z_b_dim})"
            )
        x = member_inputs(
            members,
            np.asarray(head_cfg.support),
            z_b if head_cfg.z_b_dim else None,
            head_cfg.inputs,
            self.robot,
        )
        x = torch.as_tensor(_finite("z_b", x), dtype=torch.float32)
        head = self._graphs.one_input("member_head", self.member_head, "forward", x) if len(x) == 1 else None
        with self._lock, torch.inference_mode():
            body = (head or self.member_head)(x).numpy().astype(np.float64)
        return body * self._body_std + self._body_mean

    def predict_physics_paths(self, members: list[Member], features: np.ndarray) -> np.ndarray:
        """The body series (B, 500, 6) the physics head predicts for members on robots of physics
        ``features`` (B, F) (``model.heads.physics_head.physics_features``, relative to ``self.robot``)."""
        if self.physics_head is None:
            raise ValueError("this checkpoint has no physics head (calibrate --physics-head fits one)")
        head_cfg = self.physics_head.cfg
        features = np.asarray(features, np.float64).reshape(len(members), -1)
        if features.shape[1] != len(head_cfg.physics):
            raise ValueError(
                f"expected {len(head_cfg.physics)} physics features per member, got {features.shape[1]}"
            )
        x = member_inputs(members, np.asarray(head_cfg.support), None, head_cfg.inputs, self.robot)
        x = torch.as_tensor(
            _finite("physics features", np.concatenate([x, features], axis=1)), dtype=torch.float32
        )
        with self._lock, torch.inference_mode():
            body = self.physics_head(x).numpy().astype(np.float64)
        return body * self._body_std + self._body_mean

    def covers(self, robot) -> bool:
        """Whether the physics head predicts paths on ``robot`` (a ``sim.robot.description.Robot`` of this
        checkpoint's geometry): every physics feature within the range it was trained on."""
        if self.physics_head is None or robot.n_joints != self.robot.n_joints:
            return False
        span = self.physics_head.cfg.summary.get("feature_range")
        if span is None:
            return False
        f = physics_features([robot], self.robot)[0]
        return bool(
            np.all(f >= np.asarray(span["low"]) - 1e-9) and np.all(f <= np.asarray(span["high"]) + 1e-9)
        )

    def predict_variation_paths(self, member: Member, robots: list) -> np.ndarray:
        """The body series (V, 500, 6) the physics head predicts for one member on each of ``robots``
        (``sim.robot.description.Robot``, of this checkpoint's geometry)."""
        return self.predict_physics_paths([member] * len(robots), physics_features(robots, self.robot))
