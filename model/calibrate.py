"""``snakeloco calibrate``: fit the statistics head to the physics of the model's own gaits.

The statistics head (``HierarchicalVAE.predict_stats``) is trained on the dataset's measured joint
shapes. The designer, though, asks it about *decoded* shapes: with z_k = 0 (the paper's setting (a))
they are the prior's smooth, low-amplitude mean gaits, which no multisine record looks like, and
sampled z_k concentrate amplitude in fewer components. There the head extrapolates (measured on the
first shipped model: vertical-oscillation error 183% and net-roll error over 1000% with z_k = 0).

Calibration closes that gap with the simulator as teacher. For ``n`` z_B drawn from the prior it
decodes a gait in each z_k mode the designer offers (z_k = 0, and sampled at temperatures 0.5 and
1), for ``zero_samples`` (default 4 n) more z_B a gait with z_k = 0 only, and for
``sampled_samples`` (default 2 n) more z_B a gait at each sampled temperature; it resynthesises
the commands exactly as the designer does (``GaitModel.commands``), replays them once in MuJoCo and
measures the body statistics of the replay. The head (signal CNN and MLP, nothing
else) is then fine-tuned on those (decoded shape -> replayed statistics) pairs mixed with the
dataset's own (measured shape -> statistics) training pairs.

A second stage fits the body decoder (``path_fit``: by default all of it; or only the FiLM layer
through which it sees the predicted statistics, ``ModelConfig.body_sees_stats``) to the same
replays: decoded (z_B, z_k, statistics) -> the replay's body path, mixed with the dataset's
(posterior latents, statistics) -> recorded path. Why: the decoder learned its paths on records
only, and with z_k = 0 the statistics lie far outside them (net roll near 0 where records roll
~86 rad), so it extrapolated: with the first stage alone, 10% of z_k = 0 decoded final positions
fell inside the replays' spread (48 prior z_B); fitting the FiLM layer raised that to 61% (256
prior z_B), the whole decoder to 76%, and to 79% with 2048 extra z_k = 0 gaits, at the same
held-out body R^2 (``README.md``). The rest of the network (body encoder, GRUs, and the statistics
head once stage 1 is done), its normalisation and so every decoded *shape* and every z_B posterior
are unchanged. The z_B draws use their own seed (default 1000), disjoint from ``snakeloco
evaluate``'s consistency draws (seed 0), and a tenth of them (all modes of a z_B together) is held
out to choose the best epoch of each stage and to report the gain.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from model.api import GaitModel, load_pretrained
from model.checkpoint import CheckpointConfig, save_checkpoint
from model.stats import MODEL_RATE, STAT_NAMES, median_relative_errors, stats_dict, stats_vector
from sim import BODY_DOWNSAMPLE, DatasetError, Simulator, load_dataset, read_npz, write_npz

MODES: dict[str, float | None] = {"zk_zero": None, "zk_t0.5": 0.5, "zk_t1": 1.0}
"""z_k modes of the calibration gaits: None is z_k = 0, a number the prior's sampling temperature."""
ZERO_MODE = list(MODES.values()).index(None)
"""Index of the z_k = 0 mode (the ``mode`` array of the replayed gaits)."""


ZERO_SEED_OFFSET = 1000
"""The extra z_k = 0 draws (``zero_samples``) use seed + this, apart from the n shared draws."""
SAMPLED_SEED_OFFSET = 2000
"""The extra sampled-z_k draws (``sampled_samples``) use seed + this (z_B) and seed + this + 1 + mode
(z_k), apart from the shared and the extra z_k = 0 draws."""
SAMPLED_MODES = [m for m, t in enumerate(MODES.values()) if t is not None]
"""Indices of the sampled-z_k modes."""


def extra_zero_samples(n: int, zero_samples: int | None) -> int:
    """How many extra z_k = 0 draws a calibration of n prior samples makes: ``zero_samples``, or
    4 n where it is None. A ValueError names bad counts (none shared, or a negative extra count)."""
    extra = 4 * n if zero_samples is None else zero_samples
    if n < 1 or extra < 0:
        raise ValueError(
            "calibration needs at least 1 prior sample and no negative extra ones: --prior-samples "
            f"must be at least 1 and --zero-samples at least 0 (got {n}, {zero_samples})"
        )
    return extra


def extra_sampled_samples(n: int, sampled_samples: int | None) -> int:
    """How many extra sampled-z_k draws a calibration of n prior samples makes: ``sampled_samples``,
    or 2 n where it is None (each is decoded in every sampled mode). A ValueError names a negative count."""
    extra = 2 * n if sampled_samples is None else sampled_samples
    if extra < 0:
        raise ValueError(f"--sampled-samples must be at least 0 (got {sampled_samples})")
    return extra


def calibration_gait_count(n: int, zero_samples: int | None, sampled_samples: int | None) -> int:
    """How many gaits a calibration replays (``replay_prior_gaits``' M, before broken ones are
    dropped), with the defaults of ``extra_zero_samples`` and ``extra_sampled_samples``; their
    ValueError names a bad count."""
    zero = extra_zero_samples(n, zero_samples)
    sampled = extra_sampled_samples(n, sampled_samples)
    return n * len(MODES) + zero + sampled * len(SAMPLED_MODES)


def replay_prior_gaits(
    model: GaitModel,
    n: int,
    seed: int = 1000,
    workers: int | None = None,
    batch: int = 32,
    progress: Callable[[int], None] | None = None,
    zero_samples: int = 0,
    sampled_samples: int = 0,
) -> dict[str, np.ndarray]:
    """Decode n prior z_B in every ``MODES`` entry, plus ``zero_samples`` more z_B with z_k = 0
    only and ``sampled_samples`` more with z_k sampled (every sampled mode), replay each gait once
    and measure it.

    Why the extra z_k = 0 draws: there a gait is a fixed function of z_B, and whether it hops
    (vertical std 20 mm where most stay near 4 mm) is a property of the z_B that the head learns
    only from many neighbouring draws (measured on the shipped model, ``README.md``). The extra
    draws come from their own seed (seed + ``ZERO_SEED_OFFSET``), so adding them leaves the n
    shared draws as they were. Why the extra sampled draws: a sampled gait's net roll is a
    function of its whole shape, not of z_B, and the head's error on it fell with every doubling
    of the sampled gaits it saw (``README.md``). They use seed + ``SAMPLED_SEED_OFFSET`` and come
    last, so the gaits before them are the same with or without them.

    Returns arrays over the M = n * len(MODES) + zero_samples + sampled_samples * len(SAMPLED_MODES)
    gaits (broken replays dropped):
    ``shape`` (M, 8, L, 2) decoded rad, ``stats`` (M, 4) the replay's statistics vector
    (``model.stats``), ``body`` (M, 500, 6) the replay's body series at the model's rate, ``z_b``
    (M, Db) and ``z_j`` (M, 8, Dj) the latents decoded, ``z_index`` (M,) which z_B draw (the
    extra z_k = 0 ones numbered from n, the extra sampled ones from n + zero_samples), ``mode``
    (M,) index into ``MODES``, and ``broken`` (len(MODES),) counts.
    """
    z_b = np.random.default_rng(seed).standard_normal((n, model.z_b_dim))
    z_extra = np.random.default_rng(seed + ZERO_SEED_OFFSET).standard_normal((zero_samples, model.z_b_dim))
    z_sampled = np.random.default_rng(seed + SAMPLED_SEED_OFFSET).standard_normal(
        (sampled_samples, model.z_b_dim)
    )
    simulator = Simulator(workers or os.cpu_count() or 1)
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("shape", "stats", "body", "z_b", "z_j", "z_index", "mode")
    }
    broken = np.zeros(len(MODES), dtype=np.int64)
    n_joints = model.config.model.n_joints
    temperatures = list(MODES.values())
    # (mode, z_B, number of its first draw, seed of its z_k samples)
    draws = [(m, z_b, 0, seed + 1 + m) for m in range(len(MODES))]
    if zero_samples:
        draws.append((ZERO_MODE, z_extra, n, None))
    if sampled_samples:
        draws += [(m, z_sampled, n + zero_samples, seed + SAMPLED_SEED_OFFSET + 1 + m) for m in SAMPLED_MODES]
    for m, zb, first_index, zk_seed in draws:
        if not len(zb):
            continue
        z_j = np.zeros((len(zb), n_joints, model.z_j_dim))
        if temperatures[m] is not None:
            z_j = model.sample_joint_latents(zb, 1, seed=zk_seed, temperature=temperatures[m])[:, 0]
        shape, _ = model.decode(zb, z_j)
        for start in range(0, len(zb), batch):
            idx = np.arange(start, min(len(zb), start + batch))
            result = simulator.simulate(model.commands(shape[idx]))
            ok = np.array([f is None for f in result.failures])
            broken[m] += int((~ok).sum())
            body_ds = result.body[ok, ::BODY_DOWNSAMPLE]  # (b, 500, 6) at the model's rate
            parts["shape"].append(shape[idx][ok])
            parts["stats"].append(stats_vector(body_ds, MODEL_RATE))
            parts["body"].append(body_ds.astype(np.float32))
            parts["z_b"].append(zb[idx][ok])
            parts["z_j"].append(z_j[idx][ok])
            parts["z_index"].append(first_index + idx[ok])
            parts["mode"].append(np.full(int(ok.sum()), m))
            if progress is not None:
                progress(len(idx))
    return {**{k: np.concatenate(v) for k, v in parts.items()}, "broken": broken}


GAIT_KEYS = ("shape", "stats", "body", "z_b", "z_j", "z_index", "mode", "broken")


def save_gaits(
    path: str | Path,
    gaits: dict[str, np.ndarray],
    n: int,
    seed: int,
    zero_samples: int = 0,
    sampled_samples: int = 0,
) -> None:
    """Write ``replay_prior_gaits``' output to an .npz (no pickle) so a calibration can be rerun
    (other epochs, learning rate, loss) without replaying."""
    write_npz(
        path,
        n=np.int64(n),
        seed=np.int64(seed),
        zero_samples=np.int64(zero_samples),
        sampled_samples=np.int64(sampled_samples),
        modes=np.array(list(MODES)),
        **{k: gaits[k] for k in GAIT_KEYS},
    )


def load_gaits(
    path: str | Path,
    model: GaitModel,
    n: int,
    seed: int,
    zero_samples: int = 0,
    sampled_samples: int = 0,
) -> dict[str, np.ndarray]:
    """Read gaits written by ``save_gaits``; refuse ones drawn with another n, seed, number of extra
    z_k = 0 or sampled draws or mode list, or decoded by another checkpoint (their z_B and z_k are
    decoded again and must give the stored shapes). Files written before ``zero_samples`` or
    ``sampled_samples`` existed hold none."""
    path = Path(path)
    stored = read_npz(path, "calibration-gaits", (*GAIT_KEYS, "n", "seed", "modes"))
    stored_zero = int(stored.get("zero_samples", 0))
    stored_sampled = int(stored.get("sampled_samples", 0))
    drawn = (int(stored["n"]), int(stored["seed"]), stored_zero, stored_sampled, list(stored["modes"]))
    if drawn != (n, seed, zero_samples, sampled_samples, list(MODES)):
        raise DatasetError(
            f"{path}: gaits of {drawn[0]} z_B (+{stored_zero} at z_k = 0, +{stored_sampled} sampled) with "
            f"seed {drawn[1]} and modes {drawn[4]}; asked for {n} (+{zero_samples}, +{sampled_samples}) "
            f"with seed {seed} and modes {list(MODES)}"
        )
    if len(stored["z_b"]):
        # The first and the last gaits: the shared draws and, where there are any, the extra ones.
        check = np.unique(np.r_[np.arange(min(32, len(stored["z_b"]))), np.arange(len(stored["z_b"]))[-32:]])
        shape, _ = model.decode(stored["z_b"][check], stored["z_j"][check])
        gap = float(np.abs(shape - stored["shape"][check]).max())
        if gap > 1e-4:
            raise DatasetError(
                f"{path}: these gaits were decoded by another checkpoint (decoding their latents again "
                f"differs by up to {gap:.3g} rad); replay them for this one"
            )
    return {k: stored[k] for k in GAIT_KEYS}


HeadLoss = Literal["l1", "mse"]

PathFit = Literal["decoder", "film"]
"""What calibration's second stage fits: "decoder", the whole body decoder (its z_B / z_k input
layer, the FiLM layer and the transposed CNN); "film", the FiLM layer only (the first calibrated
release)."""


def check_sampled_repeat(sampled_repeat: int) -> None:
    """A ValueError unless ``sampled_repeat`` (``head_training_gaits``) is at least 1."""
    if sampled_repeat < 1:
        raise ValueError(f"sampled_repeat must be at least 1, got {sampled_repeat}")


def head_training_gaits(
    gaits: dict[str, np.ndarray], held_out: np.ndarray, sampled_repeat: int = 1
) -> np.ndarray:
    """Indices of the generated gaits the statistics head trains on: those not ``held_out`` (bool
    mask), with the gaits of sampled z_k (every mode but z_k = 0) listed ``sampled_repeat`` times.

    Why it was tried: without extra sampled draws the mix is 2560 z_k = 0 gaits to 1024 sampled
    ones, and the head's error on sampled gaits' net roll stayed ~10 points above the physics'
    floor. Repeating them did not lower it; new sampled draws (``sampled_samples``) did
    (``docs/model-notes.md``).
    """
    check_sampled_repeat(sampled_repeat)
    train = np.flatnonzero(~held_out)
    sampled = train[gaits["mode"][train] != ZERO_MODE]
    return np.concatenate([train, *[sampled] * (sampled_repeat - 1)])


def _path_modules(net, path_fit: PathFit) -> list[torch.nn.Module]:
    """The modules of ``net`` that calibration's second stage fits (none: no second stage, as for
    "film" on a decoder without the FiLM layer); a ValueError names an unknown ``path_fit``."""
    film = [net.dec_film] if net.cfg.body_sees_stats else []
    if path_fit == "film":
        return film
    if path_fit == "decoder":
        return [net.dec_in, *film, net.decoder]
    raise ValueError(f"path_fit must be 'decoder' or 'film', not {path_fit!r}")


def head_loss(p: torch.Tensor, y: torch.Tensor, kind: HeadLoss = "mse") -> torch.Tensor:
    """Loss of the statistics head: predicted and target normalised statistics (B, 4) -> scalar.

    "mse" (training's loss) fits each statistic's conditional mean; "l1" its conditional median,
    which is what the median relative error of the consistency check rewards. It matters where
    the replays' statistics are skewed: with z_k = 0 most gaits barely leave the ground (vertical
    std ~5 mm) while a few hop (20 mm and more), so the mean of log vertical std sits above the
    typical gait (the squared-error head overestimated it by a median 19%), and most roll a few
    hundredths of a radian while one in ten rolls over (the squared-error head predicted a median
    2.3 rad where replays rolled -0.02 rad).
    """
    e = p - y  # (B, 4)
    return e.abs().mean() if kind == "l1" else (e**2).mean()


def _head_parameters(net) -> list[torch.nn.Parameter]:
    return [*net.signal_net.parameters(), *net.stats_head.parameters()]


def _fit_best(
    net: torch.nn.Module,
    keep: torch.nn.Module,
    params: list[torch.nn.Parameter],
    n: int,
    batch_loss: Callable[[torch.Tensor], torch.Tensor],
    val_loss: Callable[[], float],
    epochs: int,
    lr: float,
    batch_size: int,
    seed: int,
    log: Callable[[str], None] | None,
    label: str = "",
    min_batch: int = 1,
) -> tuple[int, list[dict]]:
    """Train ``params`` (the rest of ``net`` frozen) on ``n`` examples, shuffled batches, Adam with
    cosine decay to 1% of ``lr``; ``keep`` (the module holding ``params``) is restored to the epoch
    with the lowest ``val_loss`` (the untrained start counts as epoch -1). ``batch_loss`` takes a
    batch's example indices; batches under ``min_batch`` examples are skipped.
    Returns the best epoch and the per-epoch history (train and validation loss)."""
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    steps = math.ceil(n / batch_size)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps, eta_min=lr * 0.01)
    gen = torch.Generator().manual_seed(seed)
    best, best_state, best_epoch = val_loss(), None, -1
    history = []
    for epoch in range(epochs):
        net.train()
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(steps):
            idx = perm[i * batch_size : (i + 1) * batch_size]
            if len(idx) < min_batch:
                continue
            loss = batch_loss(idx)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() / steps
        v = val_loss()
        history.append({"epoch": epoch, "train_loss": total, "val_loss": v})
        if log:
            log(f"  {label}epoch {epoch}: train loss {total:.4f}, val loss {v:.4f}")
        if v < best:
            best, best_epoch = v, epoch
            best_state = {k: t.detach().clone() for k, t in keep.state_dict().items()}
    if best_state is not None:
        keep.load_state_dict(best_state)
    for p in params:
        p.requires_grad_(False)
    net.eval()
    return best_epoch, history


def _fit_path_decoder(
    model: GaitModel,
    d_shape: np.ndarray,
    d_body: np.ndarray,
    v_shape: np.ndarray,
    v_body: np.ndarray,
    gaits: dict[str, np.ndarray],
    g_val: np.ndarray,
    epochs: int,
    lr: float,
    batch_size: int,
    seed: int,
    log: Callable[[str], None] | None,
    path_fit: PathFit = "decoder",
) -> dict:
    """Stage 2: fit the body decoder's ``_path_modules`` to replayed paths (module docstring).

    Records enter with their posterior-mean z_B and the (now calibrated) statistics predicted from
    their shapes; generated gaits with the z_B and z_k they were decoded from and the statistics
    predicted from their decoded shapes. Loss: normalised MSE of the body series.
    """
    net = model.net
    net.eval()

    @torch.no_grad()
    def inputs(shape: np.ndarray, body: np.ndarray, z_b: np.ndarray | None, z_j: np.ndarray | None):
        x = model._norm_shape(np.asarray(shape, np.float64))
        y = model._norm_body(np.asarray(body, np.float64))
        st, zb, zj = [], [], []
        for i in range(0, len(x), 512):
            st.append(net.predict_stats(x[i : i + 512]))
            if z_b is None:  # a record: its posterior means
                mu, _ = net.encode_body(y[i : i + 512])
                zb.append(mu)
                zj.append(net.run_joints(mu, x[i : i + 512], sample_posterior=False)["z_j"])
        if z_b is None:
            return torch.cat(zb), torch.cat(zj), torch.cat(st), y
        f32 = torch.float32
        return torch.as_tensor(z_b, dtype=f32), torch.as_tensor(z_j, dtype=f32), torch.cat(st), y

    rec_tr = inputs(d_shape, d_body, None, None)
    rec_va = inputs(v_shape, v_body, None, None)
    gen_tr = inputs(gaits["shape"][~g_val], gaits["body"][~g_val], gaits["z_b"][~g_val], gaits["z_j"][~g_val])
    gen_va = inputs(gaits["shape"][g_val], gaits["body"][g_val], gaits["z_b"][g_val], gaits["z_j"][g_val])
    train_set = [torch.cat(parts) for parts in zip(rec_tr, gen_tr, strict=True)]

    @torch.no_grad()
    def mse(t: list[torch.Tensor]) -> float:
        net.eval()
        z_b, z_j, st, y = t
        err = [
            ((net.decode_body(z_b[i : i + 512], z_j[i : i + 512], st[i : i + 512]) - y[i : i + 512]) ** 2)
            .sum()
            .item()
            for i in range(0, len(y), 512)
        ]
        return sum(err) / y.numel()

    def val_loss() -> float:
        return 0.5 * (mse(gen_va) + mse(rec_va))

    before = {"generated": mse(gen_va), "dataset": mse(rec_va)}

    def batch_loss(idx: torch.Tensor) -> torch.Tensor:
        z_b, z_j, st, y = (t[idx] for t in train_set)
        return torch.nn.functional.mse_loss(net.decode_body(z_b, z_j, st), y)

    modules = torch.nn.ModuleList(_path_modules(net, path_fit))
    best_epoch, _ = _fit_best(
        net,
        modules,
        list(modules.parameters()),
        len(train_set[0]),
        batch_loss,
        val_loss,
        epochs,
        lr,
        batch_size,
        seed + 1,
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
    return {"fit": path_fit, "best_epoch": best_epoch, "mse_before": before, "mse_after": after}


def calibrate(
    checkpoint: str | Path | None,
    data: str | Path,
    out: str | Path,
    n: int = 512,
    seed: int = 1000,
    epochs: int = 40,
    lr: float = 1e-2,
    batch_size: int = 128,
    workers: int | None = None,
    val_fraction: float = 0.1,
    log: Callable[[str], None] | None = print,
    progress: Callable[[int], None] | None = None,
    gaits: dict[str, np.ndarray] | None = None,
    gaits_path: str | Path | None = None,
    loss: HeadLoss = "l1",
    zero_samples: int | None = None,
    path_fit: PathFit = "decoder",
    sampled_repeat: int = 1,
    sampled_samples: int | None = None,
) -> dict:
    """Fine-tune the statistics head of ``checkpoint`` on replays of its own prior gaits; write to ``out``.

    ``data`` must be the dataset the checkpoint was trained on (its meta hash is checked): its
    training split keeps the head right on measured shapes. ``gaits``: reuse the output of
    ``replay_prior_gaits`` instead of simulating; ``gaits_path``: an .npz that is read when it
    exists (``load_gaits``), else written after replaying. ``loss``: the head's loss
    (``head_loss``). ``zero_samples``: extra z_B decoded with z_k = 0 only (``replay_prior_gaits``;
    None: 4 n); ``sampled_samples``: extra z_B decoded with z_k sampled in every sampled mode
    (None: 2 n). ``path_fit``: what the second stage fits (``PathFit``). ``sampled_repeat``: how many
    times the head sees each sampled-z_k gait per epoch (``head_training_gaits``). Returns the calibration
    summary (also stored in the checkpoint's ``summary.calibration``).
    """
    t_start = time.perf_counter()
    zero_samples = extra_zero_samples(n, zero_samples)
    sampled_samples = extra_sampled_samples(n, sampled_samples)
    model = load_pretrained(checkpoint)
    path_modules = _path_modules(model.net, path_fit)  # a bad choice is refused before any replay
    check_sampled_repeat(sampled_repeat)  # so is this
    config: CheckpointConfig = model.config
    ds = load_dataset(data)
    if ds.meta_hash != config.dataset_meta_sha256:
        raise DatasetError(
            f"{data} is not the dataset this checkpoint was trained on (meta hash {ds.meta_hash[:12]}, "
            f"checkpoint {config.dataset_meta_sha256[:12]})"
        )
    warning = model.robot_warning()
    if warning and log:
        log(f"warning: {warning}")
    if gaits is None and gaits_path is not None and Path(gaits_path).exists():
        gaits = load_gaits(gaits_path, model, n, seed, zero_samples, sampled_samples)
        if log:
            log(f"reusing {len(gaits['shape'])} replayed prior gaits from {gaits_path}")
    if gaits is None:
        t0 = time.perf_counter()
        gaits = replay_prior_gaits(
            model,
            n,
            seed,
            workers,
            progress=progress,
            zero_samples=zero_samples,
            sampled_samples=sampled_samples,
        )
        if log:
            log(
                f"replayed {len(gaits['shape'])} prior gaits in {time.perf_counter() - t0:.0f} s "
                f"(broken: {dict(zip(MODES, gaits['broken'].tolist(), strict=True))})"
            )
        if gaits_path is not None:
            save_gaits(gaits_path, gaits, n, seed, zero_samples, sampled_samples)
    # The dataset's training split, as ``train`` drew it.
    from model.train import _split

    train_cfg = config.train
    tr_idx, va_idx = _split(len(ds), float(train_cfg.get("val_fraction", 0.1)), int(train_cfg.get("seed", 0)))
    d_shape = ds.shape.astype(np.float64)
    d_stats = stats_vector(ds.body_ds.astype(np.float64))
    # Held-out z_B draws (all modes of one z_B together).
    z_ids = np.unique(gaits["z_index"])
    held = np.random.default_rng(seed).permutation(z_ids)[: max(1, round(len(z_ids) * val_fraction))]
    g_val = np.isin(gaits["z_index"], held)

    norm = config.normalization.arrays()
    s_mean, s_std = norm["stats_mean"].astype(np.float64), norm["stats_std"].astype(np.float64)

    def tensors(shape: np.ndarray, stats: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        x = model._norm_shape(shape)
        y = torch.as_tensor((stats - s_mean) / s_std, dtype=torch.float32)
        return x, y

    g_tr = head_training_gaits(gaits, g_val, sampled_repeat)
    x_tr, y_tr = tensors(
        np.concatenate([d_shape[tr_idx], gaits["shape"][g_tr]]),
        np.concatenate([d_stats[tr_idx], gaits["stats"][g_tr]]),
    )
    x_gv, y_gv = tensors(gaits["shape"][g_val], gaits["stats"][g_val])
    x_dv, y_dv = tensors(d_shape[va_idx], d_stats[va_idx])

    net = model.net
    for p in net.parameters():
        p.requires_grad_(False)

    @torch.no_grad()
    def predict(x: torch.Tensor) -> np.ndarray:
        net.eval()
        return np.concatenate([net.predict_stats(x[i : i + 512]).numpy() for i in range(0, len(x), 512)])

    def errors(p: np.ndarray, y: torch.Tensor) -> dict[str, float]:
        """Predicted and target normalised statistics -> median relative error per statistic."""
        return median_relative_errors(stats_dict(p * s_std + s_mean), stats_dict(y.numpy() * s_std + s_mean))

    def val_loss() -> float:
        # Both held-out sets count equally: generated gaits and measured records.
        return 0.5 * sum(
            float(head_loss(torch.as_tensor(predict(x)), y, loss)) for x, y in ((x_gv, y_gv), (x_dv, y_dv))
        )

    val_modes = gaits["mode"][g_val]

    def held_out_errors() -> dict[str, dict[str, float]]:
        """Median relative errors on the held-out generated gaits (all, and per z_k mode) and records."""
        p_gv = predict(x_gv)
        out = {"generated": errors(p_gv, y_gv), "dataset": errors(predict(x_dv), y_dv)}
        for m, mode in enumerate(MODES):
            sel = val_modes == m
            if sel.any():
                out[mode] = errors(p_gv[sel], y_gv[torch.as_tensor(sel)])
        return out

    before = held_out_errors()
    best_epoch, history = _fit_best(
        net,
        net,
        _head_parameters(net),
        len(x_tr),
        lambda idx: head_loss(net.predict_stats(x_tr[idx]), y_tr[idx], loss),
        val_loss,
        epochs,
        lr,
        batch_size,
        seed,
        log,
        min_batch=2,
    )
    after = held_out_errors()
    path_summary = None
    if path_modules:
        path_summary = _fit_path_decoder(
            model,
            ds.shape[tr_idx],
            ds.body_ds[tr_idx],
            ds.shape[va_idx],
            ds.body_ds[va_idx],
            gaits,
            g_val,
            epochs=epochs,
            lr=lr,
            batch_size=batch_size,
            seed=seed,
            log=log,
            path_fit=path_fit,
        )
    summary = {
        "prior_samples": n,
        "zero_samples": zero_samples,
        "sampled_samples": sampled_samples,
        "seed": seed,
        "modes": list(MODES),
        "gaits": len(gaits["shape"]),
        "broken": dict(zip(MODES, gaits["broken"].tolist(), strict=True)),
        "held_out_gaits": int(g_val.sum()),
        "epochs": epochs,
        "head_loss": loss,
        "sampled_repeat": sampled_repeat,
        "best_epoch": best_epoch,
        "median_rel_err_before": before,
        "median_rel_err_after": after,
        "history": history,
        "path": path_summary,
        "wall_time_s": time.perf_counter() - t_start,
        "data": str(data),
    }
    new_summary = config.summary.model_copy(update={"calibration": summary})
    save_checkpoint(out, net, config.model_copy(update={"summary": new_summary}))
    if log:
        log(
            "held-out generated gaits, median relative error before -> after: "
            + ", ".join(
                f"{k} {before['generated'][k]:.3f} -> {after['generated'][k]:.3f}" for k in STAT_NAMES
            )
        )
        for part in [*MODES, "dataset"]:
            if part in after:
                log(
                    f"  {'records' if part == 'dataset' else part}: "
                    + ", ".join(f"{k} {before[part][k]:.3f} -> {after[part][k]:.3f}" for k in STAT_NAMES)
                )
    return summary
