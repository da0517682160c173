"""``snakeloco calibrate``: fit the statistics head and the body decoder to the physics of the model's
own gaits.

The statistics head (``HierarchicalVAE.predict_stats``) is trained on the dataset's measured joint
shapes. The designer, though, asks it about *decoded* shapes: with z_k = 0 (the paper's setting (a))
they are the prior's smooth, low-amplitude mean gaits, which no multisine record looks like, and
sampled z_k concentrate amplitude in fewer components. There the head extrapolates (measured on the
first shipped model: vertical-oscillation error 183% and net-roll error over 1000% with z_k = 0).

Calibration closes that gap with the simulator as teacher. For ``prior_samples`` z_B drawn from the
prior it decodes a gait in each z_k mode of ``MODES`` (z_k = 0, and sampled at temperatures 0.5 and
1), for ``zero_samples`` (default 4x) more z_B a gait with z_k = 0 only, and for
``sampled_samples`` (default 2x) more z_B a gait at each sampled temperature; it resynthesises the
commands exactly as the designer does and replays each once in MuJoCo (``model.replays``). Stage 1
fine-tunes the head on those (decoded shape -> replayed statistics) pairs mixed with the dataset's
own training pairs; stage 2 fits the body decoder to the same replays, (z_B, z_k, statistics) ->
the replay's body path, mixed with the records (``model.heads.finetune``). Why stage 2: the decoder
learned its paths on records only, and with z_k = 0 the statistics lie far outside them (net roll
near 0 where records roll ~86 rad), so it extrapolated: with stage 1 alone 10% of z_k = 0 decoded
final positions fell inside the replays' spread (48 prior z_B); fitting the FiLM layer raised that
to 61% (256 prior z_B), the whole decoder to 76%, 79% with the extra z_k = 0 gaits (docs/model.md).
The z_B draws use their own seed (default 1000), disjoint from ``snakeloco evaluate``'s (seed 0), and
a tenth of them (all modes of a z_B together) is held out to choose the best epoch of each stage and
to report the gain.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from snakeloco.model.api import GaitModel
from snakeloco.model.checkpoint import check_trained_on, save_checkpoint
from snakeloco.model.heads.finetune import fit_head, fit_path_decoder
from snakeloco.model.options import MODES, SAMPLED_MODES, ZERO_MODE, CalibrateConfig
from snakeloco.model.replays import Fit, check_same_gaits, load_side_file, replay_shapes, save_side_file
from snakeloco.model.vae.stats import STAT_NAMES, stats_vector
from snakeloco.model.vae.train import split_records

ZERO_SEED_OFFSET = 1000
"""The extra z_k = 0 draws use seed + this, apart from the shared draws."""
SAMPLED_SEED_OFFSET = 2000
"""The extra sampled draws use seed + this (z_B) and seed + this + 1 + mode (z_k)."""
GAIT_KEYS = ("shape", "stats", "body", "z_b", "z_j", "z_index", "mode", "broken")
GAITS = "calibration-gaits"


def replay_prior_gaits(model: GaitModel, cfg: CalibrateConfig, fit: Fit) -> dict[str, np.ndarray]:
    """Decode ``cfg``'s prior z_B in their z_k modes, replay each gait once and measure it.

    The n shared z_B come first in every mode, then the extra z_k = 0 draws, then the extra sampled
    ones; each group has its own seed, so adding a group leaves the gaits before it as they were.

    Returns arrays over the M = ``cfg.gait_count`` gaits, broken replays dropped: ``shape``
    (M, n_joints, L, 2) decoded rad, ``stats`` (M, 4) the replay's statistics vector (``model.vae.stats``),
    ``body`` (M, 500, 6) the replay's body series at the model's rate, ``z_b`` (M, Db) and ``z_j``
    (M, n_joints, Dj) the latents decoded, ``z_index`` (M,) which z_B draw (the extra z_k = 0 ones numbered
    from n, the extra sampled ones from n + zero_count), ``mode`` (M,) index into ``MODES``, and
    ``broken`` (len(MODES),) counts.
    """
    n, seed, dim = cfg.prior_samples, cfg.seed, model.z_b_dim
    z_b = np.random.default_rng(seed).standard_normal((n, dim))
    z_extra = np.random.default_rng(seed + ZERO_SEED_OFFSET).standard_normal((cfg.zero_count, dim))
    z_sampled = np.random.default_rng(seed + SAMPLED_SEED_OFFSET).standard_normal((cfg.sampled_count, dim))
    # (mode, z_B, number of its first draw, seed of its z_k samples)
    draws = [(m, z_b, 0, seed + 1 + m) for m in range(len(MODES))]
    draws.append((ZERO_MODE, z_extra, n, 0))
    first_sampled = n + cfg.zero_count
    draws += [(m, z_sampled, first_sampled, seed + SAMPLED_SEED_OFFSET + 1 + m) for m in SAMPLED_MODES]
    temperatures = list(MODES.values())
    runner = fit.open_backend(model.robot, model.world)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in GAIT_KEYS if k != "broken"}
    broken = np.zeros(len(MODES), dtype=np.int64)
    try:
        for m, zb, first, zk_seed in draws:
            if not len(zb):
                continue
            z_j = model.joint_latents(zb, temperatures[m], seed=zk_seed)
            shape, _ = model.decode(zb, z_j)
            bodies, ok = replay_shapes(model, shape, runner, progress=fit.progress)
            ok = ok[:, 0]
            broken[m] += int((~ok).sum())
            body = bodies[ok, 0]  # (b, 500, 6) at the model's rate
            parts["shape"].append(shape[ok])
            parts["stats"].append(stats_vector(body.astype(np.float64)))
            parts["body"].append(body)
            parts["z_b"].append(zb[ok])
            parts["z_j"].append(z_j[ok])
            parts["z_index"].append(first + np.flatnonzero(ok))
            parts["mode"].append(np.full(int(ok.sum()), m))
    finally:
        runner.close()
    return {**{k: np.concatenate(v) for k, v in parts.items()}, "broken": broken}


def _drawn(cfg: CalibrateConfig) -> dict:
    """What identifies a calibration's draw in its gaits file."""
    return {
        "n": cfg.prior_samples,
        "seed": cfg.seed,
        "zero_samples": cfg.zero_count,
        "sampled_samples": cfg.sampled_count,
        "modes": list(MODES),
    }


def save_gaits(path: str | Path, gaits: dict[str, np.ndarray], cfg: CalibrateConfig, robot=None) -> None:
    """Write ``replay_prior_gaits``' output (replayed on ``robot``, None: the default) to an .npz side
    file (``model.replays``), so a calibration can be rerun (other epochs, learning rate) without
    replaying."""
    save_side_file(path, _drawn(cfg), robot, **{k: gaits[k] for k in GAIT_KEYS})


def load_gaits(path: str | Path, model: GaitModel, cfg: CalibrateConfig) -> dict[str, np.ndarray]:
    """Read gaits written by ``save_gaits``; refuse ones of another draw (counts, seed, modes), robot
    or checkpoint (their first and last 32 latents are decoded again and must give the stored
    shapes)."""
    stored = load_side_file(path, GAITS, _drawn(cfg), list(GAIT_KEYS), model.robot)
    if len(stored["z_b"]):
        check = np.unique(np.r_[np.arange(min(32, len(stored["z_b"]))), np.arange(len(stored["z_b"]))[-32:]])
        shape, _ = model.decode(stored["z_b"][check], stored["z_j"][check])
        check_same_gaits(path, stored["shape"][check], shape)
    return {k: stored[k] for k in GAIT_KEYS}


def calibrate(
    fit: Fit, cfg: CalibrateConfig | None = None, gaits: dict[str, np.ndarray] | None = None
) -> dict:
    """Calibrate ``fit.checkpoint`` on replays of its own prior gaits and write the result to
    ``fit.out``.

    ``fit.data`` must be the dataset the checkpoint was trained on (its meta hash is checked): its
    training split keeps the head and the decoder right on records. ``gaits``: reuse the output of
    ``replay_prior_gaits`` instead of simulating; ``fit.gaits_path``: a side file that is read when
    it exists (``load_gaits``), else written after replaying. Returns the calibration summary (also
    stored in the checkpoint's ``summary.calibration``).
    """
    cfg = cfg or CalibrateConfig()
    t_start = time.perf_counter()
    model, ds = fit.load()
    config = model.config
    check_trained_on(config, ds, fit.data)
    if gaits is None and fit.gaits_path is not None and Path(fit.gaits_path).exists():
        gaits = load_gaits(fit.gaits_path, model, cfg)
        fit.say(f"reusing {len(gaits['shape'])} replayed prior gaits from {fit.gaits_path}")
    if gaits is None:
        t0 = time.perf_counter()
        gaits = replay_prior_gaits(model, cfg, fit)
        fit.say(
            f"replayed {len(gaits['shape'])} prior gaits in {time.perf_counter() - t0:.0f} s "
            f"(broken: {dict(zip(MODES, gaits['broken'].tolist(), strict=True))})"
        )
        if fit.gaits_path is not None:
            save_gaits(fit.gaits_path, gaits, cfg, model.robot)

    # The dataset's training split, as ``train`` drew it, and the held-out z_B draws (all modes of one
    # z_B together).
    tr_idx, va_idx = split_records(
        len(ds), float(config.train.get("val_fraction", 0.1)), int(config.train.get("seed", 0))
    )
    d_shape, d_body = ds.shape.astype(np.float64), ds.body_ds.astype(np.float64)
    d_stats = stats_vector(d_body)
    z_ids = np.unique(gaits["z_index"])
    held = np.random.default_rng(cfg.seed).permutation(z_ids)[: max(1, round(len(z_ids) * cfg.val_fraction))]
    g_val = np.isin(gaits["z_index"], held)
    held_out = {
        "generated": (gaits["shape"][g_val], gaits["stats"][g_val]),
        "dataset": (d_shape[va_idx], d_stats[va_idx]),
    }
    for m, mode in enumerate(MODES):
        sel = g_val & (gaits["mode"] == m)
        if sel.any():
            held_out[mode] = (gaits["shape"][sel], gaits["stats"][sel])
    for p in model.net.parameters():
        p.requires_grad_(False)
    train_pairs = (
        np.concatenate([d_shape[tr_idx], gaits["shape"][~g_val]]),
        np.concatenate([d_stats[tr_idx], gaits["stats"][~g_val]]),
    )
    head = fit_head(model, train_pairs, held_out, cfg, fit.log)
    path = fit_path_decoder(
        model,
        (ds.shape[tr_idx], ds.body_ds[tr_idx]),
        (ds.shape[va_idx], ds.body_ds[va_idx]),
        tuple(gaits[k][~g_val] for k in ("shape", "body", "z_b", "z_j")),
        tuple(gaits[k][g_val] for k in ("shape", "body", "z_b", "z_j")),
        cfg,
        fit.log,
    )
    before, after = head["before"], head["after"]
    summary = {
        **cfg.model_dump(),
        "zero_samples": cfg.zero_count,
        "sampled_samples": cfg.sampled_count,
        "modes": list(MODES),
        "gaits": len(gaits["shape"]),
        "broken": dict(zip(MODES, gaits["broken"].tolist(), strict=True)),
        "held_out_gaits": int(g_val.sum()),
        "best_epoch": head["best_epoch"],
        "median_rel_err_before": before,
        "median_rel_err_after": after,
        "history": head["history"],
        "path": path,
        "wall_time_s": time.perf_counter() - t_start,
        "data": str(fit.data),
    }
    new_summary = config.summary.model_copy(update={"calibration": summary})
    save_checkpoint(fit.out, model.net, config.model_copy(update={"summary": new_summary}))
    fit.say(
        "held-out generated gaits, median relative error before -> after: "
        + ", ".join(f"{k} {before['generated'][k]:.3f} -> {after['generated'][k]:.3f}" for k in STAT_NAMES)
    )
    for part in [*MODES, "dataset"]:
        if part in after:
            fit.say(
                f"  {'records' if part == 'dataset' else part}: "
                + ", ".join(f"{k} {before[part][k]:.3f} -> {after[part][k]:.3f}" for k in STAT_NAMES)
            )
    return summary
