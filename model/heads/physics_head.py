"""The path a member takes on another robot: the member path head conditioned on the physics.

The member path head (``model.heads.member_path``) predicts the path of a member on the robot the
checkpoint was trained on. A user's robot differs (friction, servos, masses, slope:
``sim.robot.variations``), and the designer shows that as the Variations fan, replayed. This head
predicts it: the same MLP, fed the member's inputs and a robot's physics relative to the
checkpoint's (``physics_features``), trained on replays of the sampler's members (z_k = 0 and
sampled, as the designer decodes) on the nominal robot, on every variation of the default set and
on ``sampled`` combined variations per member (``sim.robot.variations.sampled_set``): physics labels
it, as it does the member head. It is stored beside a checkpoint's weights
(``PHYSICS_HEAD_WEIGHTS`` and ``PHYSICS_HEAD_CONFIG``: the head's config, the features and what it
scored) without changing them. It is fitted by ``model.heads.physics_fit``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from safetensors.torch import save_file

from snakeloco.model.heads.member_path import MemberHeadConfig, MemberPathHead, ResidualHead
from snakeloco.sim.robot.description import Robot

PHYSICS_HEAD_WEIGHTS = "physics_head.safetensors"
PHYSICS_HEAD_CONFIG = "physics_head.json"

LOG_FIELDS = ("friction_along", "friction_across", "link_mass", "servo_kp", "servo_kv", "joint_damping")
"""Physical fields fed as the log of their ratio to the checkpoint robot's."""
PHYSICS_FEATURES = (*LOG_FIELDS, "latency", "slope_ahead", "slope_left")
"""The head's physics inputs: log ratios, the command latency (s), and the slope (deg) split into
its rise along the snake's initial heading and to its left (a mirror image negates the last)."""


def physics_features(robots: list[Robot], nominal: Robot) -> np.ndarray:
    """Robots -> their physics relative to ``nominal`` (N, ``len(PHYSICS_FEATURES)``): zeros for the
    nominal robot itself."""
    rows = []
    for r in robots:
        logs = [math.log(getattr(r, f) / getattr(nominal, f)) for f in LOG_FIELDS]
        a = math.radians(r.slope_direction_deg)
        rows.append(
            [*logs, r.latency - nominal.latency, r.slope_deg * math.cos(a), r.slope_deg * math.sin(a)]
        )
    return np.array(rows, np.float64).reshape(len(robots), len(PHYSICS_FEATURES))


def mirror_features(features: np.ndarray) -> np.ndarray:
    """The physics of a mirror image (y -> -y): the slope's rise to the left negated."""
    out = np.array(features, np.float64, copy=True)
    out[..., PHYSICS_FEATURES.index("slope_left")] *= -1
    return out


def save_physics_head(directory: str | Path, head: MemberPathHead | ResidualHead) -> None:
    """Write the head's weights and config beside a checkpoint's (atomically, each file)."""
    directory = Path(directory)
    own = head.delta if isinstance(head, ResidualHead) else head  # a residual head's base is the member head
    state = {k: v.detach().cpu().contiguous() for k, v in own.state_dict().items()}
    tmp = directory / (PHYSICS_HEAD_WEIGHTS + ".tmp")
    save_file(state, str(tmp))
    tmp.replace(directory / PHYSICS_HEAD_WEIGHTS)
    tmp = directory / (PHYSICS_HEAD_CONFIG + ".tmp")
    tmp.write_text(head.cfg.model_dump_json(indent=1))
    tmp.replace(directory / PHYSICS_HEAD_CONFIG)


def load_physics_head(
    directory: str | Path, base: MemberPathHead | None = None
) -> MemberPathHead | ResidualHead | None:
    """The physics head stored beside a checkpoint (None where it has none; a residual one on the
    checkpoint's member head ``base``); a CheckpointError where its files are corrupt or disagree."""
    from snakeloco.model.checkpoint import CheckpointError, load_head_weights

    directory = Path(directory)
    if not (directory / PHYSICS_HEAD_CONFIG).is_file():
        return None
    try:
        cfg = MemberHeadConfig.model_validate_json((directory / PHYSICS_HEAD_CONFIG).read_text())
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {directory}: corrupt {PHYSICS_HEAD_CONFIG} ({exc})") from exc
    if tuple(cfg.physics) != PHYSICS_FEATURES:
        raise CheckpointError(
            f"checkpoint {directory}: {PHYSICS_HEAD_CONFIG} reads physics {cfg.physics}, this version "
            f"{list(PHYSICS_FEATURES)}; fit it again (calibrate --physics-head)"
        )
    own = load_head_weights(directory, PHYSICS_HEAD_WEIGHTS, MemberPathHead(cfg))
    if not cfg.residual:
        return own
    if base is None:
        raise CheckpointError(f"checkpoint {directory}: its physics head corrects a member head it has not")
    return ResidualHead(base, own).eval()


class OnRobot:
    """A ``GaitModel`` whose decoded paths are its physics head's prediction on ``robot`` (a fitted
    robot, say, that ``GaitModel.members.covers``): what inverse design searches on for that robot. Every
    other attribute is the model's own."""

    def __init__(self, model, robot: Robot) -> None:
        if not model.projects or not model.members.covers(robot):
            raise ValueError(f"the checkpoint's physics head does not cover {robot.name}")
        self._model, self.on = model, robot
        self._features = physics_features([robot], model.robot)

    def __getattr__(self, name: str):
        return getattr(self._model, name)

    def decode(self, z_b: np.ndarray, z_j: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The members' shapes (B, J, L, 2) and their paths on ``self.on`` (B, 500, 6)."""
        members, _, shape, _, _ = self._model.decode_members(z_b, z_j, with_stats=False)
        return shape, self._model.members.predict_physics_paths(
            members, np.repeat(self._features, len(members), 0)
        )
