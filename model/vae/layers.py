"""The network's building blocks and what its forward pass returns (``model.vae.network``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


class SeparableConv(nn.Module):
    """A depthwise then pointwise 1-D convolution (same length out)."""

    def __init__(self, c_in: int, c_out: int, kernel: int) -> None:
        super().__init__()
        self.depthwise = nn.Conv1d(c_in, c_in, kernel, padding=kernel // 2, groups=c_in)
        self.pointwise = nn.Conv1d(c_in, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pointwise(self.depthwise(x))


def gaussian_head(d_in: int, d_out: int, hidden: int) -> nn.Module:
    """An MLP to a Gaussian's mean and log-variance, concatenated: (..., d_in) -> (..., 2 d_out)."""
    return nn.Sequential(nn.Linear(d_in, hidden), nn.GELU(), nn.Linear(hidden, 2 * d_out))


@dataclass
class Output:
    """Everything a forward pass produces (normalised units)."""

    shape: torch.Tensor  # (B, K, L, 2)
    body: torch.Tensor  # (B, T, C)
    z_b: torch.Tensor  # (B, Db) sample
    z_b_mu: torch.Tensor  # (B, Db)
    z_j: torch.Tensor  # (B, K, Dj) posterior samples
    z_j_mu: torch.Tensor  # (B, K, Dj) posterior means
    prior_sample: torch.Tensor  # (B, K, Dj) samples of the learned prior
    stats: torch.Tensor  # (B, n_stats) normalised body statistics
