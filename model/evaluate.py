"""``snakeloco evaluate``: reconstruction, latent health and the consistency of generated gaits.

Consistency is judged against the physics' own predictability: each generated gait's commands are
replayed as an ensemble (the commands plus K-1 copies with 1e-3 relative noise), and the decoded
body path is scored beside the ensemble's spread (``sim.scores.consistency``).
"""

from __future__ import annotations

from contextlib import ExitStack, closing
from pathlib import Path

import numpy as np

from snakeloco.model.api import GaitModel, load_pretrained
from snakeloco.model.checkpoint import SHAPE_STD_FLOOR
from snakeloco.model.design.library import robustness_by_kind
from snakeloco.model.options import PRIOR_SAMPLES as PRIOR_SAMPLES  # re-exported
from snakeloco.model.options import ZK_MODES, ConsistencyConfig
from snakeloco.model.replays import check_same_gaits, load_side_file, replay_shapes, save_side_file
from snakeloco.model.vae.metrics import (
    median_interval,
    mmd_null_quantile,
    mmd_numpy,
    r2_overall,
    r2_per_channel,
)
from snakeloco.model.vae.stats import median_relative_errors
from snakeloco.sim import BODY_CHANNELS, BODY_RATE, load_dataset
from snakeloco.sim.gaits.structured import KINDS
from snakeloco.sim.physics.backend import BackendConfig, open_backend
from snakeloco.sim.scores.closed_loop import closed_loop_table
from snakeloco.sim.scores.consistency import (
    ENSEMBLE_NOISE,
    PREDICTABLE,
    compare,
    diversity,
    path_stats,
    perturbed_commands,
)


def _stats_errors(predicted: dict[str, np.ndarray], body_ds: np.ndarray) -> dict[str, float]:
    return median_relative_errors(predicted, path_stats(body_ds, BODY_RATE))


def reconstruction(model: GaitModel, shape: np.ndarray, body_ds: np.ndarray, batch: int = 512) -> dict:
    """R^2 of encode -> decode (posterior means) per channel and overall, in physical units."""
    z_b, z_j = [], []
    for i in range(0, len(shape), batch):
        a, b = model.encode(shape[i : i + batch], body_ds[i : i + batch])
        z_b.append(a)
        z_j.append(b)
    z_b, z_j = np.concatenate(z_b), np.concatenate(z_j)
    s_hat, b_hat = model.decode(z_b, z_j)
    s_zero, _ = model.decode(z_b)  # what a slider at the record's z_B draws (z_k = 0)
    # A projecting checkpoint decodes the member's shape and the path predicted for it from the gait
    # alone; the network's own decode sees the recorded path through the encoder: a reconstruction.
    _, b_raw = model.decode_raw(z_b, z_j) if model.projects else (None, b_hat)
    n_l = shape.shape[2]
    flat = shape.reshape(len(shape), -1)[..., None]  # (N, K L 2, 1): one pooled channel
    shape_by_freq = shape.transpose(0, 1, 3, 2).reshape(-1, n_l)  # (N K 2, L)
    hat_by_freq = s_hat.transpose(0, 1, 3, 2).reshape(-1, n_l)
    std = shape_by_freq.std(axis=0)
    excited_bins = std >= SHAPE_STD_FLOOR * std.max()
    return {
        "r2_shape": r2_overall(flat, s_hat.reshape(flat.shape)),
        # The designer's decoding: does z_B alone carry the record's gait?
        "r2_shape_zk_zero": r2_overall(flat, s_zero.reshape(flat.shape)),
        # A bin the data barely excite (a structured gait uses 1-3 of the 8) has ~1e-8 variance: its
        # R^2 says nothing, so it is reported as None ("not excited"), by the normalisation's rule.
        "r2_shape_per_freq": dict(
            zip(
                map(str, model.freqs.round(3)),
                [
                    r if excited else None
                    for r, excited in zip(
                        r2_per_channel(shape_by_freq, hat_by_freq).tolist(),
                        excited_bins,
                        strict=True,
                    )
                ],
                strict=True,
            )
        ),
        "r2_shape_per_joint": r2_per_channel(
            shape.transpose(0, 2, 3, 1).reshape(-1, shape.shape[1]),
            s_hat.transpose(0, 2, 3, 1).reshape(-1, shape.shape[1]),
        ).tolist(),
        "r2_body": r2_overall(body_ds, b_hat),
        "r2_body_per_channel": dict(zip(BODY_CHANNELS, r2_per_channel(body_ds, b_hat).tolist(), strict=True)),
        "r2_body_raw": r2_overall(body_ds, b_raw),
        "r2_body_raw_per_channel": dict(
            zip(BODY_CHANNELS, r2_per_channel(body_ds, b_raw).tolist(), strict=True)
        ),
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
    _, logvar = model.encode_body(body_ds[:n], np.asarray(shape[:n]))
    std = np.exp(0.5 * logvar)
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


REPLAYS = "consistency-replays"


def consistency(
    model: GaitModel,
    cfg: ConsistencyConfig | None = None,
    workers: int | None = None,
    progress=None,
    replays: str | Path | None = None,
    backend: BackendConfig | None = None,
    robustness: int = 0,
    closed_loop: int = 0,
) -> dict:
    """Decode ``cfg.prior_samples`` z_B from the sampler (or the N(0, I) prior, ``positions``; z_k = 0 and z_k
    sampled), replay each as an ensemble, score. Per mode also: the share of z_B the density flags
    as off the data and the figures per density component (``per_component``).

    Returns per mode: medians of each figure over the gaits whose own (unperturbed) replay
    simulated cleanly, the count of those that broke (``n_broken``), and the fraction of all
    replays that broke; perturbed members that broke are left out of their gait's ensemble, as
    the designer does. ``replays``: an .npz of the ensembles' replays, read when it exists (the same
    draw of this checkpoint's decodes: ``model.replays``), else written after replaying (re-scores a
    recalibrated checkpoint in seconds). ``backend``: where replays run (``sim.physics.backend``).
    ``robustness`` / ``closed_loop``: the first that many gaits of each mode also replayed on the
    default variation set open loop (``robustness_by_kind``) / closed loop (``closed_loop_table``).
    """
    cfg = cfg or ConsistencyConfig()
    n_prior, ensemble, seed, positions = cfg.prior_samples, cfg.ensemble, cfg.seed, cfg.positions
    if positions == "sampler":
        z_b = model.sample_z_b(n_prior, seed)
    else:
        z_b = np.random.default_rng(seed).standard_normal((n_prior, model.z_b_dim))
    density = model.config.density
    component = density.component_of(z_b) if density is not None else np.zeros(n_prior, np.int64)
    names = density.names if density is not None else ["prior"]
    off_data = model.off_data(z_b)
    modes = {
        name: model.joint_latents(z_b, ZK_MODES[name], seed=seed + 1) for name in dict.fromkeys(cfg.zk_modes)
    }
    decoded, kinds = {}, {}  # kinds: the family member each decode is, where the checkpoint decodes members
    for name, z_j in modes.items():
        if model.projects:
            members, _, shape, body, stats = model.decode_members(z_b, z_j)
            decoded[name], kinds[name] = (shape, body, stats), [m.kind for m in members]
        else:
            decoded[name], kinds[name] = model.decode_with_stats(z_b, z_j), None
    drawn = {
        "n_prior": n_prior,
        "ensemble": ensemble,
        "seed": seed,
        "temperature": ZK_MODES["zk_sampled"],
        "positions": positions,
    }
    if replays is not None and Path(replays).exists():
        need = [f"{name}/{k}" for name in modes for k in ("shapes", "bodies", "ok")]
        file = load_side_file(replays, REPLAYS, drawn, need, model.robot)
        stored = {}
        for name, (shapes, _, _) in decoded.items():
            stored[name] = {k: file[f"{name}/{k}"] for k in ("shapes", "bodies", "ok")}
            check_same_gaits(replays, stored[name]["shapes"], shapes, name)
        if progress is not None:
            progress(len(modes) * n_prior)
    else:
        runner = open_backend(backend, workers, robot=model.robot, world=model.world)
        stored = {}
        try:
            for name, (shapes, _, _) in decoded.items():
                bodies, ok = replay_shapes(model, shapes, runner, ensemble, seed, progress)
                stored[name] = {"shapes": shapes, "z_j": modes[name], "bodies": bodies, "ok": ok}
        finally:
            runner.close()
        if replays is not None:
            arrays = {f"{name}/{k}": v for name, r in stored.items() for k, v in r.items()}
            save_side_file(replays, drawn, model.robot, **arrays)
    report = {}
    with ExitStack() as stack:  # one backend for every mode's variation replays
        robust_runner = (
            stack.enter_context(closing(open_backend(backend, workers, robot=model.robot, world=model.world)))
            if robustness > 0
            else None
        )
        for name, (_, bodies, stats) in decoded.items():
            sim_bodies, sim_ok = stored[name]["bodies"], stored[name]["ok"]
            rows, broken = [], 0
            broken_in = np.zeros(len(names), np.int64)
            for i in range(n_prior):
                ok = sim_ok[i]
                if not ok[0] or ok.sum() < 2:  # its own replay broke, or no spread is left
                    broken += 1
                    broken_in[component[i]] += 1
                    continue
                # As the designer does: perturbed members that broke leave the ensemble (counted).
                predicted = {k: float(v[i]) for k, v in stats.items()}
                row = compare(bodies[i], sim_bodies[i][ok].astype(np.float64), BODY_RATE, predicted)
                row["ensemble_broken"] = float((~ok).sum())
                row["component"] = float(component[i])
                row["off_data"] = float(off_data[i])
                if kinds[name] is not None:
                    row["kind"] = float(KINDS.index(kinds[name][i]))
                rows.append(row)
            keys = [
                k
                for k in (rows[0] if rows else {})
                if k not in ("direction_deg", "rolls", "component", "off_data", "kind")
            ]
            summary = {k: float(np.median([r[k] for r in rows])) for k in keys}
            summary["diversity"] = diversity(rows)
            for k in PREDICTABLE:  # how far another draw of gaits could move the medians that are judged
                for part in ("err", "floor"):
                    if rows:
                        summary[f"{k}_{part}_ci90"] = list(
                            median_interval([r[f"{k}_{part}"] for r in rows], seed=seed)
                        )
            summary["final_inside_fraction"] = (
                float(np.mean([r["final_inside"] for r in rows])) if rows else 0.0
            )
            summary["n_gaits"] = len(rows)
            summary["n_broken"] = broken
            summary["broken_replay_fraction"] = float((~sim_ok).sum()) / float(n_prior * ensemble)
            summary["n_gaits_with_a_broken_member"] = int(
                broken + sum(r["ensemble_broken"] > 0 for r in rows)
            )
            summary["positions"] = positions
            summary["off_data_fraction"] = float(off_data.mean())
            summary["per_component"] = {
                c_name: {
                    "n_gaits": len(mine),
                    "n_broken": int(broken_in[c]),
                    **{
                        k: float(np.median([r[k] for r in mine])) if mine else float("nan")
                        for k in ("xy_r2", "final_error_rel", "final_spread")
                    },
                }
                for c, c_name in enumerate(names)
                for mine in [[r for r in rows if r["component"] == c]]
            }
            if kinds[name] is not None:
                summary["per_kind"] = _per_kind(rows, kinds[name])
            if robust_runner is not None:
                n = min(robustness, n_prior)
                summary["robustness"] = robustness_by_kind(
                    model,
                    decoded[name][0][:n],
                    kinds[name][:n] if kinds[name] is not None else ["gait"] * n,
                    sim_bodies[:n],
                    sim_ok[:n],
                    robust_runner,
                )
            if closed_loop > 0:
                n = min(closed_loop, n_prior)
                summary["closed_loop"] = closed_loop_table(
                    model.commands(decoded[name][0][:n]),
                    (kinds[name] or ["gait"] * n)[:n],
                    model.robot,
                    workers,
                )
            summary["gaits"] = rows
            report[name] = summary
    return report


def _per_kind(rows: list[dict], kinds: list[str]) -> dict:
    """The consistency figures (medians) and where the replays went, per member kind."""
    out = {}
    for kind in (k for k in KINDS if k in kinds):
        mine = [r for r in rows if r.get("kind") == float(KINDS.index(kind))]
        out[kind] = {
            "n_drawn": kinds.count(kind),
            "n_gaits": len(mine),
            **{
                k: float(np.median([r[k] for r in mine])) if mine else float("nan")
                for k in ("xy_r2", "final_error_rel", "final_spread", "displacement_m", "net_yaw_error_rel")
            },
            "diversity": diversity(mine),
        }
    return out


def physics_floor(commands: np.ndarray, body_ds: np.ndarray, runner, seed: int = 0, batch: int = 16) -> dict:
    """The body R^2 physics allows: each record's commands (n, T, n_joints) replayed with ``ENSEMBLE_NOISE``
    relative noise (record i's noise seeded ``seed + i``), its 5 Hz body series scored against the
    record's own ``body_ds`` (n, 500, 6) as a reconstruction is. A model cannot beat this on a
    family whose paths physics does not repeat (the paper family's is about 0). Records whose noisy
    replay broke are left out (``floor_broken``)."""
    from snakeloco.sim.physics.backend import simulate_bodies

    jobs = (  # a batch's noisy commands made only when the backend takes it: memory stays bounded
        np.stack(
            [perturbed_commands(c, 2, seed=seed + i)[1] for i, c in enumerate(commands[s : s + batch], s)]
        )
        for s in range(0, len(commands), batch)
    )
    replayed, ran = np.zeros(body_ds.shape), np.zeros(len(commands), bool)
    for b, (body, failures) in runner.map(simulate_bodies, jobs):  # a backend may finish out of order
        rows = slice(b * batch, b * batch + len(failures))
        replayed[rows], ran[rows] = body, [f is None for f in failures]
    target, replayed = body_ds[ran], replayed[ran]
    return {
        "r2_body_floor": r2_overall(target, replayed),
        "r2_body_floor_per_channel": dict(
            zip(BODY_CHANNELS, r2_per_channel(target, replayed).tolist(), strict=True)
        ),
        "floor_noise": ENSEMBLE_NOISE,
        "floor_records": int(ran.sum()),
        "floor_broken": int((~ran).sum()),
    }


REPEATED = 0.5
"""A body channel physics repeats: its replays under the ensemble's 0.1% command noise reach an R^2
of at least this against the record (``physics_floor``). A planar snake's vertical, roll and pitch
channels are contact jitter (std 0.06 mm, 0.002 and 0.0005 rad) that no replay repeats: no model can
learn them, and averaged in they say nothing of the model."""


def repeated_channels(report: dict) -> dict:
    """Body R^2 over the channels physics repeats (``REPEATED``), from a report with ``physics_floor``'s
    figures: the mean of their standardised R^2, which is ``r2_overall`` over them. ``r2_body_raw``:
    the VAE's reconstruction; ``r2_body``: a member's path from its gait alone."""
    floor = report["r2_body_floor_per_channel"]
    keep = [c for c in BODY_CHANNELS if floor[c] >= REPEATED]
    out: dict = {"body_channels_repeated": keep}
    for key in ("r2_body", "r2_body_raw"):
        per = report.get(f"{key}_per_channel")
        if per is not None and keep:
            out[f"{key}_repeated"] = float(np.mean([per[c] for c in keep]))
    return out


def evaluate(
    checkpoint: str | Path | None,
    data: str | Path,
    cfg: ConsistencyConfig | None = None,
    workers: int | None = None,
    progress=None,
    replays: str | Path | None = None,
    backend: BackendConfig | None = None,
    floor_records: int = 0,
    robustness: int = 0,
    closed_loop: int = 0,
) -> dict:
    """All evaluation figures for a checkpoint on a (held-out) dataset (``replays``, ``backend``,
    ``robustness``, ``closed_loop``: ``consistency``; ``floor_records``: how many of the dataset's records
    ``physics_floor`` replays, 0 none)."""
    cfg = cfg or ConsistencyConfig()
    model = load_pretrained(checkpoint)
    ds = load_dataset(data)
    shape, body_ds = ds.shape.astype(np.float64), ds.body_ds.astype(np.float64)
    rec = reconstruction(model, shape, body_ds)
    z_b, z_j = rec.pop("z_b"), rec.pop("z_j")
    out = {"checkpoint": str(model.path), "data": str(data), "n_samples": len(ds), **rec}
    out["robot_warning"] = model.robot_warning()
    out.update(latent_health(model, z_b, z_j, shape, body_ds, seed=cfg.seed))
    if floor_records > 0:
        n = min(floor_records, len(ds))
        runner = open_backend(backend, workers, robot=model.robot, world=model.world)
        try:
            out.update(physics_floor(ds.commands[:n].astype(np.float64), body_ds[:n], runner, cfg.seed))
        finally:
            runner.close()
        out.update(repeated_channels(out))
    if cfg.prior_samples > 0:
        out["consistency"] = consistency(
            model, cfg, workers, progress, replays, backend, robustness, closed_loop
        )
    return out
