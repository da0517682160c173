"""The model's command-line configs (training, calibration, the sampler, the consistency check),
apart from the code that runs them: importing this module imports neither torch nor MuJoCo, so the
command line builds its parser and answers ``--help`` without them. Each config's own module
re-exports it."""

from __future__ import annotations

from typing import Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.model.vae.config import ModelConfig
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE


class TrainConfig(BaseModel):
    """Optimisation settings (the model's own are in ``ModelConfig``)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    epochs: int = Field(300, ge=1, description="Training epochs (the shipped model: 140, preset paper).")
    batch_size: int = Field(
        128, ge=2, description="Records per step (the MMD and batch statistics need two)."
    )
    lr_min: float = Field(2e-4, gt=0, description="Floor of the cyclical learning rate (paper).")
    lr_max: float = Field(4e-3, gt=0, description="First peak of the cyclical learning rate (paper).")
    cycle_epochs: float = Field(
        50.0,
        gt=0,
        description="Period of the triangular learning-rate cycle (epochs); the paper's 800 scaled to a "
        "140-epoch CPU run.",
    )
    peak_decay: float = Field(0.5, gt=0, le=1, description="Peak multiplier per completed cycle.")
    val_fraction: float = Field(0.1, gt=0, lt=1, description="Share of records held out for validation.")
    seed: int = Field(0, ge=0, description="Seed of the split, initialisation and batches.")
    device: Literal["cpu", "cuda"] = Field("cpu", description="Torch device; cuda only where present.")
    grad_clip: float = Field(10.0, gt=0, description="Gradient-norm clip.")


class TrainPreset(NamedTuple):
    """A named training recipe: the settings that made a shipped checkpoint."""

    train: TrainConfig
    model: ModelConfig


PRESETS: dict[str, TrainPreset] = {
    "paper": TrainPreset(TrainConfig(epochs=140), ModelConfig()),
    "structured": TrainPreset(
        TrainConfig(epochs=200, cycle_epochs=50.0),
        ModelConfig(
            z_b_dim=8, body_sees_signals=True, body_signals_see_latent=True, encoder_sees_signals=True
        ),
    ),
}
"""``snakeloco train --preset NAME`` starts from these (any option still overrides them). ``paper``:
the shipped checkpoint of the paper family (``model/pretrained``), 140 epochs on the 4096-record
dataset (docs/model.md). ``structured``: the structured family's recipe, chosen on its first 1744
records (docs/structured-notes.md: z_B of 8, the body decoder and encoder both seeing the joint
signals, 200 epochs in cycles of 50)."""


MODES: dict[str, float | None] = {"zk_zero": None, "zk_t0.5": 0.5, "zk_t1": 1.0}
"""z_k modes of the calibration gaits, name -> sampling temperature (None: z_k = 0), as
``GaitModel.joint_latents`` takes it."""
ZERO_MODE = list(MODES.values()).index(None)
"""Index of the z_k = 0 mode (the ``mode`` array of the replayed gaits)."""
SAMPLED_MODES = [m for m, t in enumerate(MODES.values()) if t is not None]
"""Indices of the sampled-z_k modes."""


class CalibrateConfig(BaseModel):
    """What a calibration replays and how it fine-tunes (defaults: the shipped calibration)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    prior_samples: int = Field(
        512,
        ge=1,
        description="z_B drawn from the prior, each decoded with z_k = 0 and sampled at T 0.5 and 1.",
    )
    zero_samples: int | None = Field(
        None,
        ge=0,
        description="Further z_B decoded with z_k = 0 only (default: 4 x --prior-samples); seed + 1000. "
        "With z_k = 0 whether a gait hops is a property of z_B that the head learns from many "
        "neighbouring draws.",
    )
    sampled_samples: int | None = Field(
        None,
        ge=0,
        description="Further z_B decoded with z_k sampled at each temperature (default: 2 x "
        "--prior-samples); seed + 2000. The head's sampled net-roll error fell with each doubling.",
    )
    epochs: int = Field(40, ge=1, description="Fine-tuning epochs of each stage.")
    lr: float = Field(1e-2, gt=0, description="Peak learning rate of both stages (Adam, cosine to 1%).")
    batch_size: int = Field(128, ge=2, description="Examples per step.")
    seed: int = Field(1000, ge=0, description="Seed of the z_B draws (evaluate draws with seed 0).")
    val_fraction: float = Field(0.1, gt=0, lt=1, description="Share of z_B draws held out.")

    @property
    def zero_count(self) -> int:
        """Extra z_k = 0 draws: ``zero_samples``, or 4 x ``prior_samples``."""
        return 4 * self.prior_samples if self.zero_samples is None else self.zero_samples

    @property
    def sampled_count(self) -> int:
        """Extra sampled draws (each decoded in every sampled mode): ``sampled_samples``, or 2 x."""
        return 2 * self.prior_samples if self.sampled_samples is None else self.sampled_samples

    @property
    def gait_count(self) -> int:
        """Gaits a calibration replays (before broken ones are dropped)."""
        return self.prior_samples * len(MODES) + self.zero_count + self.sampled_count * len(SAMPLED_MODES)


HeadInputs = Literal["coefficients", "named", "named_curve"]
"""What describes a member to the head (``member_inputs``); "named_curve": the named parameters and
the curving wave's (``Member.curve``)."""
HeadPath = Literal["direct", "heading"]
"""How the head draws the path in the plane: "direct", forward and sideways positions as outputs;
"heading", velocities in the body's own frame, turned by the predicted heading and summed (dead
reckoning), so a turn in place ends where its predicted yaw takes it round its circle."""


class SamplerConfig(BaseModel):
    """What ``calibrate --sampler`` fits (defaults: the shipped structured checkpoint's)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    density_only: bool = Field(
        False, description="Fit and store the slider density only (no replays; the paper family)."
    )
    regenerated: bool = Field(
        False,
        description="The dataset is the checkpoint's training set generated again (the same family, seed "
        "and config; records are deterministic in seed and index), possibly only its first N records or "
        "under another MuJoCo version, so its meta hash differs: the records of the training split are "
        "used. For a training set not at hand or too large to regenerate whole.",
    )
    max_components: int = Field(6, ge=1, description="Most mixture components tried (chosen by BIC).")
    samples: int = Field(
        256,
        ge=0,
        description="Sampler z_B decoded with z_k = 0 and with z_k sampled (T = 1), each member replayed "
        "once: the member path head's labels beside the records.",
    )
    seed: int = Field(
        3000,
        ge=0,
        description="Seed of those draws (evaluate uses 0, calibrate 1000, the designer's Random none).",
    )
    epochs: int = Field(400, ge=1, description="Epochs of the member path head.")
    lr: float = Field(2e-3, gt=0, description="Peak learning rate of the head (Adam, cosine to 1%).")
    hidden: int = Field(
        128, ge=8, description="Width of the head's hidden layers (docs/model.md: 128 over 256)."
    )
    head_sees_z_b: bool = Field(
        False,
        description="The head also reads the member's z_B (a record's posterior, a sampler gait's draw). "
        "Off for the shipped checkpoint: its path is then the member's alone (docs/model.md).",
    )
    head_inputs: HeadInputs = Field(
        "coefficients",
        description="What describes a member to the head: its coefficients (the shipped undulation "
        "checkpoint) or its named parameters (kind, amplitudes, wavenumbers, phases, frequency, "
        "steering; the every family's, docs/every-model.md).",
    )
    mirror: bool = Field(
        False,
        description="Train the head on each member's mirror image too (yaw joints negated: the path "
        "mirrored) where it is a member (``StructuredConfig.mirrors``): more examples at no replay cost.",
    )
    val_fraction: float = Field(0.1, gt=0, lt=1, description="Share of z_B draws held out.")
    head_path: HeadPath = Field(
        "direct",
        description="How the head draws the path in the plane (``model.heads.member_path.HeadPath``): "
        "positions directly, or (heading) velocities in the body's frame turned by the predicted "
        "heading and summed, so a turn in place ends where its yaw takes it.",
    )
    xy_floor: float | None = Field(
        None,
        gt=0,
        description="Weight each example's forward and sideways errors by 1 / (its path's scale² + "
        "this²) (m; ``model.heads.member_path.fit_member_head``), so a turn in place that wanders half a "
        "metre is fitted as closely, relative to its size, as a 15 m undulation. None: errors in "
        "the family's metres (the library checkpoint's head).",
    )
    balance_kinds: bool = Field(
        False,
        description="Weight each training example by 1 / its kind's share, so that every kind of member "
        "(undulation, sidewinding, rolling, turning in place) weighs the same in the head's loss, as in "
        "the per-kind figures (docs/model.md).",
    )

    @model_validator(mode="after")
    def _mirror_has_no_z_b(self) -> SamplerConfig:
        if self.mirror and self.head_sees_z_b:
            raise ValueError(
                "a mirrored member has no z_B of its own: mirror and head_sees_z_b exclude each other"
            )
        return self


PRIOR_SAMPLES = 256
"""z_B the consistency check draws by default (``snakeloco evaluate --prior-samples``)."""
ZK_MODES: dict[str, float | None] = {"zk_zero": None, "zk_sampled": 1.0}
"""The consistency check's z_k modes (report keys): z_k = 0, and z_k sampled from the learned prior
at this temperature (``GaitModel.joint_latents``)."""


class ConsistencyConfig(BaseModel):
    """What the generated-gait consistency check draws and how it replays (``consistency``; the flags
    of ``snakeloco evaluate``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    prior_samples: int = Field(PRIOR_SAMPLES, ge=0, description="z_B drawn for the check (0 skips it).")
    positions: Literal["sampler", "prior"] = Field(
        "sampler",
        description="Where those z_B come from: the checkpoint's sampler (its density over the training "
        "posteriors, where the sliders and Random put them) or the N(0, I) prior (what sliders dragged to "
        "their edges reach).",
    )
    ensemble: int = Field(
        ENSEMBLE_SIZE,
        ge=2,
        description="Replays per generated gait: the commands plus ensemble-1 copies with 1e-3 relative noise.",
    )
    seed: int = Field(0, ge=0, description="Seed of the draws and the noise.")
    zk_modes: tuple[Literal["zk_zero", "zk_sampled"], ...] = Field(
        tuple(ZK_MODES),
        min_length=1,
        description="The z_k modes replayed: z_k = 0 (what the sliders decode) and z_k sampled at T = 1 "
        "(what Random with a temperature decodes); one of them halves the replays.",
    )


class PhysicsHeadConfig(BaseModel):
    """What ``calibrate --physics-head`` replays and fits (``model.heads.physics_head``)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    samples: int = Field(192, ge=2, description="Sampler z_B drawn, each decoded with z_k = 0 and sampled.")
    seed: int = Field(5000, ge=0, description="Seed of the draws and of the sampled variations.")
    sampled: int = Field(3, ge=0, description="Combined variations per member besides the default set.")
    eval_samples: int = Field(
        256, ge=0, description="Further sampler positions (z_k = 0) replayed on the default set to score it."
    )
    eval_seed: int = Field(6000, ge=0, description="Seed of those positions.")
    chunk: int = Field(8, ge=1, description="Members per resumable chunk of replays.")
    epochs: int = Field(300, ge=1, description="Epochs of the head.")
    lr: float = Field(2e-3, gt=0, description="Peak learning rate (Adam, cosine to 1%).")
    hidden: int = Field(256, ge=8, description="Width of its hidden layers.")
    val_fraction: float = Field(0.1, gt=0, lt=1, description="Share of the z_B draws held out for the epoch.")
    residual: bool = Field(
        True,
        description="Learn a correction of the member head's output that is zero at the nominal physics (the "
        "nominal path stays the member head's); off, or for a member head that reads z_B: a head of its own.",
    )
