"""Checkpoints: ``model.safetensors`` (weights) + ``config.json`` (pydantic-validated). No pickle.

``config.json`` holds the schema version, the model config, the normalisation statistics, the
dataset's excited frequencies and meta hash, the MJCF hash, the training config and a summary of
the run. Loading validates all of it and names the problem when something is off.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from snakeloco.model.heads.density import LatentDensity
from snakeloco.model.heads.member_path import MEMBER_HEAD_WEIGHTS, MemberHeadConfig, MemberPathHead
from snakeloco.model.vae.config import ModelConfig
from snakeloco.model.vae.network import HierarchicalVAE
from snakeloco.sim.gaits.structured import StructuredConfig
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.world.description import World

SCHEMA_VERSION = 4
"""2: the body-statistics head (signal CNN, MLP, inverse-transform buffers) and its normalisation.
3: the body decoder may see the gait's predicted statistics (``ModelConfig.body_sees_stats``).
4: the slider density over z_B (``density``), the structured family decodes are projected onto
(``members``) and the member path head (``member_head``, weights in ``MEMBER_HEAD_WEIGHTS``)."""
READABLE_VERSIONS = (2, 3, 4)
"""Schema versions this code loads; a version-2 config is read with ``body_sees_stats`` off, as
its decoder was built; versions 2-3 have no density, members or member head."""
WEIGHTS = "model.safetensors"
CONFIG = "config.json"
PRETRAINED_DIR = Path(__file__).with_name("pretrained")
"""The shipped checkpoint of the paper family, trained on its 4096-record dataset (docs/model.md: how
to reproduce it)."""
STRUCTURED_DIR = Path(__file__).with_name("pretrained_structured")
"""The shipped checkpoint of the structured family: its undulation preset (``snakeloco generate
--structured-preset undulate``), 512 records, the family whose decoded gaits inverse design lands in
MuJoCo (docs/design.md; docs/model.md: how to reproduce it, and why it is not the 4096-record mixed
family the design contract asks for)."""
SHIPPED: dict[str, Path] = {"structured": STRUCTURED_DIR, "paper": PRETRAINED_DIR}
"""Shipped checkpoints by gait family: ``--checkpoint NAME`` and ``load_pretrained(NAME)`` take these
names as well as a directory."""
DEFAULT_FAMILY = "structured"
"""The checkpoint a command uses when none is named: the family whose promise holds (its slider gaits
replay as drawn; docs/evaluation.md, and docs/load.md "DEFAULT_FAMILY" for why it changed)."""


def resolve_checkpoint(directory: str | Path | None) -> Path:
    """The checkpoint directory meant by ``directory``: None is the default family's, a shipped
    family's name is its checkpoint (unless a directory of that name exists here), a build's folder
    (``snakeloco build --out runs/NAME``: its ``build.json`` and ``model/``) its model, anything
    else a path."""
    if directory is None:
        return SHIPPED[DEFAULT_FAMILY]
    if str(directory) in SHIPPED and not Path(directory).is_dir():
        return SHIPPED[str(directory)]
    path = Path(directory)
    if (path / "build.json").is_file() and (path / "model").is_dir():  # ``app.cli.build``'s folder
        return path / "model"
    return path


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt or does not match this code; the message says which."""


SHAPE_STD_FLOOR = 0.05
"""A bin's shape std is at least this fraction of the largest: a bin the data barely excite (the
structured family's gaits use 1-3 of the 8 bins; the others hold 1e-4 rad of harmonics) is not
blown up to unit scale, where the reconstruction loss would chase its noise. Paper-family bins are
within 0.9x of each other, so the floor never acts there."""


class Normalization(BaseModel):
    """Per-feature statistics: normalised = (physical - mean) / std."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    shape_mean: list[list[float]] = Field(description="(L, 2) rad")
    shape_std: list[list[float]] = Field(description="(L, 2) rad")
    body_mean: list[float] = Field(description="(6,) m and rad")
    body_std: list[float] = Field(description="(6,) m and rad")
    stats_mean: list[float] = Field(description="(4,) body statistics vector (model/vae/stats.py)")
    stats_std: list[float] = Field(description="(4,) body statistics vector (model/vae/stats.py)")

    @model_validator(mode="after")
    def _positive(self) -> Normalization:
        if min(min(r) for r in self.shape_std) <= 0 or min(self.body_std) <= 0 or min(self.stats_std) <= 0:
            raise ValueError("normalisation std must be positive")
        return self

    @classmethod
    def fit(cls, shape: np.ndarray, body: np.ndarray, stats: np.ndarray) -> Normalization:
        """Statistics of a training set: shape (N, K, L, 2), body (N, T, 6), body statistics (N, 4)."""
        return cls(
            stats_mean=stats.mean(axis=0).tolist(),
            stats_std=np.maximum(stats.std(axis=0), 1e-6).tolist(),
            shape_mean=shape.mean(axis=(0, 1)).tolist(),
            shape_std=np.maximum(
                std := shape.std(axis=(0, 1)), max(SHAPE_STD_FLOOR * std.max(), 1e-6)
            ).tolist(),
            body_mean=body.mean(axis=(0, 1)).tolist(),
            body_std=np.maximum(body.std(axis=(0, 1)), 1e-6).tolist(),
        )

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v, dtype=np.float32) for k, v in self.model_dump().items()}


class TrainSummary(BaseModel):
    """What the run that made the checkpoint did."""

    model_config = ConfigDict(extra="allow")

    best_epoch: int = -1
    epochs_run: int = 0
    best_val_loss: float = float("nan")
    wall_time_s: float = 0.0
    device: str = "cpu"


class CheckpointConfig(BaseModel):
    """Contents of ``config.json``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: int
    model: ModelConfig
    normalization: Normalization
    freqs: list[float] = Field(description="(L,) excited frequencies of the training data (Hz)")
    dataset_meta_sha256: str
    family: Literal["paper", "structured"] = Field(
        "paper", description="Gait family of the training data (checkpoints from before families: paper)."
    )
    servo_response: list[list[list[float]]] | None = Field(
        None,
        description="(n_joints, L, 2) mean measured/commanded complex gain of each joint at each frequency in "
        "the training data; decoded shapes (measured angles) are divided by it to get commands.",
    )
    shape_support: list[list[bool]] | None = Field(
        None,
        description="(n_joints, L) which joint-frequency coefficients the training data excites (RMS amplitude "
        "above SUPPORT_FRACTION of the largest); a decoded coefficient outside it is set to zero, so a "
        "decoded gait keeps still what its family keeps still. None (older checkpoints): all of them.",
    )
    density: LatentDensity | None = Field(
        None,
        description="Gaussian mixture over the training records' posterior z_B: the sliders, Random and "
        "generated gaits draw from it, and a z_B it finds unlikely is flagged (``model.heads.density``). None: "
        "the N(0, I) prior.",
    )
    members: StructuredConfig | None = Field(
        None,
        description="The structured family every decoded shape is projected onto (``sim.gaits.members``): "
        "the commands replayed, drawn and exported are exactly one member. None: decodes as they are.",
    )
    member_head: MemberHeadConfig | None = Field(
        None,
        description="The member path head (``model.heads.member_path``): the decoded path is its prediction "
        "for the projected member. Needs ``members``.",
    )
    robot: Robot | None = Field(
        None,
        description="The robot description the training data was simulated on (``sim.robot.description``); None "
        "(checkpoints of the paper's robot before robots were data): the default robot, sim/snake.xml.",
    )
    world: World | None = Field(
        None,
        description="The ground the training data was simulated on (``sim.world``); None: the flat plane.",
    )
    mjcf_sha256: str = Field(description="Hash of that robot's MJCF (``Robot.mjcf_sha256``).")
    train: dict = Field(default_factory=dict, description="The resolved training config.")
    summary: TrainSummary = TrainSummary()

    @model_validator(mode="after")
    def _consistent(self) -> CheckpointConfig:
        n_l = self.model.n_components
        if len(self.freqs) != n_l:
            raise ValueError(f"{len(self.freqs)} freqs for a model with {n_l} components")
        if np.asarray(self.normalization.shape_mean).shape != (n_l, 2):
            raise ValueError("shape_mean is not (L, 2)")
        if len(self.normalization.body_mean) != self.model.body_channels:
            raise ValueError("body_mean does not match body_channels")
        if self.shape_support is not None:
            support = np.asarray(self.shape_support)
            if support.shape != (self.model.n_joints, n_l) or not support.any():
                raise ValueError(
                    f"shape_support must be ({self.model.n_joints}, {n_l}) with a coefficient in it"
                )
        if self.robot is not None and self.robot.n_joints != self.model.n_joints:
            raise ValueError(
                f"a model of {self.model.n_joints} joints for a robot of {self.robot.n_joints} ({self.robot.name})"
            )
        if self.member_head is not None and self.members is None:
            raise ValueError("member_head needs the family it predicts members of (members)")
        if self.density is not None and self.density.dim != self.model.z_b_dim:
            raise ValueError(f"density over {self.density.dim} dimensions for a z_B of {self.model.z_b_dim}")
        if self.servo_response is not None:
            g = np.asarray(self.servo_response, dtype=np.float64)
            if g.shape != (self.model.n_joints, n_l, 2) or not np.isfinite(g).all():
                raise ValueError(f"servo_response must be finite ({self.model.n_joints}, {n_l}, 2)")
            if np.hypot(g[..., 0], g[..., 1]).min() < 0.2:
                raise ValueError("servo_response has a gain below 0.2: not a servo this model can invert")
        return self


def check_trained_on(config: CheckpointConfig, ds, data: str | Path) -> None:
    """A DatasetError unless the dataset ``ds`` (read from ``data``) is the one the checkpoint with
    ``config`` was trained on (its meta hash)."""
    from snakeloco.sim import DatasetError

    if ds.meta_hash != config.dataset_meta_sha256:
        raise DatasetError(
            f"{data} is not the dataset this checkpoint was trained on (meta hash {ds.meta_hash[:12]}, "
            f"checkpoint {config.dataset_meta_sha256[:12]})"
        )


def save_checkpoint(
    directory: str | Path,
    net: HierarchicalVAE,
    config: CheckpointConfig,
    member_head: MemberPathHead | None = None,
) -> Path:
    """Write weights and config to ``directory`` (created if needed); returns the directory.
    ``member_head``: its weights go to ``MEMBER_HEAD_WEIGHTS`` (the config must describe it)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if (member_head is None) != (config.member_head is None):
        raise ValueError("a member head's weights and its config go together")
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    tmp_w, tmp_c = directory / (WEIGHTS + ".tmp"), directory / (CONFIG + ".tmp")
    save_file(state, str(tmp_w), metadata={"schema_version": str(SCHEMA_VERSION)})
    if member_head is not None:
        head_state = {k: v.detach().cpu().contiguous() for k, v in member_head.state_dict().items()}
        tmp_h = directory / (MEMBER_HEAD_WEIGHTS + ".tmp")
        save_file(head_state, str(tmp_h))
        tmp_h.replace(directory / MEMBER_HEAD_WEIGHTS)
    else:
        (directory / MEMBER_HEAD_WEIGHTS).unlink(missing_ok=True)
    # Written as this code's schema: the model config spells out every field, older ones included.
    config = config.model_copy(update={"schema_version": SCHEMA_VERSION})
    tmp_c.write_text(json.dumps(config.model_dump(mode="json"), indent=2))
    tmp_w.replace(directory / WEIGHTS)
    tmp_c.replace(directory / CONFIG)
    return directory


def load_checkpoint(directory: str | Path | None = None) -> tuple[HierarchicalVAE, CheckpointConfig]:
    """Load and validate a checkpoint directory, or a shipped one by family name (``resolve_checkpoint``;
    None: the default family's).

    Raises:
        CheckpointError: missing files, invalid or mismatched config, wrong schema version, corrupt or
            mismatched weights.
    """
    directory = resolve_checkpoint(directory)
    cfg_path, w_path = directory / CONFIG, directory / WEIGHTS
    for p in (cfg_path, w_path):
        if not p.is_file():
            hint = (
                ""
                if directory.is_dir()
                else f" (no such directory; shipped checkpoints: {', '.join(SHIPPED)})"
            )
            raise CheckpointError(f"checkpoint {directory}: missing {p.name}{hint}")
    try:
        raw = json.loads(cfg_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"checkpoint {directory}: {CONFIG} is not valid JSON ({exc})") from exc
    version = raw.get("schema_version") if isinstance(raw, dict) else None
    if version not in READABLE_VERSIONS:
        readable = " or ".join(map(str, READABLE_VERSIONS))
        raise CheckpointError(
            f"checkpoint {directory}: schema version {version!r}, this snakeloco reads {readable}"
        )
    if version == 2 and isinstance(raw.get("model"), dict):
        raw["model"].setdefault("body_sees_stats", False)
    try:
        config = CheckpointConfig.model_validate(raw)
    except ValidationError as exc:
        raise CheckpointError(f"checkpoint {directory}: invalid {CONFIG}: {exc}") from exc
    state = _read_weights(directory, WEIGHTS)
    net = HierarchicalVAE(config.model)
    expected = net.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(k for k in set(expected) & set(state) if expected[k].shape != state[k].shape)
    if missing or unexpected or wrong:
        raise CheckpointError(
            f"checkpoint {directory}: weights do not match its config "
            f"(missing {missing[:5]}, unexpected {unexpected[:5]}, wrong shape {wrong[:5]})"
        )
    if any(not torch.isfinite(v).all() for v in state.values() if v.is_floating_point()):
        raise CheckpointError(f"checkpoint {directory}: weights contain NaN or Inf")
    net.load_state_dict(state)
    if not bool(net.signal_ready):
        raise CheckpointError(
            f"checkpoint {directory}: the statistics head's signal branch was never initialised"
        )
    net.eval()
    return net, config


def _read_weights(directory: Path, name: str) -> dict[str, torch.Tensor]:
    """The tensors of a checkpoint's safetensors file ``name``; a CheckpointError if it is corrupt."""
    try:
        return load_file(str(directory / name))
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"checkpoint {directory}: corrupt {name} ({exc})") from exc


def load_member_head(directory: str | Path, config: CheckpointConfig) -> MemberPathHead | None:
    """The member path head a checkpoint's config describes (None where it has none).

    Raises:
        CheckpointError: its weights are missing, corrupt, of another shape or not finite.
    """
    if config.member_head is None:
        return None
    directory = resolve_checkpoint(directory)
    path = directory / MEMBER_HEAD_WEIGHTS
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {directory}: missing {MEMBER_HEAD_WEIGHTS} (its config has a member head)"
        )
    return load_head_weights(directory, MEMBER_HEAD_WEIGHTS, MemberPathHead(config.member_head))


def load_head_weights(directory: Path, name: str, head: torch.nn.Module) -> torch.nn.Module:
    """``head`` with the weights of the checkpoint's file ``name``, frozen, in eval mode; a
    CheckpointError if the file is corrupt, of another shape than ``head`` or not finite."""
    state = _read_weights(directory, name)
    expected = head.state_dict()
    if set(state) != set(expected) or any(state[k].shape != expected[k].shape for k in expected):
        raise CheckpointError(f"checkpoint {directory}: {name} does not match its config")
    if any(not torch.isfinite(v).all() for v in state.values()):
        raise CheckpointError(f"checkpoint {directory}: {name} contains NaN or Inf")
    head.load_state_dict(state)
    return head.requires_grad_(False).eval()
