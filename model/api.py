"""``GaitModel``: the trained VAE in physical units, numpy in and numpy out, no gradients.

Shapes: shape (B, n_joints, L, 2) rad (single-sided FFT coefficients, ``sim.joint_shape`` convention);
body_ds (B, 500, 6) at 5 Hz, channels vertical, forward, sideways (m), roll, pitch, yaw (rad);
z_b (B, z_b_dim); z_j (B, n_joints, z_j_dim).

A checkpoint of the structured family with ``members`` (schema 4) decodes *members*: each decoded
shape is projected onto the family (``sim.gaits.members``), the shape returned is that member's (as the
servos measure it) and the path is the member path head's prediction for it
(``model.heads.member_path``), so what is drawn, replayed and exported is one gait with its own path
(``model.heads.member_decoding``). ``decode_raw`` keeps the network's own decode.
"""

from __future__ import annotations

import hashlib
import threading
from pathlib import Path

import numpy as np
import torch

from snakeloco.model.checkpoint import WEIGHTS, CheckpointConfig, load_checkpoint, load_member_head
from snakeloco.model.heads.density import draw_z_b
from snakeloco.model.heads.member_decoding import MemberHeads, _finite
from snakeloco.model.heads.member_path import MemberPathHead
from snakeloco.model.heads.physics_head import load_physics_head
from snakeloco.model.vae.network import HierarchicalVAE
from snakeloco.model.vae.stats import stats_dict
from snakeloco.model.vae.tracing import Graphs
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.world.description import DEFAULT_WORLD


class GaitModel:
    """A loaded checkpoint ready for encoding and decoding. Thread-safe (calls are serialised)."""

    def __init__(
        self,
        net: HierarchicalVAE,
        config: CheckpointConfig,
        path: Path | None = None,
        member_head: MemberPathHead | None = None,
        physics_head: MemberPathHead | None = None,
    ) -> None:
        self.net = net.eval()
        self.config = config
        self.path = path
        self.member_head = member_head
        self.physics_head = physics_head
        """The member path head conditioned on the physics (``model.heads.physics_head``), where fitted."""
        if physics_head is not None and member_head is None:
            raise ValueError("a physics head extends a member head")
        if (member_head is None) != (config.member_head is None):
            raise ValueError("a member head and its config go together")
        norm = config.normalization.arrays()
        self._shape_mean, self._shape_std = norm["shape_mean"], norm["shape_std"]  # (L, 2)
        self._body_mean, self._body_std = norm["body_mean"], norm["body_std"]  # (6,)
        self._stats_mean, self._stats_std = norm["stats_mean"], norm["stats_std"]  # (4,)
        self.robot = config.robot or DEFAULT_ROBOT
        """The robot the checkpoint was trained on (``sim.robot.description.Robot``): its joints, its members."""
        self.world = config.world or DEFAULT_WORLD
        """The ground its training data was simulated on (``sim.world``; the flat plane for every shipped one)."""
        g = config.servo_response
        self._servo_response = None if g is None else np.asarray(g, dtype=np.float64)  # (n_joints, L, 2)
        support = config.shape_support
        self._support = None if support is None else np.asarray(support, bool)[..., None]  # (n_joints, L, 1)
        self._lock = threading.Lock()
        self._graphs = Graphs(net)  # one-z_B graphs, made on first use
        heads, body_norm = (member_head, physics_head), (self._body_mean, self._body_std)
        self.members = MemberHeads(
            config, self.robot, heads, body_norm, self._check_shape, self._lock, self._graphs
        )
        """Projection onto the family's members and the paths its heads predict (``model.heads.member_decoding``)."""

    @property
    def family(self) -> str:
        """Gait family of the training data: paper (chaotic on this robot) or structured."""
        return self.config.family

    @property
    def z_b_dim(self) -> int:
        return self.config.model.z_b_dim

    @property
    def z_j_dim(self) -> int:
        return self.config.model.z_j_dim

    @property
    def freqs(self) -> np.ndarray:
        """(L,) excited frequencies (Hz) the model was trained on."""
        return np.asarray(self.config.freqs, dtype=np.float64)

    @property
    def servo_response(self) -> np.ndarray | None:
        """(n_joints, L, 2) measured/commanded complex servo gain of the training data, or None."""
        return self._servo_response

    def commands(self, shape: np.ndarray) -> np.ndarray:
        """Joint commands (..., 2000, 8) rad that make the servos move as a decoded shape (..., 8, L, 2).

        Decoded shapes are *measured* joint angles, so each coefficient is divided by the servo's
        measured complex gain before the inverse FFT (``sim.shape_to_commands(..., response=...)``);
        a checkpoint without that gain resynthesises the shape as is. A checkpoint that decodes
        members (``projects``) synthesises the member the shape projects onto
        (``Member.commands``): for a decoded member's shape, exactly that member's commands.
        """
        from snakeloco.sim import shape_to_commands

        if not self.projects:
            return shape_to_commands(
                shape, self.freqs, response=self._servo_response, limit=self.robot.command_limit
            )
        shape = np.asarray(shape, np.float64)
        members, _ = self.members.project(shape.reshape(-1, *shape.shape[-3:]))
        out = np.stack([m.commands(self.robot) for m in members])
        return out.reshape(*shape.shape[:-3], *out.shape[1:])

    def robot_warning(self, robot=None) -> str | None:
        """None if the checkpoint was trained on ``robot`` (a ``sim.robot.description.Robot``; None: the robot it
        was trained on), else a warning.

        Another robot (joints, servos, friction, a fitted robot) changes what a decoded gait does when
        replayed, so predictions and consistency figures then describe the robot it was trained on.
        """
        robot = robot or self.robot
        here = robot.mjcf_sha256
        if self.config.mjcf_sha256 == here:
            return None
        trained = (
            "the nominal robot (sim/snake.xml)"
            if self.config.mjcf_sha256 == DEFAULT_ROBOT.mjcf_sha256
            else f"robot {self.robot.name} (MJCF sha256 {self.config.mjcf_sha256[:12]})"
        )
        if self.projects and self.members.covers(robot):
            return (
                f"checkpoint {self.path or ''} was trained on {trained}; replays run on {robot.name} "
                f"(MJCF sha256 {here[:12]}): the model's path is its physics head's prediction for this "
                "robot (within the physics it was trained on), its statistics the trained robot's"
            )
        return (
            f"checkpoint {self.path or ''} was trained on {trained}; replays run on {robot.name} "
            f"(MJCF sha256 {here[:12]}): the MuJoCo path is this robot's, the model's path and "
            "statistics the one it was trained on"
        )

    @property
    def hash(self) -> str:
        """sha256 of the weights file (identifies the checkpoint in exported gaits)."""
        if self.path is None:
            return ""
        return hashlib.sha256((self.path / WEIGHTS).read_bytes()).hexdigest()

    # --- normalisation: the network's units --------------------------------------------------------

    def normalize_shape(self, shape: np.ndarray) -> torch.Tensor:
        """Joint shapes (..., 8, L, 2) rad -> the network's normalised float32 tensor."""
        return torch.as_tensor((shape - self._shape_mean) / self._shape_std, dtype=torch.float32)

    def normalize_body(self, body_ds: np.ndarray) -> torch.Tensor:
        """Body series (..., 500, 6) m and rad -> the network's normalised float32 tensor."""
        return torch.as_tensor((body_ds - self._body_mean) / self._body_std, dtype=torch.float32)

    def normalize_stats(self, stats: np.ndarray) -> torch.Tensor:
        """Statistics vectors (..., 4) (``model.vae.stats.stats_vector``) -> normalised float32 tensor."""
        return torch.as_tensor((stats - self._stats_mean) / self._stats_std, dtype=torch.float32)

    def stats_from_network(self, stats: torch.Tensor | np.ndarray) -> dict[str, np.ndarray]:
        """The network's normalised statistics (..., 4) -> {name: (...)} in physical units."""
        v = np.asarray(stats, np.float64)
        return stats_dict(v * self._stats_std + self._stats_mean)

    def _phys(self, shape: torch.Tensor, body: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Decoded network outputs in physical units; joint-shape coefficients outside the family's
        support (``CheckpointConfig.shape_support``) are zero, as in every training record."""
        return self._phys_shape(shape), body.numpy().astype(np.float64) * self._body_std + self._body_mean

    def _phys_shape(self, shape: torch.Tensor) -> np.ndarray:
        shape_p = shape.numpy().astype(np.float64) * self._shape_std + self._shape_mean
        return shape_p if self._support is None else np.where(self._support, shape_p, 0.0)

    # --- API -------------------------------------------------------------------------------------

    def encode(self, shape: np.ndarray, body_ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posterior means: shape (B, n_joints, L, 2), body_ds (B, 500, 6) -> z_b (B, Db), z_j (B, n_joints, Dj)."""
        shape, body_ds = self._check_shape(shape), np.asarray(body_ds, np.float64)
        cfg = self.config.model
        if body_ds.shape != (shape.shape[0], cfg.body_steps, cfg.body_channels):
            raise ValueError(
                f"body_ds must be ({shape.shape[0]}, {cfg.body_steps}, {cfg.body_channels}), got {body_ds.shape}"
            )
        _finite("body_ds", body_ds)
        with self._lock, torch.inference_mode():
            x = self.normalize_shape(shape)
            mu, _ = self.net.encode_body(self.normalize_body(body_ds), x)
            joints = self.net.run_joints(mu, x, sample_posterior=False)
        return mu.numpy().astype(np.float64), joints["z_j"].numpy().astype(np.float64)

    def encode_body(
        self, body_ds: np.ndarray, shape: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """q(z_B | x_B): body series (B, 500, 6) -> posterior mean and log-variance, each (B, Db).
        A model whose encoder sees the joint signals also needs the records' shapes (B, n_joints, L, 2)."""
        body_ds = _finite("body_ds", np.asarray(body_ds, np.float64))
        x = None if shape is None else self.normalize_shape(self._check_shape(shape))
        with self._lock, torch.inference_mode():
            mu, logvar = self.net.encode_body(self.normalize_body(body_ds), x)
        return mu.numpy().astype(np.float64), logvar.numpy().astype(np.float64)

    def decode(self, z_b: np.ndarray, z_j: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """z_b (B, Db) and z_j (B, n_joints, Dj) (None: zeros, the paper's setting (a)) -> shape, body_ds.
        Where the checkpoint ``projects``: the member's shape and the path predicted for it."""
        if self.projects:
            _, _, shape, body, _ = self.decode_members(z_b, z_j, with_stats=False)
            return shape, body
        return self.decode_raw(z_b, z_j)

    def decode_with_stats(
        self, z_b: np.ndarray, z_j: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """``decode`` plus the predicted body statistics of the decoded gait, {name: (B,)}.

        Names (``model.vae.stats.STAT_NAMES``): path_length (m over the 100 s), median_speed (m/s),
        vertical_std (m), net_roll (rad); as ``sim.scores.consistency.path_stats`` measures them at 5 Hz.
        """
        if self.projects:
            _, _, shape, body, stats = self.decode_members(z_b, z_j)
            return shape, body, stats
        return self.decode_raw(z_b, z_j, with_stats=True)

    def decode_raw(self, z_b: np.ndarray, z_j: np.ndarray | None = None, with_stats: bool = False):
        """The network's own decode, no projection: shape, body_ds (and the statistics head's
        prediction with ``with_stats``)."""
        z_b, zj = self._latents(z_b, z_j)
        with self._lock, torch.inference_mode():
            shape, body, stats = self._generate(torch.as_tensor(z_b), zj)
        shape_p, body_p = self._phys(shape, body)
        if not with_stats:
            return shape_p, body_p
        return shape_p, body_p, self.stats_from_network(stats.numpy())

    def decode_shape(self, z_b: np.ndarray, z_j: np.ndarray | None = None) -> np.ndarray:
        """The network's decoded joint shape alone (rad), as ``decode_raw`` gives it."""
        z_b, zj = self._latents(z_b, z_j)
        if zj is None:
            zj = torch.zeros(z_b.shape[0], self.config.model.n_joints, self.z_j_dim)
        traced = self._graphs.single("generate_shape") if z_b.shape[0] == 1 else None
        with self._lock, torch.inference_mode():
            shape = (traced or self.net.generate_shape)(torch.as_tensor(z_b), zj)
        return self._phys_shape(shape)

    @property
    def projects(self) -> bool:
        """Whether decodes are projected onto exact members of the structured family."""
        return self.config.members is not None

    def sample_z_b(self, n: int, seed: int = 0, component: int | None = None) -> np.ndarray:
        """n slider positions (n, Db) from the shipped sampler (``model.heads.density.draw_z_b``; one
        ``component`` of it, or all), deterministic in ``seed``; N(0, I) where there is no density."""
        return draw_z_b(self.config.density, self.z_b_dim, n, seed, component)

    def off_data(self, z_b: np.ndarray) -> np.ndarray:
        """Whether each z_B (B, Db) lies off the data (less dense than 99% of the training records'
        posteriors): (B,) bool. All False without a density."""
        z = self._check_z_b(z_b).astype(np.float64)
        return np.zeros(len(z), bool) if self.config.density is None else self.config.density.off_data(z)

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
            members, residuals = self.members.project(shape)
            return (
                members,
                residuals,
                self.members.member_shapes(members),
                body,
                stats if with_stats else None,
            )
        # The network's own path and statistics would be thrown away: its joint decoder alone.
        members, residuals = self.members.project(self.decode_shape(z_b, z_j))
        # The statistics head judges the member's own shape: the predicted path's 5 Hz steps carry the
        # head's small ripple, which a path length summed over 500 steps would count 3x over.
        measured = self.members.member_shapes(members)
        stats = self.predict_stats(measured) if with_stats else None
        return (
            members,
            residuals,
            measured,
            self.members.predict_paths(members, np.reshape(z_b, (len(members), -1))),
            stats,
        )

    def _check_shape(self, shape: np.ndarray) -> np.ndarray:
        """Joint shapes as float64 (B, n_joints, L, 2); a ValueError names a wrong shape or a non-finite value."""
        shape = np.asarray(shape, np.float64)
        cfg = self.config.model
        if shape.ndim != 4 or shape.shape[1:] != (cfg.n_joints, cfg.n_components, 2):
            raise ValueError(f"shape must be (B, {cfg.n_joints}, {cfg.n_components}, 2), got {shape.shape}")
        return _finite("shape", shape)

    def _latents(self, z_b: np.ndarray, z_j: np.ndarray | None) -> tuple[np.ndarray, torch.Tensor | None]:
        """Checked z_b (B, Db) float32 and z_j as a tensor (None stays None)."""
        z_b = self._check_z_b(z_b)
        if z_j is None:
            return z_b, None
        z_j = np.asarray(z_j, np.float32)
        want = (z_b.shape[0], self.config.model.n_joints, self.z_j_dim)
        if z_j.shape != want:
            raise ValueError(f"z_j must be {want} for {z_b.shape[0]} z_b, got {z_j.shape}")
        return z_b, torch.as_tensor(_finite("z_j", z_j))

    def _check_z_b(self, z_b: np.ndarray) -> np.ndarray:
        """z_b as float32 (B, Db) (one (Db,) vector becomes B = 1); a ValueError names a wrong shape
        or a non-finite value."""
        z_b = np.atleast_2d(np.asarray(z_b, np.float32))
        if z_b.ndim != 2 or z_b.shape[1] != self.z_b_dim:
            raise ValueError(f"z_b must be (B, {self.z_b_dim}), got {z_b.shape}")
        return _finite("z_b", z_b)

    def _generate(self, z_b: torch.Tensor, z_j: torch.Tensor | None):
        """``net.generate``; one z_B (the slider path) runs the traced graph."""
        traced = self._graphs.single("generate") if z_b.shape[0] == 1 else None
        if traced is None:
            return self.net.generate(z_b, z_j)
        if z_j is None:
            z_j = torch.zeros(1, self.config.model.n_joints, self.z_j_dim)
        return traced(z_b, z_j)

    def predict_stats(self, shape: np.ndarray) -> dict[str, np.ndarray]:
        """Body statistics the model predicts for the gaits of joint shapes (B, n_joints, L, 2) rad."""
        shape = self._check_shape(shape)
        x = self.normalize_shape(shape)
        traced = (
            self._graphs.one_input("predict_stats", self.net, "predict_stats", x) if len(x) == 1 else None
        )
        with self._lock, torch.inference_mode():
            v = traced(x) if traced is not None else self.net.predict_stats(x)
        return self.stats_from_network(v.numpy())

    def sample_joint_latents(
        self, z_b: np.ndarray, n: int = 1, seed: int = 0, temperature: float = 1.0
    ) -> np.ndarray:
        """n draws of z_{1:8} from the learned prior given z_b (Db,) -> (n, n_joints, Dj); (B, Db) -> (B, n, n_joints, Dj).

        ``temperature`` scales the prior's standard deviation (0: its mean).
        """
        single = np.ndim(z_b) == 1
        z = self._check_z_b(z_b)
        if n < 1 or not np.isfinite(temperature) or temperature < 0:
            raise ValueError(f"n must be at least 1 and temperature finite and >= 0, got {n}, {temperature}")
        gen = torch.Generator().manual_seed(int(seed))
        eps = (
            torch.randn(z.shape[0], n, self.config.model.n_joints, self.z_j_dim, generator=gen) * temperature
        )
        with self._lock, torch.inference_mode():
            zb = torch.as_tensor(z).repeat_interleave(n, dim=0)  # (B n, Db)
            eps = eps.flatten(0, 1)
            traced = self._graphs.single("sample_joints") if zb.shape[0] == 1 else None
            joints = traced(zb, eps) if traced is not None else self.net.sample_joints(zb, eps)
            out = joints.view(z.shape[0], n, -1, self.z_j_dim)
        out = out.numpy().astype(np.float64)
        return out[0] if single else out

    def joint_latents(self, z_b: np.ndarray, temperature: float | None, seed: int = 0) -> np.ndarray:
        """One z_{1:8} per z_b (B, Db) -> (B, n_joints, Dj): zeros where ``temperature`` is None (the
        paper's generation setting (a), the designer's "zero" mode), else a draw from the learned
        prior at that temperature (``sample_joint_latents``; the designer's "sampled" mode)."""
        z = self._check_z_b(z_b)
        if temperature is None:
            return np.zeros((len(z), self.config.model.n_joints, self.z_j_dim))
        return self.sample_joint_latents(z, 1, seed=seed, temperature=temperature)[:, 0]


def load_pretrained(path: str | Path | None = None) -> GaitModel:
    """Load a checkpoint as a ``GaitModel``: a directory, or a shipped one by gait family
    (``"paper"``; None: the default family's, ``model.checkpoint.SHIPPED``).

    Raises:
        CheckpointError: the checkpoint is missing, corrupt or mismatched (the message says which).
    """
    from snakeloco.model.checkpoint import resolve_checkpoint

    directory = resolve_checkpoint(path)
    net, config = load_checkpoint(directory)
    member_head = load_member_head(directory, config)
    return GaitModel(
        net,
        config,
        directory,
        member_head,
        load_physics_head(directory, member_head) if member_head else None,
    )
