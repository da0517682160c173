"""The training loss (paper eq. 15) and its MMD estimator, on normalised tensors."""

from __future__ import annotations

import torch
from torch.nn import functional as F

from snakeloco.model.vae.network import HierarchicalVAE


def gaussian_mmd(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Squared MMD between samples x (N, D) and y (M, D) with a Gaussian kernel (V-statistic).

    The biased estimator (diagonal kept) is used because it is never negative: minimising the
    unbiased one lets the optimiser chase noise below zero.

    Bandwidth rule: k(a, b) = exp(-||a - b||^2 / (2 D)), i.e. sigma^2 = D, the scale of the squared
    distance between two draws of a D-dimensional unit Gaussian (the InfoVAE/WAE choice). Fixed, so the
    loss is comparable across batches and checkpoints.
    """
    d = x.shape[1]

    def k(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.exp(-torch.cdist(a, b).pow(2) / (2.0 * d))

    return k(x, x).mean() + k(y, y).mean() - 2.0 * k(x, y).mean()


def loss_terms(
    model: HierarchicalVAE, shape: torch.Tensor, body: torch.Tensor, stats: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Paper eq. 15 on a normalised batch (stats (B, n_stats): normalised body statistics) plus the
    statistics term: rec_joint + alpha rec_body + alpha_stats rec_stats + beta MMD_k + gamma MMD_B."""
    cfg = model.cfg
    out = model(shape, body)
    rec_joint = F.mse_loss(out.shape, shape)
    rec_body = F.mse_loss(out.body, body)
    rec_stats = F.mse_loss(out.stats, stats)
    mmd_joint = gaussian_mmd(out.z_j.flatten(0, 1), out.prior_sample.flatten(0, 1))
    mmd_body = gaussian_mmd(out.z_b, torch.randn_like(out.z_b))
    total = (
        rec_joint
        + cfg.alpha * rec_body
        + cfg.alpha_stats * rec_stats
        + cfg.beta * mmd_joint
        + cfg.gamma * mmd_body
    )
    return {
        "loss": total,
        "rec_joint": rec_joint,
        "rec_body": rec_body,
        "rec_stats": rec_stats,
        "mmd_joint": mmd_joint,
        "mmd_body": mmd_body,
    }
