"""The body path the model predicts for an exact member of the structured family.

The hierarchical VAE decodes a joint shape and a body path side by side from z_B. The designer
replays the *member* the shape projects onto (``sim.gaits.members``), so the path it draws must be the
path of that member, not a second decode beside the shape (a shape error or a blend of clusters
then gives a path for a gait that is never replayed). ``MemberPathHead`` is that prediction: an
MLP from the member's commanded coefficients on the family's support to the body series (500, 6)
at 5 Hz, in the checkpoint's body normalisation. It is trained after the VAE on the training
records (each record is a member) and on MuJoCo replays of the members the sliders produce
(``model.heads.sampler``): physics is the teacher, never the predictor at run time.

The head's inputs are the member's coefficients on the family's support (``inputs="coefficients"``,
the undulation family's head) or its named parameters (``"named"``: the kind, amplitudes,
wavenumbers, the offset and steering phase as cosine and sine, frequency): on the every family, whose
kinds travel in directions set by the sign of a phase, the named inputs and a training set doubled
by each member's mirror image (``sim.gaits.members.Member.mirrored``) took the final-position error of 96
held-out records (those ending >= 2 m away) from 0.38 to 0.26 of the distance (docs/every-model.md).

``z_b_dim`` > 0 (``calibrate --sampler --sampler.head-sees-z-b``) also feeds the slider position
z_B the member was decoded from: one member's replays spread (physics' floor on 24 held-out records
replayed with 0.001 relative command noise: sideways R² 0.921, yaw 0.952) and a record's posterior
z_B has seen its path. Measured on the undulation checkpoint (docs/model.md): held-out sideways
0.940 -> 0.964 on 24 records, but 0.984 -> 0.977 on held-out sampler gaits, and a z_B that is not
the member's own pulls the path away from the member's (6 unseen members with one foreign z_B: xy
R² median 0.70). The shipped head reads the member alone.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from snakeloco.model.heads.fitting import fit_best
from snakeloco.model.options import HeadInputs, HeadPath
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.gaits.structured import KINDS, StructuredConfig
from snakeloco.sim.physics.body import mirror_body
from snakeloco.sim.robot.description import Robot

MEMBER_HEAD_WEIGHTS = "member_head.safetensors"
CHANNEL_WEIGHTS = (1.0, 4.0, 4.0, 1.0, 1.0, 4.0)
"""Loss weight per body channel (vertical, forward, sideways, roll, pitch, yaw): the path in the
plane and the heading are what the designer draws and scores; the oscillating channels still count
(the predicted statistics come from them)."""


class MemberHeadConfig(BaseModel):
    """The head's size and its input statistics (stored in the checkpoint's ``config.json``)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    support: list[list[bool]] = Field(
        description="(n_joints, L) the coefficients fed in (the family's support)."
    )
    inputs: HeadInputs = Field("coefficients", description="What describes a member to the head.")
    mirrored: bool = Field(False, description="Trained on every member and its mirror image too.")
    input_mean: list[float] = Field(
        description="(2 S + z_b_dim,) mean of the inputs (rad, then z_B) over the training set."
    )
    input_std: list[float] = Field(description="(2 S + z_b_dim,) their std, floored at 1e-3.")
    z_b_dim: int = Field(0, ge=0, description="z_B inputs after the coefficients (0: the member alone).")
    residual: bool = Field(
        False,
        description="A correction added to the member head's output (``ResidualHead``), zero at nominal physics.",
    )
    physics: list[str] = Field(
        default_factory=list,
        description="Physics inputs after those (``model.heads.physics_head.PHYSICS_FEATURES``; none: the robot "
        "the checkpoint was trained on).",
    )
    hidden: int = Field(256, ge=8, description="Width of the hidden layers.")
    layers: int = Field(3, ge=1, description="Hidden layers.")
    steps: int = Field(500, ge=1, description="Body steps predicted (5 Hz over 100 s).")
    channels: int = Field(6, ge=1, description="Body channels predicted.")
    path: HeadPath = Field("direct", description="How the path in the plane is drawn (``HeadPath``).")
    body_mean: list[float] | None = Field(
        None, description="(6,) the checkpoint's body normalisation (m, rad): a heading head's frame."
    )
    body_std: list[float] | None = Field(None, description="(6,) its std.")
    velocity_scale: float = Field(
        1.0, gt=0, description="m per 5 Hz step of a heading head's unit velocity output."
    )
    summary: dict = Field(default_factory=dict, description="How it was fitted and what it scored.")


class MemberPathHead(nn.Module):
    """Inputs (B, 2 S + z_b_dim) (``member_inputs``) -> normalised body series (B, 500, 6)."""

    def __init__(self, cfg: MemberHeadConfig) -> None:
        super().__init__()
        self.cfg = cfg
        n_in = len(cfg.input_mean)
        dims = [n_in] + [cfg.hidden] * cfg.layers
        layers: list[nn.Module] = []
        for a, b in itertools.pairwise(dims):
            layers += [nn.Linear(a, b), nn.SiLU()]
        layers.append(nn.Linear(dims[-1], cfg.steps * cfg.channels))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_mean", torch.tensor(cfg.input_mean, dtype=torch.float32))
        self.register_buffer("in_std", torch.tensor(cfg.input_std, dtype=torch.float32))
        if cfg.path == "heading":
            if cfg.body_mean is None or cfg.body_std is None or cfg.channels != 6:
                raise ValueError("a heading head needs the body normalisation and all 6 channels")
            self.register_buffer("body_mean", torch.tensor(cfg.body_mean, dtype=torch.float32))
            self.register_buffer("body_std", torch.tensor(cfg.body_std, dtype=torch.float32))

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        """The MLP's output (B, T, C), before a heading head draws the path from it."""
        return self.mlp((x - self.in_mean) / self.in_std).view(-1, self.cfg.steps, self.cfg.channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.draw(self.raw(x))

    def draw(self, y: torch.Tensor) -> torch.Tensor:
        """The normalised body series from the MLP's output ``y`` (B, T, C)."""
        if self.cfg.path == "direct":
            return y  # (B, T, C)
        # Dead reckoning: step k moves the body by its velocity u_k in its own frame, turned by its
        # heading; the series starts at the origin of the initial frame (as every record does).
        yaw = y[..., 5] * self.body_std[5] + self.body_mean[5]
        u = y[..., 1:3] * self.cfg.velocity_scale
        c, s = torch.cos(yaw), torch.sin(yaw)
        step = torch.stack([c * u[..., 0] - s * u[..., 1], s * u[..., 0] + c * u[..., 1]], dim=-1)
        xy = torch.cat([torch.zeros_like(step[:, :1]), torch.cumsum(step[:, :-1], dim=1)], dim=1)
        xy = (xy - self.body_mean[1:3]) / self.body_std[1:3]
        return torch.cat([y[..., :1], xy, y[..., 3:]], dim=-1)


class ResidualHead(nn.Module):
    """A frozen member head plus a correction read from the physics inputs that end each row:
    ``base`` on the member's inputs, plus ``delta`` on the whole row minus ``delta`` with the
    physics zeroed, so the nominal robot's path is the member head's own, exactly, and only the
    physics' effect is learnt (``model.heads.physics_head``)."""

    def __init__(self, base: MemberPathHead, delta: MemberPathHead) -> None:
        super().__init__()
        self.base, self.delta = base.requires_grad_(False), delta
        self.cfg = delta.cfg

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = x.shape[1] - len(self.cfg.physics)
        x0 = torch.cat([x[:, :n], torch.zeros_like(x[:, n:])], dim=1)
        return self.base.draw(self.base.raw(x[:, :n]) + self.delta.raw(x) - self.delta.raw(x0))


NAMED_INPUTS = len(KINDS) + 10
"""Named inputs per member: the kind one-hot, then a_pitch, a_yaw, nu_pitch, nu_yaw, cos and sin of
the offset, frequency, steering amplitude and its two components."""
CURVE_INPUTS = 3
"""With "named_curve", after those: the curving wave's yaw amplitude and its two components (cosine
and sine of its offset; zeros for a straight member)."""


def named_inputs(members: list[Member], curve: bool = False) -> np.ndarray:
    """Members -> their named parameters (B, ``NAMED_INPUTS`` (+ ``CURVE_INPUTS`` with ``curve``)); a
    mirror image negates the offset's, the steering's and the curve's cosine and sine and keeps the
    rest."""
    rows = []
    for m in members:
        w, s = m.wave, m.steering_amplitude
        kind = [float(m.kind == k) for k in KINDS]
        wave = [w.a_pitch, w.a_yaw, w.nu_pitch, w.nu_yaw, np.cos(w.delta), np.sin(w.delta), w.frequency]
        row = [*kind, *wave, s, s * np.cos(m.steering_phase), s * np.sin(m.steering_phase)]
        if curve:
            c = m.curve
            row += (
                [0.0] * CURVE_INPUTS
                if c is None
                else [c.a_yaw, c.a_yaw * np.cos(c.delta), c.a_yaw * np.sin(c.delta)]
            )
        rows.append(row)
    return np.array(rows, np.float64).reshape(len(members), NAMED_INPUTS + CURVE_INPUTS * curve)


def with_mirror_images(
    members: list[Member], body: np.ndarray, family: StructuredConfig
) -> tuple[list[Member], np.ndarray]:
    """Training pairs (members, body series (N, T, 6)) and, after them, the mirror image of each pair
    whose mirrored member is a member of ``family`` too (``StructuredConfig.mirrors``)."""
    images = np.array([family.mirrors(m.kind) for m in members], bool)
    mirrored = [m.mirrored() for m, image in zip(members, images, strict=True) if image]
    return members + mirrored, np.concatenate([body, mirror_body(np.asarray(body)[images])])


def member_inputs(
    members: list[Member],
    support: np.ndarray,
    z_b: np.ndarray | None,
    inputs: HeadInputs,
    robot: Robot,
) -> np.ndarray:
    """Members (and their slider positions z_b (B, Db)) -> the head's inputs: their commanded
    coefficients on ``robot`` on the support (N, L), real and imaginary parts (B, 2 S), or their
    named parameters (``named_inputs``), then z_B."""
    if inputs in ("named", "named_curve"):
        x = named_inputs(members, curve=inputs == "named_curve")
    else:
        shapes = (
            np.stack([m.shape(robot) for m in members]) if members else np.zeros((0, *np.shape(support), 2))
        )
        x = shapes[:, np.asarray(support, bool)].reshape(len(members), -1)
    if z_b is None:
        return x
    return np.concatenate([x, np.asarray(z_b, np.float64).reshape(len(x), -1)], axis=1)


def body_frame_velocities(body: np.ndarray) -> np.ndarray:
    """(N, T, 6) body series (m, rad) -> (N, T - 1, 2) each step's plane displacement in the body's
    own frame at its start (forward, left): what a heading head predicts (``HeadPath``)."""
    b = np.asarray(body, np.float64)
    d, yaw = np.diff(b[:, :, 1:3], axis=1), b[:, :-1, 5]
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def kind_weights(members: list[Member], of: list[Member] | None = None) -> np.ndarray:
    """Weights (N,) for ``of`` (default ``members``) under which every kind among ``members`` weighs
    the same in total: 1 / (its share of ``members`` x the number of kinds), so a mean over
    ``members`` stays 1. A kind of ``of`` that ``members`` lacks gets 1."""
    kinds = [m.kind for m in members]
    names, counts = np.unique(kinds, return_counts=True)
    share = dict(zip(names.tolist(), (counts / len(kinds)).tolist(), strict=True))
    return np.array(
        [
            1.0 / (share[m.kind] * len(names)) if m.kind in share else 1.0
            for m in (members if of is None else of)
        ]
    )


def path_scales(body: np.ndarray) -> np.ndarray:
    """(N, T, 6) body series (m, rad) -> (N,) each path's scale: the RMS distance (m) of its plane
    position from its start."""
    d = np.asarray(body, np.float64)[:, :, 1:3] - np.asarray(body, np.float64)[:, :1, 1:3]
    return np.sqrt((d**2).sum(-1).mean(-1))


def fit_member_head(
    inputs: np.ndarray,
    body: np.ndarray,
    val_inputs: np.ndarray,
    val_body: np.ndarray,
    support: np.ndarray,
    *,
    input_kind: HeadInputs = "coefficients",
    mirrored: bool = False,
    z_b_dim: int = 0,
    epochs: int = 400,
    lr: float = 2e-3,
    batch_size: int = 128,
    hidden: int = 256,
    layers: int = 3,
    seed: int = 0,
    xy_scale: tuple[np.ndarray, np.ndarray] | None = None,
    xy_floor: float = 0.0,
    example_weights: tuple[np.ndarray, np.ndarray] | None = None,
    path: HeadPath = "direct",
    body_norm: tuple[np.ndarray, np.ndarray] | None = None,
    physics: tuple[str, ...] = (),
    base: MemberPathHead | None = None,
    log: Callable[[str], None] | None = print,
) -> tuple[MemberPathHead, dict]:
    """Fit a head on (inputs (N, I) from ``member_inputs`` with ``input_kind``, normalised body (N,
    500, 6)) pairs, the epoch with the lowest validation loss kept (``model.heads.fitting.fit_best``);
    ``mirrored`` records that the pairs include the members' mirror images. ``xy_scale`` (training,
    validation), each (N,) m: every example's own path scale (``path_scales``); given, an example's
    forward and sideways errors are weighted by 1 / (scale² + ``xy_floor``²), normalised to a mean of
    1 over the training examples, so the loss scores a path's shape relative to its own size, as
    the designer's figures do (xy R², final-position error over the distance). ``example_weights``
    (training, validation), each (N,): every example's whole error is weighted so (``kind_weights``:
    each kind of member counts as much as any other). ``path``: how the
    head draws the plane path (``HeadPath``); a heading head needs ``body_norm``, the (mean, std) (6,)
    the body series are normalised by. ``physics``: the names of the physics inputs that end each
    input row (``model.heads.physics_head``); ``base``: a member head (reading the rows without them) the
    fitted head corrects (``ResidualHead``; its path drawing is the base's). Returns the head and
    what it scored."""

    torch.manual_seed(seed)
    x, y = torch.as_tensor(inputs, dtype=torch.float32), torch.as_tensor(body, dtype=torch.float32)
    vx, vy = torch.as_tensor(val_inputs, dtype=torch.float32), torch.as_tensor(val_body, dtype=torch.float32)
    cfg = MemberHeadConfig(
        support=np.asarray(support, bool).tolist(),
        inputs=input_kind,
        mirrored=mirrored,
        input_mean=x.mean(0).tolist(),
        input_std=x.std(0).clamp_min(1e-3).tolist(),
        z_b_dim=z_b_dim,
        physics=list(physics),
        hidden=hidden,
        layers=layers,
        steps=y.shape[1],
        channels=y.shape[2],
    )
    if path == "heading":
        if body_norm is None:
            raise ValueError("a heading head needs body_norm, the body normalisation")
        mean, std = (np.asarray(a, np.float64) for a in body_norm)
        cfg = cfg.model_copy(
            update={
                "path": path,
                "body_mean": mean.tolist(),
                "body_std": std.tolist(),
                "velocity_scale": float(body_frame_velocities(np.asarray(body) * std + mean).std()),
            }
        )
    if base is not None:
        cfg = cfg.model_copy(
            update={k: getattr(base.cfg, k) for k in ("path", "body_mean", "body_std", "velocity_scale")}
            | {"residual": True}
        )
    head = MemberPathHead(cfg) if base is None else ResidualHead(base, MemberPathHead(cfg))
    keep = head if base is None else head.delta
    w = torch.tensor(CHANNEL_WEIGHTS[: y.shape[2]], dtype=torch.float32)

    xy = torch.zeros(y.shape[2], dtype=torch.bool)
    xy[1:3] = True  # forward, sideways
    ew, vew = torch.ones(len(x)), torch.ones(len(vx))
    if xy_scale is not None:
        inv, vinv = (1.0 / (np.asarray(s, np.float64) ** 2 + xy_floor**2) for s in xy_scale)
        ew, vew = (torch.as_tensor(i / inv.mean(), dtype=torch.float32) for i in (inv, vinv))
    kw, vkw = (
        (torch.ones(len(x)), torch.ones(len(vx)))
        if example_weights is None
        else (torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in example_weights)
    )

    def loss(pred: torch.Tensor, true: torch.Tensor, ex_w: torch.Tensor, k_w: torch.Tensor) -> torch.Tensor:
        per = ((pred - true) ** 2).mean(dim=1)  # (B, C)
        per = torch.where(xy, per * ex_w[:, None], per) * k_w[:, None]
        return (per.mean(dim=0) * w).sum() / w.sum()

    def val_loss() -> float:
        head.eval()
        with torch.no_grad():
            return float(loss(head(vx), vy, vew, vkw))

    best_epoch, history = fit_best(
        head,
        keep,
        len(x),
        lambda idx: loss(head(x[idx]), y[idx], ew[idx], kw[idx]),
        val_loss,
        epochs,
        lr,
        batch_size,
        seed,
        None,
        min_batch=2,
    )
    summary = {
        "epochs": epochs,
        "best_epoch": best_epoch,
        "val_loss": val_loss(),
        "train_examples": len(x),
        "val_examples": len(vx),
        "lr": lr,
        "seed": seed,
        "xy_floor": xy_floor if xy_scale is not None else None,
        "example_weights": example_weights is not None,
        "path": path,
    }
    if log:
        log(f"member path head: best epoch {best_epoch} of {epochs}, val loss {summary['val_loss']:.4f}")
    return head.requires_grad_(False).eval(), summary | {"history": history[-5:]}
