"""The slider density and the structured family's members, as a part of ``GaitModel``: slider
positions drawn from the shipped sampler, decoded shapes projected onto exact members, and the
paths the member path head predicts for them (``model.heads.member_path``).

``MemberDecoding`` is a mixin: it uses the ``GaitModel`` it is part of (config, servo gain, traced
graphs, lock, decoders).
"""

from __future__ import annotations

import numpy as np
import torch

from snakeloco.model.heads.member_path import member_inputs
from snakeloco.model.heads.physics_head import physics_features
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.gaits.projection import project_many


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` unchanged; a ValueError naming ``name`` if it holds NaN or inf (they would decode to NaN
    joint commands that no simulator can replay)."""
    if not np.isfinite(a).all():
        raise ValueError(f"{name} holds {int((~np.isfinite(a)).sum())} non-finite values (NaN or inf)")
    return a


class MemberDecoding:
    """``GaitModel``'s slider density and member decoding."""

    @property
    def projects(self) -> bool:
        """Whether decodes are projected onto exact members of the structured family."""
        return self.config.members is not None

    def sample_z_b(self, n: int, seed: int = 0, component: int | None = None) -> np.ndarray:
        """n slider positions (n, Db) from the shipped sampler: the density over the training
        records' posterior z_B (``model.heads.density``; one ``component`` of it, or all), deterministic in
        ``seed``. A checkpoint without a density draws from the N(0, I) prior."""
        if self.config.density is None:
            if component is not None:
                raise ValueError("this checkpoint has no density, so no components to draw from")
            return np.random.default_rng(seed).standard_normal((n, self.z_b_dim))
        return self.config.density.sample(n, seed, component)[0]

    def off_data(self, z_b: np.ndarray) -> np.ndarray:
        """Whether each z_B (B, Db) lies off the data (less dense than 99% of the training records'
        posteriors): (B,) bool. All False without a density."""
        z = self._check_z_b(z_b).astype(np.float64)
        if self.config.density is None:
            return np.zeros(len(z), bool)
        return self.config.density.off_data(z)

    def _gain(self) -> np.ndarray | None:
        g = self._servo_response
        return None if g is None else g[..., 0] + 1j * g[..., 1]  # (n_joints, L)

    def project(self, shape: np.ndarray) -> tuple[list[Member], np.ndarray]:
        """Measured joint shapes (B, n_joints, L, 2) -> the members they project onto (their commanded
        coefficients fitted, ``sim.gaits.projection.project``) and the fits' relative residuals (B,)."""
        if not self.projects:
            raise ValueError("this checkpoint's family has no members to project onto")
        shape = self._check_shape(shape)
        c = shape[..., 0] + 1j * shape[..., 1]
        if (g := self._gain()) is not None:
            c = c / g
        return project_many(np.stack([c.real, c.imag], axis=-1), self.config.members, self.robot)

    def member_shapes(self, members: list[Member]) -> np.ndarray:
        """The joint shapes (B, n_joints, L, 2) the servos measure for members (commanded x servo gain)."""
        c = np.stack([m.shape(self.robot) for m in members])
        c = c[..., 0] + 1j * c[..., 1]
        if (g := self._gain()) is not None:
            c = c * g
        return np.stack([c.real, c.imag], axis=-1)

    def predict_paths(self, members: list[Member], z_b: np.ndarray | None = None) -> np.ndarray:
        """The body series (B, 500, 6) the member path head predicts for members (physical units);
        ``z_b`` (B, Db): the slider positions they were decoded from, for a head that reads them."""
        if self.member_head is None:
            raise ValueError("this checkpoint has no member path head")
        head_cfg = self.config.member_head
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

    def decode_members(
        self, z_b: np.ndarray, z_j: np.ndarray | None = None, with_stats: bool = True
    ) -> tuple[list[Member], np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray] | None]:
        """Decode, project and predict: the members (B), the projections' residuals (B,), the
        members' measured shapes (B, n_joints, L, 2), the paths predicted for them (B, 500, 6) (the
        network's own body decode where the checkpoint has no member head) and the statistics the
        model predicts for the members' shapes {name: (B,)} (``predict_stats``; None without
        ``with_stats``, which saves half a batch's time where only paths count: inverse design)."""
        if self.member_head is None:
            shape, body, stats = self.decode_raw(z_b, z_j, with_stats=True)
            members, residuals = self.project(shape)
            return members, residuals, self.member_shapes(members), body, stats if with_stats else None
        # The network's own path and statistics would be thrown away: its joint decoder alone.
        members, residuals = self.project(self.decode_shape(z_b, z_j))
        # The statistics head judges the member's own shape: the predicted path's 5 Hz steps carry the
        # head's small ripple, which a path length summed over 500 steps would count 3x over.
        measured = self.member_shapes(members)
        stats = self.predict_stats(measured) if with_stats else None
        return (
            members,
            residuals,
            measured,
            self.predict_paths(members, np.reshape(z_b, (len(members), -1))),
            stats,
        )
