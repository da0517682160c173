"""``snakeloco evaluate``: reconstruction, latent health and the consistency of generated gaits.

Consistency is judged against the physics' own predictability: each generated gait's commands are
replayed as an ensemble (the commands plus K-1 copies with 1e-3 relative noise), and the decoded
body path is scored beside the ensemble's spread (``sim.consistency``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from model.api import GaitModel, load_pretrained
from model.metrics import median_interval, mmd_null_quantile, mmd_numpy, r2_overall, r2_per_channel
from model.stats import MODEL_RATE, median_relative_errors
from sim import BODY_CHANNELS, BODY_DOWNSAMPLE, DatasetError, Simulator, load_dataset, read_npz, write_npz
from sim.consistency import ENSEMBLE_NOISE, PREDICTABLE, compare, path_stats, perturbed_commands


def _stats_errors(predicted: dict[str, np.ndarray], body_ds: np.ndarray) -> dict[str, float]:
    return median_relative_errors(predicted, path_stats(body_ds, MODEL_RATE))


def reconstruction(model: GaitModel, shape: np.ndarray, body_ds: np.ndarray, batch: int = 512) -> dict:
    """R^2 of encode -> decode (posterior means) per channel and overall, in physical units."""
    z_b, z_j = [], []
    for i in range(0, len(shape), batch):
        a, b = model.encode(shape[i : i + batch], body_ds[i : i + batch])
        z_b.append(a)
        z_j.append(b)
    z_b, z_j = np.concatenate(z_b), np.concatenate(z_j)
    s_hat, b_hat = model.decode(z_b, z_j)
    n_l = shape.shape[2]
    shape_by_freq = shape.transpose(0, 1, 3, 2).reshape(-1, n_l)  # (N K 2, L)
    hat_by_freq = s_hat.transpose(0, 1, 3, 2).reshape(-1, n_l)
    return {
        "r2_shape": r2_overall(
            shape.reshape(len(shape), -1)[..., None], s_hat.reshape(len(shape), -1)[..., None]
        ),
        "r2_shape_per_freq": dict(
            zip(
                map(str, model.freqs.round(3)),
                r2_per_channel(shape_by_freq, hat_by_freq).tolist(),
                strict=True,
            )
        ),
        "r2_body": r2_overall(body_ds, b_hat),
        "r2_body_per_channel": dict(zip(BODY_CHANNELS, r2_per_channel(body_ds, b_hat).tolist(), strict=True)),
        # The statistics head on the true shapes: median relative error against the records' own.
        "stats_median_rel_err": _stats_errors(model.predict_stats(shape), body_ds),
        "z_b": z_b,
        "z_j": z_j,
    }


def latent_health(model: GaitModel, z_b: np.ndarray, z_j: np.ndarray, shape, body_ds, seed: int = 0) -> dict:
    """MMD(q(z_B) || N(0, I)) with its null 95th percentile, active units, inter/intra body variance."""
    rng = np.random.default_rng(seed)
    n = min(len(z_b), 1024)
    # Samples of the aggregate posterior q(z_B): posterior means plus their own noise.
    import torch

    with model._lock, torch.inference_mode():
        _, logvar = model.net.encode_body(model._norm_body(body_ds[:n]))
    std = np.exp(0.5 * logvar.numpy())
    q = z_b[:n] + std * rng.standard_normal(std.shape)
    mmd = mmd_numpy(q, rng.standard_normal(q.shape))
    null95 = mmd_null_quantile(n, q.shape[1], 0.95, seed=seed)
    active_b = int((z_b.var(axis=0) > 0.01).sum())
    active_j = int((z_j.reshape(-1, z_j.shape[-1]).var(axis=0) > 0.01).sum())
    # Body path variance across z_k draws with z_B fixed (intra) vs across z_B (inter).
    m, s = 32, 8
    zb = rng.standard_normal((m, model.z_b_dim))
    _, body0 = model.decode(zb)
    inter = body0.var(axis=0).mean()
    zj = model.sample_joint_latents(zb, s, seed=seed)  # (m, s, K, Dj)
    _, bodies = model.decode(np.repeat(zb, s, axis=0), zj.reshape(m * s, *zj.shape[2:]))
    intra = bodies.reshape(m, s, *bodies.shape[1:]).var(axis=1).mean()
    return {
        "mmd_zb": mmd,
        "mmd_zb_null95": null95,
        "active_units_zb": active_b,
        "active_units_zj": active_j,
        "inter_intra_ratio": float(inter / max(intra, 1e-12)),
    }


REPLAY_MODES = ("zk_zero", "zk_sampled")
"""The consistency check's z_k modes: z_k = 0, and z_k sampled from the learned prior."""


def replay_ensembles(
    model: GaitModel, shapes: np.ndarray, ensemble: int, seed: int, simulator: Simulator, progress=None
) -> tuple[np.ndarray, np.ndarray]:
    """Replay each decoded shape (n, 8, L, 2) as an ensemble: its commands plus ensemble-1 copies
    with ``sim.consistency.ENSEMBLE_NOISE`` relative noise (gait i's noise seeded with seed + i).

    Returns the body series at the model's rate, (n, ensemble, 500, 6) float32 (member 0 the
    unperturbed replay; zeros where a replay broke), and (n, ensemble) bool, which replays ran.
    """
    n, cfg = len(shapes), model.config.model
    bodies = np.zeros((n, ensemble, cfg.body_steps, cfg.body_channels), np.float32)
    ok = np.zeros((n, ensemble), bool)
    per_batch = max(1, (4 * simulator.workers) // ensemble + 1)
    for start in range(0, n, per_batch):
        idx = range(start, min(n, start + per_batch))
        cmds = np.concatenate(
            [perturbed_commands(model.commands(shapes[i]), ensemble, seed=seed + i) for i in idx]
        )  # (b K, T, 8)
        result = simulator.simulate(cmds)
        for j, i in enumerate(idx):
            members = range(j * ensemble, (j + 1) * ensemble)
            ok[i] = [result.failures[m] is None for m in members]
            bodies[i, ok[i]] = result.body[
                [m for m in members if result.failures[m] is None], ::BODY_DOWNSAMPLE
            ]
        if progress is not None:
            progress(len(idx))
    return bodies, ok


def save_replays(path: str | Path, replays: dict[str, dict[str, np.ndarray]], **drawn) -> None:
    """Write the consistency check's replays (``consistency``'s ``replays``) to an .npz (no pickle):
    per mode its decoded ``shapes``, ``z_j``, ``bodies`` and ``ok``, and the draw (``drawn``:
    n_prior, ensemble, seed, temperature) with the noise level and the robot's MJCF hash."""
    from sim import mjcf_sha256

    arrays = {f"{mode}/{k}": v for mode, r in replays.items() for k, v in r.items()}
    write_npz(path, noise=np.float64(ENSEMBLE_NOISE), mjcf_sha256=np.array(mjcf_sha256()), **drawn, **arrays)


def load_replays(
    path: str | Path, decoded: dict[str, np.ndarray], **drawn
) -> dict[str, dict[str, np.ndarray]]:
    """Read replays written by ``save_replays`` for the same draw (``drawn``) of the same decoded
    shapes (``decoded``: mode -> (n, 8, L, 2)) on the same robot; anything else is refused with a
    ``DatasetError`` naming the difference (a checkpoint with other decodes needs its own replays)."""
    from sim import mjcf_sha256

    path = Path(path)
    need = [
        "noise",
        "mjcf_sha256",
        *drawn,
        *(f"{m}/{k}" for m in decoded for k in ("shapes", "bodies", "ok")),
    ]
    stored = read_npz(path, "consistency-replays", need)
    asked = {"noise": ENSEMBLE_NOISE, **drawn}
    held = {k: stored[k].item() for k in asked}
    if held != asked:
        raise DatasetError(f"{path}: replays of {held}; this evaluation asks for {asked}")
    if str(stored["mjcf_sha256"]) != mjcf_sha256():
        raise DatasetError(
            f"{path}: replayed on another robot model (sim/snake.xml changed since); replay again"
        )
    out = {}
    for mode, shapes in decoded.items():
        r = {k.split("/", 1)[1]: v for k, v in stored.items() if k.startswith(mode + "/")}
        gap = float(np.abs(r["shapes"] - shapes).max()) if r["shapes"].shape == shapes.shape else float("inf")
        if gap > 1e-4:
            raise DatasetError(
                f"{path}: these replays are of other gaits ({mode}: the checkpoint's decodes differ by up "
                f"to {gap:.3g} rad); replay them for this checkpoint"
            )
        out[mode] = r
    return out


def consistency(
    model: GaitModel,
    n_prior: int = 256,
    ensemble: int = 8,
    seed: int = 0,
    workers: int | None = None,
    temperature: float = 1.0,
    progress=None,
    replays: str | Path | None = None,
) -> dict:
    """Decode n_prior z_B from the prior (z_k = 0 and z_k sampled), replay each as an ensemble, score.

    Returns per mode: medians of each figure over the gaits whose own (unperturbed) replay
    simulated cleanly, the count of those that broke (``n_broken``), and the fraction of all
    replays that broke; perturbed members that broke are left out of their gait's ensemble, as
    the designer does. ``replays``: an .npz of the ensembles' replays, read when it exists (it must
    hold the same draw of this checkpoint's decodes: ``load_replays``), else written after
    replaying. A calibration that leaves the decoded shapes alone (``snakeloco calibrate``) is
    then re-scored in seconds instead of replaying 2 n_prior ensembles.
    """
    rng = np.random.default_rng(seed)
    z_b = rng.standard_normal((n_prior, model.z_b_dim))
    z_zero = np.zeros((n_prior, model.config.model.n_joints, model.z_j_dim))
    z_sampled = model.sample_joint_latents(z_b, 1, seed=seed + 1, temperature=temperature)[:, 0]
    modes = dict(zip(REPLAY_MODES, (z_zero, z_sampled), strict=True))
    decoded = {name: model.decode_with_stats(z_b, z_j) for name, z_j in modes.items()}
    drawn = {"n_prior": n_prior, "ensemble": ensemble, "seed": seed, "temperature": temperature}
    if replays is not None and Path(replays).exists():
        stored = load_replays(replays, {name: d[0] for name, d in decoded.items()}, **drawn)
        if progress is not None:
            progress(len(modes) * n_prior)
    else:
        simulator = Simulator(workers or os.cpu_count() or 1)
        stored = {}
        for name, (shapes, _, _) in decoded.items():
            bodies, ok = replay_ensembles(model, shapes, ensemble, seed, simulator, progress)
            stored[name] = {"shapes": shapes, "z_j": modes[name], "bodies": bodies, "ok": ok}
        if replays is not None:
            save_replays(replays, stored, **drawn)
    report = {}
    for name, (_, bodies, stats) in decoded.items():
        sim_bodies, sim_ok = stored[name]["bodies"], stored[name]["ok"]
        rows, broken = [], 0
        for i in range(n_prior):
            ok = sim_ok[i]
            if not ok[0] or ok.sum() < 2:  # its own replay broke, or no spread is left
                broken += 1
                continue
            # As the designer does: perturbed members that broke leave the ensemble (counted).
            predicted = {k: float(v[i]) for k, v in stats.items()}
            row = compare(bodies[i], sim_bodies[i][ok].astype(np.float64), MODEL_RATE, predicted)
            row["ensemble_broken"] = float((~ok).sum())
            rows.append(row)
        keys = rows[0].keys() if rows else []
        summary = {k: float(np.median([r[k] for r in rows])) for k in keys}
        for k in PREDICTABLE:  # how far another draw of gaits could move the medians that are judged
            for part in ("err", "floor"):
                if rows:
                    summary[f"{k}_{part}_ci90"] = list(
                        median_interval([r[f"{k}_{part}"] for r in rows], seed=seed)
                    )
        summary["final_inside_fraction"] = float(np.mean([r["final_inside"] for r in rows])) if rows else 0.0
        summary["n_gaits"] = len(rows)
        summary["n_broken"] = broken
        summary["broken_replay_fraction"] = float((~sim_ok).sum()) / float(n_prior * ensemble)
        summary["n_gaits_with_a_broken_member"] = int(broken + sum(r["ensemble_broken"] > 0 for r in rows))
        summary["gaits"] = rows
        report[name] = summary
    return report


def evaluate(
    checkpoint: str | Path | None,
    data: str | Path,
    n_prior: int = 256,
    ensemble: int = 8,
    seed: int = 0,
    workers: int | None = None,
    progress=None,
    replays: str | Path | None = None,
) -> dict:
    """All evaluation figures for a checkpoint on a (held-out) dataset (``replays``: ``consistency``)."""
    model = load_pretrained(checkpoint)
    ds = load_dataset(data)
    shape, body_ds = ds.shape.astype(np.float64), ds.body_ds.astype(np.float64)
    rec = reconstruction(model, shape, body_ds)
    z_b, z_j = rec.pop("z_b"), rec.pop("z_j")
    out = {
        "checkpoint": str(model.path),
        "data": str(data),
        "n_samples": len(ds),
        "robot_warning": model.robot_warning(),
        **rec,
    }
    out.update(latent_health(model, z_b, z_j, shape, body_ds, seed=seed))
    if n_prior > 0:
        out["consistency"] = consistency(
            model, n_prior, ensemble, seed, workers, progress=progress, replays=replays
        )
    return out


def _interval(c: dict, key: str, part: str) -> str:
    lo, hi = c.get(f"{key}_{part}_ci90", (float("nan"), float("nan")))
    return f"[{lo:.3f}-{hi:.3f}]"


def format_report(r: dict) -> str:
    """Human-readable evaluation report."""
    lines = [f"WARNING: {r['robot_warning']}"] if r.get("robot_warning") else []
    lines += [
        f"checkpoint {r['checkpoint']} on {r['data']} ({r['n_samples']} samples)",
        f"R^2 joint shape {r['r2_shape']:.3f}; per frequency: "
        + ", ".join(f"{k} Hz {v:.3f}" for k, v in r["r2_shape_per_freq"].items()),
        f"R^2 body {r['r2_body']:.3f}; per channel: "
        + ", ".join(f"{k} {v:.3f}" for k, v in r["r2_body_per_channel"].items()),
        "body statistics predicted for the records' own shapes, median relative error: "
        + ", ".join(f"{k} {v:.3f}" for k, v in r["stats_median_rel_err"].items()),
        f"MMD(q(z_B) || N(0, I)) {r['mmd_zb']:.5f} (null 95th percentile {r['mmd_zb_null95']:.5f})",
        f"active units: z_B {r['active_units_zb']}, z_j {r['active_units_zj']}; "
        f"inter/intra body variance {r['inter_intra_ratio']:.2f}",
    ]
    for mode, c in r.get("consistency", {}).items():
        lines.append(
            f"consistency ({mode}): {c['n_gaits']} gaits, {c['n_broken']} whose own replay broke "
            f"({100 * c.get('broken_replay_fraction', float('nan')):.1f}% of all replays broke); medians:"
        )
        lines.append(
            f"  physics' spread: final position {c.get('final_spread', float('nan')):.2f} x displacement; "
            + ", ".join(f"{k} {c.get(k + '_spread', float('nan')):.3f}" for k in PREDICTABLE)
        )
        for part, label in (
            ("floor", "physics' floor (perturbed replays' mean vs the replay)"),
            ("err", "decoded vs simulated relative error"),
        ):
            lines.append(
                f"  {label} [90% bootstrap interval of the median]: "
                + ", ".join(
                    f"{k} {c.get(f'{k}_{part}', float('nan')):.3f} {_interval(c, k, part)}"
                    for k in PREDICTABLE
                )
            )
        lines.append(
            f"  xy-path R^2 {c.get('xy_r2', float('nan')):.3f}; decoded final position inside the ensemble's "
            f"spread in {100 * c['final_inside_fraction']:.0f}% (median distance {c.get('final_z', float('nan')):.1f} x RMS spread)"
        )
    return "\n".join(lines)
