"""Reconstruction and latent metrics shared by training and evaluation (numpy, any units)."""

from __future__ import annotations

import numpy as np


def r2_per_channel(target: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """R^2 = 1 - SSE / SST per last-axis channel, pooling every other axis: (..., C) -> (C,)."""
    t = target.reshape(-1, target.shape[-1])
    p = pred.reshape(-1, pred.shape[-1])
    sse = ((t - p) ** 2).sum(axis=0)
    sst = ((t - t.mean(axis=0)) ** 2).sum(axis=0)
    return 1.0 - sse / np.maximum(sst, 1e-30)


def r2_overall(target: np.ndarray, pred: np.ndarray, scale: np.ndarray | None = None) -> float:
    """R^2 over all elements after dividing each channel by ``scale`` (C,) (default: its std)."""
    t = target.reshape(-1, target.shape[-1])
    p = pred.reshape(-1, pred.shape[-1])
    s = t.std(axis=0) if scale is None else np.asarray(scale)
    s = np.maximum(s, 1e-30)
    t, p = t / s, p / s
    return float(1.0 - ((t - p) ** 2).sum() / np.maximum(((t - t.mean(axis=0)) ** 2).sum(), 1e-30))


def mmd_numpy(x: np.ndarray, y: np.ndarray) -> float:
    """Squared Gaussian-kernel MMD (V-statistic, sigma^2 = D), as ``model.vae.losses.gaussian_mmd``."""
    d = x.shape[1]

    def k(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
        return np.exp(-np.maximum(sq, 0.0) / (2.0 * d))

    return float(k(x, x).mean() + k(y, y).mean() - 2.0 * k(x, y).mean())


def mmd_null_quantile(n: int, d: int, q: float = 0.95, repeats: int = 200, seed: int = 0) -> float:
    """q-quantile of the MMD between two independent N(0, I) samples of size n: the null distribution."""
    rng = np.random.default_rng(seed)
    vals = [mmd_numpy(rng.standard_normal((n, d)), rng.standard_normal((n, d))) for _ in range(repeats)]
    return float(np.quantile(vals, q))


def median_interval(
    values: np.ndarray, level: float = 0.9, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile-bootstrap interval of the median of ``values`` (1-D): (low, high) at ``level``.

    Why: consistency errors are medians over a few hundred gaits whose per-gait errors can be
    bimodal (with z_k = 0 a gait either hops or stays near the ground), so the median alone hides
    how far another draw of gaits could move it.
    """
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return float("nan"), float("nan")
    idx = np.random.default_rng(seed).integers(0, len(v), (resamples, len(v)))
    med = np.median(v[idx], axis=1)
    tail = 0.5 * (1.0 - level)
    return float(np.quantile(med, tail)), float(np.quantile(med, 1.0 - tail))
