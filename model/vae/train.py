"""Training: held-out split, Adam with a cyclical, exponentially decaying learning rate, best-on-validation.

Learning-rate schedule (paper: cyclical 2e-4..4e-3 with an 800-epoch period whose peak decays
exponentially). We keep the shape and scale the period to our shorter run: a triangular cycle of
``cycle_epochs`` epochs (half up, half down) between ``lr_min`` and a peak that starts at ``lr_max``
and is multiplied by ``peak_decay`` once per *cycle* (computed per step from the epoch position, so
the decay is per cycle, not per step as ``CyclicLR(mode="exp_range")`` would do; Adam's betas are
never cycled).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from snakeloco.model.checkpoint import (
    SCHEMA_VERSION,
    CheckpointConfig,
    Normalization,
    TrainSummary,
    save_checkpoint,
)
from snakeloco.model.options import PRESETS as PRESETS  # re-exported: the recipes live with the configs
from snakeloco.model.options import TrainConfig
from snakeloco.model.options import TrainPreset as TrainPreset
from snakeloco.model.vae.config import ModelConfig
from snakeloco.model.vae.losses import loss_terms
from snakeloco.model.vae.metrics import r2_overall, r2_per_channel
from snakeloco.model.vae.network import HierarchicalVAE
from snakeloco.model.vae.stats import stats_vector
from snakeloco.sim import BODY_DOWNSAMPLE, load_dataset, mjcf_sha256, servo_response, synthesis_phase
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.world.description import DEFAULT_WORLD


class TrainingError(RuntimeError):
    """Training cannot run or went wrong: the asked-for device is missing, or the loss diverged."""


def cyclic_lr(epoch: float, cfg: TrainConfig) -> float:
    """Learning rate at a (fractional) epoch: triangular between lr_min and a per-cycle decaying peak."""
    cycle, pos = divmod(epoch / cfg.cycle_epochs, 1.0)
    peak = cfg.lr_min + (cfg.lr_max - cfg.lr_min) * cfg.peak_decay**cycle
    tri = 1.0 - abs(2.0 * pos - 1.0)  # 0 -> 1 -> 0 over a cycle
    return cfg.lr_min + (peak - cfg.lr_min) * tri


SUPPORT_FRACTION = 0.01
"""A joint-frequency coefficient is in a family's support if its RMS amplitude over the training
records is above this fraction of the largest one's. Every coefficient of the paper's multisines is;
the structured families leave the frequencies they never draw (and the undulation family its pitch
joints) below 0.5% of it (docs/model.md)."""


def shape_support(shapes: np.ndarray) -> np.ndarray:
    """Joint shapes (N, n_joints, L, 2) rad -> (n_joints, L) bool: the coefficients the records excite."""
    rms = np.sqrt((np.asarray(shapes, np.float64) ** 2).sum(-1).mean(0))
    return rms > SUPPORT_FRACTION * rms.max()


def make_scheduler(
    opt: torch.optim.Optimizer, steps_per_epoch: int, cfg: TrainConfig
) -> torch.optim.lr_scheduler.LambdaLR:
    """Per-step LambdaLR realising ``cyclic_lr`` (the optimizer's base lr must be ``lr_max``)."""
    return torch.optim.lr_scheduler.LambdaLR(
        opt, lambda step: cyclic_lr(step / steps_per_epoch, cfg) / cfg.lr_max
    )


def init_signal_source(net: HierarchicalVAE, freqs: np.ndarray, norm: Normalization) -> None:
    """Give the statistics head's signal branch the inverse transform of ``sim.gaits.spectra`` at the body
    series' time stamps (every ``BODY_DOWNSAMPLE``-th command sample) and the shape normalisation."""
    phase = synthesis_phase(np.asarray(freqs, np.float64), stride=BODY_DOWNSAMPLE)  # (T, L)
    if phase.shape[0] != net.cfg.body_steps:
        raise ValueError(
            f"{phase.shape[0]} body time stamps for a model with body_steps={net.cfg.body_steps}"
        )
    a = norm.arrays()
    net.set_signal_source(
        torch.as_tensor(phase),
        torch.tensor(np.asarray(freqs, np.float64)),  # a copy: RECORD.freqs is read-only
        torch.as_tensor(a["shape_mean"]),
        torch.as_tensor(a["shape_std"]),
    )


def split_records(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Sorted (train, validation) record indices of a dataset of ``n``: a seeded permutation's first
    ``val_fraction`` (at least one) validates. Calibration redraws the split of a checkpoint with it."""
    perm = np.random.default_rng(seed).permutation(n)
    n_val = max(1, round(n * val_fraction))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


@torch.no_grad()
def evaluate_batches(
    net: HierarchicalVAE, shape: torch.Tensor, body: torch.Tensor, stats: torch.Tensor, batch: int, seed: int
) -> dict:
    """Mean loss terms (fixed noise seed) and posterior-mean reconstruction R^2 on normalised tensors."""
    net.eval()
    torch.manual_seed(seed)
    sums: dict[str, float] = {}
    rec_s, rec_b, rec_st = [], [], []
    for i in range(0, len(shape), batch):
        s, b, st = shape[i : i + batch], body[i : i + batch], stats[i : i + batch]
        terms = loss_terms(net, s, b, st)
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + v.item() * len(s)
        out = net(s, b, sample=False)
        rec_s.append(out.shape.cpu().numpy())
        rec_b.append(out.body.cpu().numpy())
        rec_st.append(out.stats.cpu().numpy())
    n = sum(len(r) for r in rec_s)
    result = {k: v / n for k, v in sums.items()}
    s_true = shape[:n].cpu().numpy()
    b_true = body[:n].cpu().numpy()
    s_hat, b_hat = np.concatenate(rec_s), np.concatenate(rec_b)
    result["r2_shape"] = r2_overall(
        s_true.reshape(n, -1)[..., None], s_hat.reshape(n, -1)[..., None], np.ones(1)
    )
    result["r2_body"] = r2_overall(b_true, b_hat, np.ones(b_true.shape[-1]))
    result["r2_body_channels"] = r2_per_channel(b_true, b_hat).tolist()
    result["r2_stats"] = r2_per_channel(stats[:n].cpu().numpy(), np.concatenate(rec_st)).tolist()
    return result


def train(
    data: str | Path,
    out: str | Path,
    cfg: TrainConfig | None = None,
    model_cfg: ModelConfig | None = None,
    log: Callable[[str], None] | None = print,
    progress: bool = True,
) -> TrainSummary:
    """Train on a dataset file and write the best-on-validation checkpoint and metrics.jsonl to ``out``."""
    from tqdm import tqdm

    cfg = cfg or TrainConfig()
    model_cfg = model_cfg or ModelConfig()
    t_start = time.perf_counter()
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise TrainingError(
            f"--device cuda was asked for, but torch {torch.__version__} sees no CUDA device "
            "(a CPU-only build, or no GPU/driver); train with --device cpu"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    ds = load_dataset(data)
    robot = ds.config.robot
    model_cfg = model_cfg.model_copy(update={"n_joints": robot.n_joints})  # the data's robot, not a flag
    shape_np = ds.shape.astype(np.float64)  # (N, K, L, 2) rad
    body_np = ds.body_ds.astype(np.float64)  # (N, 500, 6)
    train_idx, val_idx = split_records(len(ds), cfg.val_fraction, cfg.seed)
    stats_np = stats_vector(body_np)  # (N, 4)
    norm = Normalization.fit(shape_np[train_idx], body_np[train_idx], stats_np[train_idx])
    a = norm.arrays()

    def to_t(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=device)

    shape_all = to_t((shape_np - a["shape_mean"]) / a["shape_std"])
    body_all = to_t((body_np - a["body_mean"]) / a["body_std"])
    stats_all = to_t((stats_np - a["stats_mean"]) / a["stats_std"])
    s_tr, b_tr, st_tr = shape_all[train_idx], body_all[train_idx], stats_all[train_idx]
    s_va, b_va, st_va = shape_all[val_idx], body_all[val_idx], stats_all[val_idx]

    net = HierarchicalVAE(model_cfg)
    init_signal_source(net, ds.freqs, norm)
    net = net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr_max)
    steps_per_epoch = math.ceil(len(train_idx) / cfg.batch_size)
    sched = make_scheduler(opt, steps_per_epoch, cfg)
    ckpt_cfg = dict(
        schema_version=SCHEMA_VERSION,
        model=model_cfg,
        normalization=norm,
        freqs=ds.freqs.tolist(),
        dataset_meta_sha256=ds.meta_hash,
        family=ds.meta.get("family", "paper"),
        servo_response=servo_response(
            ds.rows("commands", train_idx), ds.rows("joint_angles", train_idx)
        ).tolist(),
        shape_support=shape_support(shape_np[train_idx]).tolist(),
        robot=None if robot == DEFAULT_ROBOT else robot,
        world=None if ds.config.world == DEFAULT_WORLD else ds.config.world,
        mjcf_sha256=ds.meta.get("mjcf_sha256") or mjcf_sha256(),  # what the records were simulated on
        train=cfg.model_dump(mode="json")
        | {"data": str(data), "n_train": len(train_idx), "n_val": len(val_idx)},
    )
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    best = float("inf")
    summary = TrainSummary(device=str(device))
    metrics_path = out / "metrics.jsonl"
    metrics_path.write_text("")
    bar = tqdm(range(cfg.epochs), desc="train", unit="epoch", disable=not progress)
    for epoch in bar:
        net.train()
        t0 = time.perf_counter()
        perm = torch.randperm(len(train_idx), generator=gen).to(device)
        sums: dict[str, float] = {}
        for i in range(steps_per_epoch):
            idx = perm[i * cfg.batch_size : (i + 1) * cfg.batch_size]
            if len(idx) < 2:
                continue
            terms = loss_terms(net, s_tr[idx], b_tr[idx], st_tr[idx])
            opt.zero_grad(set_to_none=True)
            terms["loss"].backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.grad_clip)
            opt.step()
            sched.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v.item() / steps_per_epoch
        if not math.isfinite(sums.get("loss", float("nan"))):
            raise TrainingError(
                f"training diverged at epoch {epoch}: loss {sums.get('loss')}; the best checkpoint so "
                f"far (if any) is in {out}"
            )
        val = evaluate_batches(net, s_va, b_va, st_va, 512, seed=cfg.seed)
        row = {
            "epoch": epoch,
            "lr": opt.param_groups[0]["lr"],
            "epoch_s": time.perf_counter() - t0,
            **{f"train_{k}": v for k, v in sums.items()},
            **{f"val_{k}": v for k, v in val.items()},
        }
        with metrics_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        bar.set_postfix(
            loss=f"{sums['loss']:.3f}",
            rec_j=f"{sums['rec_joint']:.3f}",
            rec_b=f"{sums['rec_body']:.3f}",
            mmd_k=f"{sums['mmd_joint']:.4f}",
            mmd_b=f"{sums['mmd_body']:.4f}",
            rec_s=f"{sums['rec_stats']:.3f}",
            val_r2=f"{val['r2_shape']:.3f}/{val['r2_body']:.3f}/{np.mean(val['r2_stats']):.3f}",
        )
        summary.epochs_run = epoch + 1
        if val["loss"] < best:
            best = val["loss"]
            summary.best_epoch, summary.best_val_loss = epoch, best
            summary.wall_time_s = time.perf_counter() - t_start
            save_checkpoint(out, net, CheckpointConfig(**ckpt_cfg, summary=summary))
    summary.wall_time_s = time.perf_counter() - t_start
    # Rewrite the config with the whole run's summary (weights stay the best epoch's).
    from snakeloco.model.checkpoint import load_checkpoint

    best_net, _ = load_checkpoint(out)
    save_checkpoint(out, best_net, CheckpointConfig(**ckpt_cfg, summary=summary))
    if log:
        log(
            f"best epoch {summary.best_epoch} (val loss {summary.best_val_loss:.4f}) of {summary.epochs_run}, "
            f"{summary.wall_time_s:.0f} s on {device}; checkpoint in {out}"
        )
    return summary
