"""``ModelConfig``: every dimension and loss weight of the hierarchical VAE (``network.py``), with the
reason for each number that is not obvious."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

_FROM_DATA = {"cli": False}
"""Field metadata: set by the training data (or fixed by the product), so not a command-line option."""


class ModelConfig(BaseModel):
    """Every dimension and loss weight of the network."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    n_joints: int = Field(8, description="Joints K (the robot's).", json_schema_extra=_FROM_DATA)
    n_components: int = Field(8, description="Excited bins L (the dataset's).", json_schema_extra=_FROM_DATA)
    body_channels: int = Field(6, description="Body channels C.", json_schema_extra=_FROM_DATA)
    body_steps: int = Field(500, description="Body steps T (5 Hz over 100 s).", json_schema_extra=_FROM_DATA)
    z_b_dim: int = Field(
        6, ge=1, le=8, description="Body latent dimensions: one designer slider each (shipped: 6)."
    )
    z_j_dim: int = Field(
        16,
        ge=1,
        description="Per-joint latent. A joint's shape is L = 8 random-phase complex coefficients, so "
        "16 numbers are needed to carry it without loss.",
    )
    cnn_channels: tuple[int, int, int] = Field(
        (24, 48, 96),
        description="Body CNN widths. 32-64-128 spent ~75% of an epoch in the CNN on a prototype; "
        "this is ~0.56x the multiply-adds.",
    )
    kernel: int = Field(5, ge=3, description="Temporal kernel of the body convolutions (odd).")
    positional_channels: int = Field(4, ge=0, description="cos(pi m t / T_rec), m = 1..P, appended to x_B.")
    root_hidden: int = Field(128, ge=1, description="Root GRU width H.")
    child_hidden: int = Field(64, ge=1, description="Child GRU width.")
    joint_embed: int = Field(64, ge=1, description="Width of a joint's shape embedding e(X_k).")
    body_sees_joint_latents: bool = Field(
        False,
        description="Feed z_1..8 to the body decoder as well as z_B. Off by default: with it on, the "
        "decoder memorised training bodies through the 128 joint-latent numbers (epoch 21 of the full "
        "run: train body loss 0.75, held-out body R^2 0.04) instead of putting the path into z_B.",
    )
    body_sees_signals: bool = Field(
        False,
        description="Add to the body decoder's output a convolution over the gait's joint signals (the "
        "joint shape synthesised at the body's time stamps): the oscillations a predictable gait "
        "imposes on the body (vertical, pitch, roll) come from its joints, phase and all, which a "
        "decoder of z_B alone at 1/8 of the body's rate cannot draw. For the structured family; "
        "off for the paper family, whose body does not follow its joints.",
    )
    body_signals_see_latent: bool = Field(
        False,
        description="Feed z_B (broadcast over time) to the joint-signal convolution beside the signals "
        "(needs body_sees_signals): the phase and size of a gait's vertical and pitch oscillation "
        "relative to its joints depend on how the body settled, which the signals alone do not say.",
    )
    body_signals_see_shape: bool = Field(
        False,
        description="Feed an embedding of the gait's whole joint shape (broadcast over time) to the "
        "joint-signal convolution (needs body_sees_signals): how the body answers its joints (the "
        "harmonics and intermodulation of a gait's waves in the vertical and pitch channels) depends "
        "on the whole gait, which a 12 s window of the signals does not show.",
    )
    body_signal_channels: int | None = Field(
        None,
        ge=1,
        description="Width of the body decoder's joint-signal convolution (None: signal_channels).",
    )
    joint_latent_dropout: float = Field(
        0.0,
        ge=0.0,
        lt=1.0,
        description="Share of training records whose shape is decoded as the designer decodes it: "
        "z_1..8 = 0 and each joint after the decoded ones (no teacher forcing); the MMD still sees "
        "the posterior's z_k. It trains the designer's z_k = 0 decoding directly, so z_B must carry "
        "the gait: without it the structured model kept the gait in z_1..8 and in the true shapes "
        "the root GRU is fed, and decoded z_k = 0 shapes with R^2 -0.08 from the records' own z_B "
        "(docs/structured-notes.md).",
    )
    encoder_sees_shape: bool = Field(
        False,
        description="Add an embedding of the gait's joint shape to the body encoder's pooled "
        "features, so that z_B can carry the gait itself (with joint_latent_dropout: the designer's "
        "z_k = 0 decoding then draws the gait from z_B alone). For the structured family, whose "
        "gaits are a few wave parameters.",
    )
    encoder_sees_signals: bool = Field(
        False,
        description="Feed the gait's joint signals to the body encoder beside the body series, so that "
        "z_B can carry the body's oscillation relative to the joints (with body_signals_see_latent).",
    )
    body_sees_stats: bool = Field(
        True,
        description="Modulate the body decoder by the gait's predicted body statistics (model "
        "docstring). Checkpoints of schema 2 predate it and load with it off.",
    )
    signal_channels: int = Field(32, ge=1, description="Width of the statistics head's signal CNN.")
    signal_dilations: tuple[int, ...] = Field(
        (1, 2, 4, 8), description="Dilations of the signal CNN (receptive field 61 steps, 12 s)."
    )
    stats_hidden: int = Field(128, ge=1, description="Hidden width of the statistics MLP.")
    n_stats: int = Field(
        4,
        description="log path length, log median speed, log vertical std, net roll.",
        json_schema_extra=_FROM_DATA,
    )
    alpha: float = Field(
        4.0,
        ge=0,
        description="Weight of the body-path reconstruction (eq. 15's alpha). The paper's 1 left half "
        "of z_B unused (3 of 6 units); 4 (shipped) uses 5 (docs/model.md).",
    )
    alpha_stats: float = Field(
        1.0, ge=0.0, description="Weight of the body-statistics term (normalised MSE)."
    )
    beta: float = Field(10.0, ge=0, description="Weight of MMD(q(z_k) || p(z_k)).")
    gamma: float = Field(10.0, ge=0, description="Weight of MMD(q(z_B) || N(0, I)).")


TINY = ModelConfig(
    z_b_dim=3,
    z_j_dim=4,
    cnn_channels=(4, 8, 8),
    root_hidden=16,
    child_hidden=8,
    joint_embed=8,
    positional_channels=2,
)
"""A network small enough to train in seconds on a few records: the test suite's, and the one
``snakeloco bench scale`` trains to measure the data path rather than the model."""
