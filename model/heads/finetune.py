"""The two fine-tuning stages of ``snakeloco calibrate`` (``model.heads.calibrate`` says why).

Stage 1 fits the statistics head (signal CNN and MLP) to (shape -> replayed statistics) pairs; stage
2 fits the body decoder (its z_B / z_k input layer, the FiLM layer and the transposed CNN) to
(latents, predicted statistics -> replayed body path) pairs. Both mix the model's replayed prior
gaits with the training records, train only their own modules, and keep the epoch with the lowest
held-out loss. The body encoder, the GRUs, the normalisation and so every decoded shape and every
z_B posterior stay as trained.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from snakeloco.model.api import GaitModel
from snakeloco.model.heads.fitting import fit_best
from snakeloco.model.vae.stats import median_relative_errors


class Schedule(Protocol):
    """How a stage fits (``model.heads.calibrate.CalibrateConfig`` is one; this module does not import
    it, so calibration sits above fine-tuning and never the other way)."""

    epochs: int
    lr: float
    batch_size: int
    seed: int


BATCH = 512
"""Records per forward pass when predicting or scoring whole sets (no gradients)."""


def head_loss(p: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Loss of the statistics head: mean absolute error of normalised statistics (B, 4).

    Absolute error fits each statistic's conditional *median*, which is what the consistency check's
    median relative error rewards; training's squared error fits the mean. It matters because the
    replays' statistics are skewed: with z_k = 0 most gaits barely leave the ground (vertical std
    ~5 mm) while a few hop (20 mm and more), and most roll a few hundredths of a radian while one in
    ten rolls over (the squared-error head predicted a median 2.3 rad where replays rolled -0.02
    rad; docs/model.md keeps the comparison).
    """
    return (p - y).abs().mean()


def fit_head(
    model: GaitModel,
    train: tuple[np.ndarray, np.ndarray],
    held_out: dict[str, tuple[np.ndarray, np.ndarray]],
    cfg: Schedule,
    log: Callable[[str], None] | None,
) -> dict:
    """Stage 1: fit the statistics head to (joint shapes (N, n_joints, L, 2) rad, statistics vectors (N, 4))
    pairs with ``cfg``'s epochs, learning rate, batch size and seed. ``held_out`` names sets scored before and after (median relative error per statistic);
    the mean head loss over its "generated" and "dataset" sets chooses the best epoch."""
    net = model.net
    x_tr, y_tr = model.normalize_shape(train[0]), model.normalize_stats(train[1])
    sets = {k: (model.normalize_shape(s), model.normalize_stats(v)) for k, (s, v) in held_out.items()}

    @torch.no_grad()
    def predict(x: torch.Tensor) -> torch.Tensor:
        net.eval()
        return torch.cat([net.predict_stats(x[i : i + BATCH]) for i in range(0, len(x), BATCH)])

    def errors() -> dict[str, dict[str, float]]:
        return {
            k: median_relative_errors(model.stats_from_network(predict(x)), model.stats_from_network(y))
            for k, (x, y) in sets.items()
        }

    def val_loss() -> float:
        # Both held-out kinds count equally: generated gaits and measured records.
        return 0.5 * sum(float(head_loss(predict(sets[k][0]), sets[k][1])) for k in ("generated", "dataset"))

    before = errors()
    head = torch.nn.ModuleList([net.signal_net, net.stats_head])
    best_epoch, history = fit_best(
        net,
        head,
        len(x_tr),
        lambda idx: head_loss(net.predict_stats(x_tr[idx]), y_tr[idx]),
        val_loss,
        cfg.epochs,
        cfg.lr,
        cfg.batch_size,
        cfg.seed,
        log,
        min_batch=2,
    )
    return {"best_epoch": best_epoch, "history": history, "before": before, "after": errors()}


def fit_path_decoder(
    model: GaitModel,
    records: tuple[np.ndarray, np.ndarray],
    records_val: tuple[np.ndarray, np.ndarray],
    gaits: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    gaits_val: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    cfg: Schedule,
    log: Callable[[str], None] | None,
) -> dict:
    """Stage 2: fit the body decoder to replayed paths.

    ``records``: (shapes, body series) of training records, which enter with their posterior-mean
    latents; ``gaits``: (shapes, body series, z_b, z_j) of replayed generated gaits, which enter with
    the latents they were decoded from. Both with the (calibrated) statistics predicted from their
    shapes. Loss: normalised MSE of the body series.
    """
    net = model.net
    net.eval()

    @torch.no_grad()
    def inputs(shape, body, z_b=None, z_j=None) -> list[torch.Tensor]:
        x, y = model.normalize_shape(np.asarray(shape, np.float64)), model.normalize_body(body)
        st = torch.cat([net.predict_stats(x[i : i + BATCH]) for i in range(0, len(x), BATCH)])
        if z_b is None:  # a record: its posterior means
            zb, zj = [], []
            for i in range(0, len(x), BATCH):
                mu, _ = net.encode_body(y[i : i + BATCH], x[i : i + BATCH])
                zb.append(mu)
                zj.append(net.run_joints(mu, x[i : i + BATCH], sample_posterior=False)["z_j"])
            return [torch.cat(zb), torch.cat(zj), st, x, y]
        f32 = torch.float32
        return [torch.as_tensor(z_b, dtype=f32), torch.as_tensor(z_j, dtype=f32), st, x, y]

    rec_va, gen_va = inputs(*records_val), inputs(*gaits_val)
    train_set = [torch.cat(parts) for parts in zip(inputs(*records), inputs(*gaits), strict=True)]

    @torch.no_grad()
    def mse(t: list[torch.Tensor]) -> float:
        net.eval()
        z_b, z_j, st, x, y = t
        part = lambda i: slice(i, i + BATCH)  # noqa: E731
        sse = sum(
            ((net.decode_body(z_b[part(i)], z_j[part(i)], st[part(i)], x[part(i)]) - y[part(i)]) ** 2)
            .sum()
            .item()
            for i in range(0, len(y), BATCH)
        )
        return sse / y.numel()

    before = {"generated": mse(gen_va), "dataset": mse(rec_va)}

    def batch_loss(idx: torch.Tensor) -> torch.Tensor:
        z_b, z_j, st, x, y = (t[idx] for t in train_set)
        return torch.nn.functional.mse_loss(net.decode_body(z_b, z_j, st, x), y)

    modules = [
        net.dec_in,
        *([net.dec_film] if net.cfg.body_sees_stats else []),
        *([net.body_sig] if net.cfg.body_sees_signals else []),
        *([net.body_gait] if net.cfg.body_sees_signals and net.cfg.body_signals_see_shape else []),
        net.decoder,
    ]
    best_epoch, _ = fit_best(
        net,
        torch.nn.ModuleList(modules),
        len(train_set[0]),
        batch_loss,
        lambda: 0.5 * (mse(gen_va) + mse(rec_va)),
        cfg.epochs,
        cfg.lr,
        cfg.batch_size,
        cfg.seed + 1,
        log,
        label="path ",
    )
    after = {"generated": mse(gen_va), "dataset": mse(rec_va)}
    if log:
        log(
            "body path, normalised MSE before -> after: held-out generated gaits "
            f"{before['generated']:.3f} -> {after['generated']:.3f}, "
            f"held-out records {before['dataset']:.3f} -> {after['dataset']:.3f}"
        )
    return {"best_epoch": best_epoch, "mse_before": before, "mse_after": after}
