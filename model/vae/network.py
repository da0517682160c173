"""Hierarchical VAE over a topological joint shape and a body trajectory (paper 3.3-3.4).

Notation (shapes in comments): B batch, K = 8 joints, L spectral components, T = 500 body steps,
C = 6 body channels, Db = z_b_dim, Dj = z_j_dim, H = root GRU width.

- Body encoder q(z_B | x_B): 1D CNN, 3 layers (the first depthwise-separable), channels doubling,
  x1/2 average pooling after each, global average pooling, then a linear head to (mu, logvar).
  A few fixed positional channels (cosines of the record time) are appended to x_B so that
  the global average can still tell early from late in the record.
- Root GRU over joints: h_k = GRU(h_{k-1}, [e(X_k), z_k, z_B]); learned prior p(z_k | h_{k-1}, z_B)
  and posterior q(z_k | e(X_k), h_{k-1}, z_B), both diagonal Gaussians.
- Child GRU (one set of weights for all joints) over the L components of joint k, started from
  [h_{k-1}, z_B, z_k] and fed the component's log-frequency, emitting c_kl = (re, im).
- Body decoder: mirror of the encoder (linear to T/8 steps, three x2 upsamplings with convolutions)
  from z_B, modulated (FiLM) by the gait's predicted body statistics (``body_sees_stats``, below); by
  default the joint latents are zeroed there (``body_sees_joint_latents``), the paper's generation
  setting (a), because the decoder otherwise memorised training bodies.
- Statistics head (an extension of the paper): the body's *predictable statistics* over the record
  (log path length, log median speed, log vertical-oscillation std, net roll), predicted from z_B and
  the gait alone. The joint shape (the true one in training, the decoded one in generation) is
  resynthesised by the inverse transform of ``sim.gaits.spectra`` into the 8 joint angles and rates at the
  body's time stamps; a dilated 1D CNN with circular padding (the gait is periodic over the record)
  runs over those 16 channels and is pooled over time (mean and std: invariant to a time shift of
  the gait), then an MLP gives the statistics. Why: a body *series* of these gaits is
  chaotic (two replays of the same commands with 1e-3 noise have body R^2 -0.04 against each
  other; vertical -0.18, pitch -0.18), so its MSE-optimal prediction is the smooth conditional mean,
  whose oscillation (path length, speed, vertical std) is far too small. The statistics themselves
  vary by a few percent across such replays, so they are predicted directly.
- The body decoder is conditioned on those predicted statistics (detached: the body loss does not
  train the head). Why: from z_B alone it draws the path of a *typical* gait for that z_B, while
  what the robot does depends on the gait z_k chose; a z_k = 0 gait (the prior's smooth mean) moves
  less than the records its z_B was fitted on (without the modulation, 43 of 48 decoded z_k = 0
  final positions fell outside the replays' spread; with it and its calibration, 24 of 48). Four
  numbers predicted from the gait (not read off the body) cannot carry a training record's chaotic
  path, so the decoder cannot memorise through them.
- At generation time the root GRU is fed the decoded shape of joint k in place of X_k.

All tensors here are normalised (statistics in model/checkpoint.py; physical units in model/api.py).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from snakeloco.model.vae.config import ModelConfig
from snakeloco.model.vae.layers import Output, SeparableConv, gaussian_head


class HierarchicalVAE(nn.Module):
    """The generative locomotion model; see the module docstring for the structure."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c1, c2, c3 = cfg.cnn_channels
        c_in = cfg.body_channels + cfg.positional_channels
        if cfg.encoder_sees_signals:
            c_in += 2 * cfg.n_joints
        pad = cfg.kernel // 2
        self.encoder = nn.Sequential(
            SeparableConv(c_in, c1, cfg.kernel),
            nn.GELU(),
            nn.AvgPool1d(2),
            nn.Conv1d(c1, c2, cfg.kernel, padding=pad),
            nn.GELU(),
            nn.AvgPool1d(2),
            nn.Conv1d(c2, c3, cfg.kernel, padding=pad),
            nn.GELU(),
            nn.AvgPool1d(2),
        )
        self.enc_head = nn.Linear(c3, 2 * cfg.z_b_dim)
        if cfg.encoder_sees_shape:
            # The gait's whole joint shape, embedded and added to the pooled body features: z_B can
            # then hold a structured gait's few parameters exactly, which a pooled convolution over
            # the body and the signals reads out only roughly (docs/structured-notes.md).
            d_shape = cfg.n_joints * cfg.n_components * 2
            self.enc_shape = nn.Sequential(
                nn.Linear(d_shape, cfg.root_hidden), nn.GELU(), nn.Linear(cfg.root_hidden, c3)
            )
        self.dec_steps = math.ceil(cfg.body_steps / 8)
        d_lat = cfg.z_b_dim + cfg.n_joints * cfg.z_j_dim
        self.dec_in = nn.Linear(d_lat, c3 * self.dec_steps)
        if cfg.body_sees_stats:
            # FiLM: the statistics scale and shift each of the decoder's input channels, so the
            # gait's reach can multiply the path z_B draws. Zero-initialised, so training starts from
            # the z_B-only decoder and z_B still has to carry the path (with the statistics fed in
            # as a plain input through a hidden layer, z_B's share fell: validation body R^2 0.35
            # vs 0.46 without the statistics at epoch 40 of the full run, 0.36 vs 0.61 at 90).
            self.dec_film = nn.Linear(cfg.n_stats, 2 * c3)
            nn.init.zeros_(self.dec_film.weight)
            nn.init.zeros_(self.dec_film.bias)
        self.decoder = nn.Sequential(
            nn.GELU(),
            nn.Upsample(scale_factor=2),
            nn.Conv1d(c3, c2, cfg.kernel, padding=pad),
            nn.GELU(),
            nn.Upsample(scale_factor=2),
            nn.Conv1d(c2, c1, cfg.kernel, padding=pad),
            nn.GELU(),
            nn.Upsample(scale_factor=2),
            SeparableConv(c1, cfg.body_channels, cfg.kernel),
        )
        c_sig = cfg.signal_channels
        if cfg.body_sees_signals:
            # A residual from the joint signals to the body, zero-initialised (training starts from
            # the z_B decoder); circular like the signals, which are periodic over the record.
            c_body = cfg.body_signal_channels or c_sig
            body_sig: list[nn.Module] = []
            c_prev = 2 * cfg.n_joints + (cfg.z_b_dim if cfg.body_signals_see_latent else 0)
            if cfg.body_signals_see_shape:
                n_shape = cfg.n_joints * cfg.n_components * 2
                self.body_gait = nn.Sequential(
                    nn.Linear(n_shape, cfg.stats_hidden), nn.GELU(), nn.Linear(cfg.stats_hidden, c_body)
                )
                c_prev += c_body
            for d in cfg.signal_dilations:
                body_sig += [
                    nn.Conv1d(
                        c_prev, c_body, cfg.kernel, padding=d * pad, dilation=d, padding_mode="circular"
                    ),
                    nn.GELU(),
                ]
                c_prev = c_body
            body_sig.append(nn.Conv1d(c_body, cfg.body_channels, 1))
            nn.init.zeros_(body_sig[-1].weight)
            nn.init.zeros_(body_sig[-1].bias)
            self.body_sig = nn.Sequential(*body_sig)
        layers: list[nn.Module] = []
        c_prev = 2 * cfg.n_joints  # angle and rate of each joint
        for d in cfg.signal_dilations:
            layers += [
                nn.Conv1d(c_prev, c_sig, cfg.kernel, padding=d * pad, dilation=d, padding_mode="circular"),
                nn.GELU(),
            ]
            c_prev = c_sig
        self.signal_net = nn.Sequential(*layers)
        self.stats_head = nn.Sequential(
            nn.Linear(2 * c_sig, cfg.stats_hidden),
            nn.GELU(),
            nn.Linear(cfg.stats_hidden, cfg.stats_hidden),
            nn.GELU(),
            nn.Linear(cfg.stats_hidden, cfg.n_stats),
        )
        # The inverse transform at the body's time stamps; set by ``set_signal_source`` and saved
        # with the weights so a checkpoint decodes exactly as it was trained.
        n_l, n_t = cfg.n_components, cfg.body_steps
        self.register_buffer("signal_cos", torch.zeros(n_t, n_l))  # (T, L)
        self.register_buffer("signal_sin", torch.zeros(n_t, n_l))  # (T, L)
        self.register_buffer("signal_freqs", torch.zeros(n_l))  # (L,) Hz
        self.register_buffer("shape_mean", torch.zeros(n_l, 2))  # (L, 2) rad
        self.register_buffer("shape_std", torch.ones(n_l, 2))  # (L, 2) rad
        self.register_buffer("signal_ready", torch.zeros(()))
        t = torch.linspace(0.0, 1.0, cfg.body_steps)
        m = torch.arange(1, cfg.positional_channels + 1, dtype=torch.float32)
        self.register_buffer("positional", torch.cos(math.pi * m[:, None] * t[None, :]), persistent=False)

        n_coef = 2 * cfg.n_components
        self.joint_embed = nn.Sequential(
            nn.Linear(n_coef, cfg.joint_embed), nn.GELU(), nn.Linear(cfg.joint_embed, cfg.joint_embed)
        )
        self.root_init = nn.Linear(cfg.z_b_dim, cfg.root_hidden)
        self.root = nn.GRUCell(cfg.joint_embed + cfg.z_j_dim + cfg.z_b_dim, cfg.root_hidden)
        self.prior = gaussian_head(cfg.root_hidden + cfg.z_b_dim, cfg.z_j_dim, cfg.root_hidden)
        self.posterior = gaussian_head(
            cfg.joint_embed + cfg.root_hidden + cfg.z_b_dim, cfg.z_j_dim, cfg.root_hidden
        )
        d_cond = cfg.root_hidden + cfg.z_b_dim + cfg.z_j_dim
        self.child_init = nn.Linear(d_cond, cfg.child_hidden)
        self.child = nn.GRU(1 + d_cond, cfg.child_hidden, batch_first=True)
        self.child_out = nn.Linear(cfg.child_hidden, 2)
        # The child GRU's per-step input: the component's position on a log-frequency axis in [-1, 1].
        self.register_buffer(
            "component_coord", torch.linspace(-1.0, 1.0, cfg.n_components)[:, None], persistent=False
        )

    # --- body ------------------------------------------------------------------------------------

    def set_signal_source(
        self, phase: torch.Tensor, freqs: torch.Tensor, shape_mean: torch.Tensor, shape_std: torch.Tensor
    ) -> None:
        """Fix the signal branch's inverse transform.

        Args:
            phase: (T, L) 2 pi f_l t at the body time stamps (``sim.synthesis_phase(..., stride=4)``).
            freqs: (L,) Hz.
            shape_mean, shape_std: (L, 2) the shape normalisation (the branch works in radians).
        """
        with torch.no_grad():
            phase = torch.as_tensor(phase, dtype=torch.float64)
            self.signal_cos.copy_(torch.cos(phase))
            self.signal_sin.copy_(torch.sin(phase))
            self.signal_freqs.copy_(torch.as_tensor(freqs))
            self.shape_mean.copy_(torch.as_tensor(shape_mean))
            self.shape_std.copy_(torch.as_tensor(shape_std))
            self.signal_ready.fill_(1.0)

    def joint_signals(self, shape: torch.Tensor) -> torch.Tensor:
        """Normalised shape (B, K, L, 2) -> joint angles (rad) and rates / 2 pi (rad/s) (B, 2K, T).

        q_k(t) = sum_l re_kl cos(w_l t) - im_kl sin(w_l t), the convention of ``sim.shape_to_commands``.
        """
        if not bool(self.signal_ready):
            raise RuntimeError(
                "signal branch not initialised: call set_signal_source (train) or load a checkpoint"
            )
        c = shape * self.shape_std + self.shape_mean  # (B, K, L, 2) rad
        re, im = c[..., 0], c[..., 1]  # (B, K, L)
        q = torch.einsum("bkl,tl->bkt", re, self.signal_cos) - torch.einsum(
            "bkl,tl->bkt", im, self.signal_sin
        )
        fre, fim = re * self.signal_freqs, im * self.signal_freqs
        dq = -torch.einsum("bkl,tl->bkt", fre, self.signal_sin) - torch.einsum(
            "bkl,tl->bkt", fim, self.signal_cos
        )
        return torch.cat([q, dq], dim=1)  # (B, 2K, T)

    def encode_body(
        self, body: torch.Tensor, shape: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """body (B, T, C) and, when ``cfg.encoder_sees_signals`` or ``cfg.encoder_sees_shape``, the
        record's normalised joint shape (B, K, L, 2) -> mu, logvar (B, Db)."""
        x = body.transpose(1, 2)  # (B, C, T)
        parts = [x, self.positional.expand(x.shape[0], -1, -1)]  # (B, P, T)
        if self.cfg.encoder_sees_signals:
            if shape is None:
                raise ValueError("this body encoder sees the gait's joint signals: pass its shape")
            parts.append(self.joint_signals(shape))
        h = self.encoder(torch.cat(parts, dim=1)).mean(dim=2)  # (B, c3): global average pooling
        if self.cfg.encoder_sees_shape:
            if shape is None:
                raise ValueError("this body encoder sees the gait's joint shape: pass it")
            h = h + self.enc_shape(shape.flatten(1))
        mu, logvar = self.enc_head(h).chunk(2, dim=1)
        return mu, logvar.clamp(-12.0, 6.0)

    def decode_body(
        self,
        z_b: torch.Tensor,
        z_j: torch.Tensor,
        stats: torch.Tensor | None = None,
        shape: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """z_b (B, Db), z_j (B, K, Dj), the gait's predicted normalised statistics (B, n_stats)
        (needed when ``cfg.body_sees_stats``) and its normalised joint shape (B, K, L, 2) (needed when
        ``cfg.body_sees_signals``) -> body (B, T, C)."""
        if not self.cfg.body_sees_joint_latents:
            z_j = torch.zeros_like(z_j)  # the joint-latent weights then see only zeros
        lat = torch.cat([z_b, z_j.flatten(1)], dim=1)  # (B, Db + K Dj)
        h = self.dec_in(lat).view(lat.shape[0], -1, self.dec_steps)  # (B, c3, T/8)
        if self.cfg.body_sees_stats:
            if stats is None:
                raise ValueError("this body decoder is conditioned on the gait's statistics: pass stats")
            scale, shift = self.dec_film(stats).chunk(2, dim=1)  # (B, c3) each
            h = h * (1.0 + scale[:, :, None]) + shift[:, :, None]
        x = self.decoder(h)[:, :, : self.cfg.body_steps]  # (B, C, T)
        if self.cfg.body_sees_signals:
            if shape is None:
                raise ValueError("this body decoder sees the gait's joint signals: pass its shape")
            sig = self.joint_signals(shape)  # (B, 2K, T)
            parts = [sig]
            if self.cfg.body_signals_see_latent:
                parts.append(z_b[:, :, None].expand(-1, -1, sig.shape[2]))
            if self.cfg.body_signals_see_shape:
                parts.append(self.body_gait(shape.flatten(1))[:, :, None].expand(-1, -1, sig.shape[2]))
            x = x + self.body_sig(torch.cat(parts, dim=1))
        return x.transpose(1, 2)

    def predict_stats(self, shape: torch.Tensor) -> torch.Tensor:
        """Normalised shape (B, K, L, 2) -> normalised body statistics (B, n_stats).

        A function of the gait alone: z_B is left out so that training cannot lean on what the
        encoder read off one chaotic realisation, which generation does not have, and so that the
        statistics term does not pull on the body latent.
        """
        h = self.signal_net(self.joint_signals(shape))  # (B, c_sig, T)
        pooled = torch.cat([h.mean(dim=2), h.std(dim=2)], dim=1)  # (B, 2 c_sig): shift-invariant
        return self.stats_head(pooled)

    # --- joints ----------------------------------------------------------------------------------

    def decode_joint(self, h: torch.Tensor, z_b: torch.Tensor, z_k: torch.Tensor) -> torch.Tensor:
        """Child GRU: root state h (B, H), z_b (B, Db), z_k (B, Dj) -> coefficients (B, L, 2)."""
        cond = torch.cat([h, z_b, z_k], dim=1)  # (B, d_cond)
        coord = self.component_coord.expand(cond.shape[0], -1, -1)  # (B, L, 1)
        steps = torch.cat(
            [coord, cond[:, None].expand(-1, self.cfg.n_components, -1)], dim=2
        )  # (B, L, 1 + d_cond)
        out, _ = self.child(steps, torch.tanh(self.child_init(cond))[None])  # (B, L, child_hidden)
        return self.child_out(out)  # (B, L, 2)

    def run_joints(
        self,
        z_b: torch.Tensor,
        shape: torch.Tensor | None = None,
        z_j: torch.Tensor | None = None,
        *,
        sample_posterior: bool = True,
        prior_eps: torch.Tensor | None = None,
        with_priors: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Run the root GRU over the K joints.

        With ``shape`` (B, K, L, 2) given, z_k comes from the posterior (a sample, or its mean) and
        the root GRU is fed the true shapes (teacher forcing); the child GRU then decodes all joints
        in one batched call. Without it, z_k is ``z_j[:, k]`` if given, else a draw from the learned
        prior using ``prior_eps`` (B, K, Dj) (zeros: its mean), and the root GRU is fed each decoded
        shape in turn. Without ``with_priors`` (and with ``z_j``) the prior net is not run and the
        output has no "prior_sample": the same shape in 0.9x the time (what a slider move decodes).
        """
        n_k = self.cfg.n_joints
        h = torch.tanh(self.root_init(z_b))  # (B, H)
        embeds = self.joint_embed(shape.flatten(2)) if shape is not None else None  # (B, K, E)
        hs, shapes, zs, mus, priors = [], [], [], [], []
        for k in range(n_k):
            if with_priors or (embeds is None and z_j is None):
                p_mu, p_logvar = self.prior(torch.cat([h, z_b], dim=1)).chunk(2, dim=1)  # (B, Dj) each
                p_std = torch.exp(0.5 * p_logvar.clamp(-12.0, 6.0))
                priors.append(p_mu + p_std * torch.randn_like(p_mu))
            hs.append(h)
            if embeds is not None:
                e_k = embeds[:, k]  # (B, E)
                q_mu, q_logvar = self.posterior(torch.cat([e_k, h, z_b], dim=1)).chunk(2, dim=1)
                q_std = torch.exp(0.5 * q_logvar.clamp(-12.0, 6.0))
                z_k = q_mu + q_std * torch.randn_like(q_mu) if sample_posterior else q_mu
                mus.append(q_mu)
            else:
                if z_j is not None:
                    z_k = z_j[:, k]
                else:
                    eps = prior_eps[:, k] if prior_eps is not None else torch.zeros_like(p_mu)
                    z_k = p_mu + p_std * eps
                x_k = self.decode_joint(h, z_b, z_k)  # (B, L, 2)
                shapes.append(x_k)
                e_k = self.joint_embed(x_k.flatten(1))
            zs.append(z_k)
            if k + 1 < n_k:  # the state after the last joint feeds nothing
                h = self.root(torch.cat([e_k, z_k, z_b], dim=1), h)
        z_all = torch.stack(zs, dim=1)  # (B, K, Dj)
        if embeds is not None:
            b = z_b.shape[0]
            h_all = torch.stack(hs, dim=1)  # (B, K, H): state before each joint
            x = self.decode_joint(
                h_all.flatten(0, 1), z_b.repeat_interleave(n_k, dim=0), z_all.flatten(0, 1)
            )  # (B K, L, 2)
            shape_hat = x.view(b, n_k, self.cfg.n_components, 2)
        else:
            shape_hat = torch.stack(shapes, dim=1)
        extra = {"prior_sample": priors, "z_j_mu": mus}  # either may be empty (see above)
        return {"shape": shape_hat, "z_j": z_all} | {k: torch.stack(v, dim=1) for k, v in extra.items() if v}

    # --- whole model -----------------------------------------------------------------------------

    def forward(self, shape: torch.Tensor, body: torch.Tensor, sample: bool = True) -> Output:
        """Reconstruct normalised shape (B, K, L, 2) and body (B, T, C) through the posteriors."""
        mu, logvar = self.encode_body(body, shape)
        z_b = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu) if sample else mu
        joints = self.run_joints(z_b, shape, sample_posterior=sample)
        shape_hat = joints["shape"]
        if self.training and self.cfg.joint_latent_dropout > 0:
            drop = torch.rand(shape.shape[0], device=shape.device) < self.cfg.joint_latent_dropout
            if drop.any():  # decoded as the designer decodes: z_k = 0, each joint after the decoded ones
                zeros = torch.zeros_like(joints["z_j"][drop])
                shape_hat = shape_hat.clone()
                shape_hat[drop] = self.run_joints(z_b[drop], z_j=zeros)["shape"]
        stats = self.predict_stats(shape)  # teacher forcing: the true shape
        body_hat = self.decode_body(z_b, joints["z_j"], stats.detach(), shape)
        return Output(
            shape=shape_hat,
            body=body_hat,
            z_b=z_b,
            z_b_mu=mu,
            z_j=joints["z_j"],
            z_j_mu=joints["z_j_mu"],
            prior_sample=joints["prior_sample"],
            stats=stats,
        )

    def generate(
        self, z_b: torch.Tensor, z_j: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Decode z_b (B, Db) and joint latents z_j (B, K, Dj) (None: zeros) -> shape, body and body
        statistics (normalised); the statistics are predicted for the decoded shape's gait."""
        if z_j is None:
            z_j = torch.zeros(z_b.shape[0], self.cfg.n_joints, self.cfg.z_j_dim, device=z_b.device)
        joints = self.run_joints(z_b, z_j=z_j)
        shape = joints["shape"]
        stats = self.predict_stats(shape)
        return shape, self.decode_body(z_b, joints["z_j"], stats, shape), stats

    def generate_shape(self, z_b: torch.Tensor, z_j: torch.Tensor) -> torch.Tensor:
        """``generate``'s shape alone (what a checkpoint that projects onto its family needs)."""
        return self.run_joints(z_b, z_j=z_j, with_priors=False)["shape"]

    def sample_joints(self, z_b: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        """Joint latents drawn from the learned prior given z_b (B, Db), noise eps (B, K, Dj)."""
        return self.run_joints(z_b, prior_eps=eps)["z_j"]
