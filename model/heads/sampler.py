"""``snakeloco calibrate --sampler``: keep the sliders on the data and predict the path of the member
that is replayed.

Three things are fitted after training and stored in the checkpoint (schema 4):

1. **The slider density** (``model.heads.density``): a Gaussian mixture over the training records'
   posterior z_B. ``GaitModel.sample_z_b`` draws from it, the designer's sliders move along one of
   its components' principal axes, and a z_B it finds unlikely is flagged.
2. **The family** decodes are projected onto (``sim.gaits.members``): the dataset's structured config.
3. **The member path head** (``model.heads.member_path``), trained on the training records (each record is
   a member, its recorded path the label) and on MuJoCo replays of the members the sampler's z_B
   decode to (z_k = 0 and sampled at temperature 1, as the designer decodes them): the distribution
   the sliders produce, labelled by physics. A tenth of the z_B draws (both modes together) and the
   dataset's validation records are held out to choose the epoch and to report the fit.

The paper family gets the density only (``density_only``): its decodes are no family's members and
its promise stays statistical. The component names say where each component's mean gait goes (the
predicted path's end: "forward, 17 m").
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from snakeloco.model.api import GaitModel
from snakeloco.model.checkpoint import check_trained_on, save_checkpoint
from snakeloco.model.heads.density import fit_density, name_components
from snakeloco.model.heads.member_path import (
    fit_member_head,
    kind_weights,
    member_inputs,
    path_scales,
    with_mirror_images,
)
from snakeloco.model.options import SamplerConfig
from snakeloco.model.replays import Fit, load_side_file, replay_shapes, save_side_file
from snakeloco.model.vae.train import split_records
from snakeloco.sim import BODY_RATE, DatasetError, joint_shape
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.gaits.projection import project_many

SAMPLER_GAITS = "sampler-gaits"
GAIT_KEYS = ("z_b", "mode", "z_index", "shape", "body")
ZK_TEMPERATURE = 1.0
"""The sampled z_k mode's temperature: the designer's default."""


def _drawn(cfg: SamplerConfig) -> dict:
    return {"samples": cfg.samples, "seed": cfg.seed, "temperature": ZK_TEMPERATURE}


def replay_sampler_gaits(model: GaitModel, cfg: SamplerConfig, fit: Fit) -> dict[str, np.ndarray]:
    """Draw ``cfg.samples`` z_B from the model's density, decode each with z_k = 0 (mode 0) and
    sampled (mode 1), project onto members (``model`` must project) and replay each member once.

    Returns, broken replays dropped: z_b (M, Db), mode (M,), z_index (M,) which draw, shape
    (M, n_joints, L, 2) the members' commanded shapes, body (M, 500, 6) their replays at 5 Hz."""
    z = model.sample_z_b(cfg.samples, cfg.seed)
    runner = fit.open_backend(model.robot, model.world)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in GAIT_KEYS}
    try:
        for mode, temperature in enumerate((None, ZK_TEMPERATURE)):
            z_j = model.joint_latents(z, temperature, seed=cfg.seed + 1)
            members, _, measured, _, _ = model.decode_members(z, z_j)
            bodies, ok = replay_shapes(model, measured, runner, progress=fit.progress)
            ok = ok[:, 0]
            parts["z_b"].append(z[ok])
            parts["mode"].append(np.full(int(ok.sum()), mode))
            parts["z_index"].append(np.flatnonzero(ok))
            parts["shape"].append(np.stack([m.shape(model.robot) for m in members])[ok])
            parts["body"].append(bodies[ok, 0])
    finally:
        runner.close()
    return {k: np.concatenate(v) for k, v in parts.items()}


def record_members(ds, index: np.ndarray, family) -> list[Member]:
    """The members of dataset records: each record's commands transformed (``sim.joint_shape``: exact
    for its periodic commands) and projected onto its family."""
    commanded = joint_shape(ds.commands[index].astype(np.float64), ds.config.excitation)
    members, residuals = project_many(commanded, family, ds.config.robot)
    if residuals.max() > 1e-4:
        raise DatasetError(
            f"record {int(index[residuals.argmax()])} is not a member of its family (residual "
            f"{residuals.max():.2g}): the dataset and the family config disagree"
        )
    return members


def _path_r2(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """xy-path R^2 of predicted vs true body series (n, T, 6), per gait."""
    from snakeloco.sim.scores.consistency import xy_r2

    return np.array([xy_r2(p, t) for p, t in zip(pred, true, strict=True)])


def by_kind(members: list[Member], pred: np.ndarray, true: np.ndarray) -> dict[str, dict[str, float]]:
    """Per kind of member: how many, the xy-path R² median and the final-position error median
    over the distance travelled, of predicted vs true body series (n, T, 6)."""
    from snakeloco.sim.scores.consistency import path_stats

    r2 = _path_r2(pred, true)
    p, t = path_stats(pred, BODY_RATE), path_stats(true, BODY_RATE)
    rel = np.linalg.norm(p["final_xy"] - t["final_xy"], axis=-1) / np.maximum(t["displacement"], 1e-9)
    kinds = np.array([m.kind for m in members])
    return {
        k: {
            "n": int((kinds == k).sum()),
            "xy_r2_median": float(np.median(r2[kinds == k])),
            "final_error_rel_median": float(np.median(rel[kinds == k])),
        }
        for k in sorted(set(kinds.tolist()))
    }


def fit_sampler(fit: Fit, cfg: SamplerConfig | None = None) -> dict:
    """Fit the slider density (and, for the structured family, the member path head) of
    ``fit.checkpoint`` on its training data ``fit.data``; write the checkpoint to ``fit.out``; the
    sampler members' replays are read from ``fit.gaits_path`` where it exists, else written there.
    Returns the summary (also stored as ``summary.sampler``)."""
    cfg = cfg or SamplerConfig()
    t_start = time.perf_counter()
    model, ds = fit.load()
    config = model.config
    n_trained = int(config.train.get("n_train", 0)) + int(config.train.get("n_val", 0))
    if cfg.regenerated:
        if ds.config.family != config.family or not 0 < len(ds) <= n_trained:
            raise DatasetError(
                f"{fit.data}: {len(ds)} {ds.config.family} records cannot be this checkpoint's "
                f"{n_trained} {config.family} training records generated again"
            )
    else:
        check_trained_on(config, ds, fit.data)
    split_n = n_trained if cfg.regenerated else len(ds)
    tr_idx, va_idx = split_records(
        split_n, float(config.train.get("val_fraction", 0.1)), int(config.train.get("seed", 0))
    )
    tr_idx, va_idx = np.sort(tr_idx[tr_idx < len(ds)]), np.sort(va_idx[va_idx < len(ds)])
    z_post, _ = model.encode(ds.shape[tr_idx], ds.body_ds[tr_idx])
    density = fit_density(z_post, cfg.max_components, seed=cfg.seed)
    summary: dict = {**cfg.model_dump(), "components": len(density.weights), "fitted_on": len(tr_idx)}
    fit.say(f"density: {len(density.weights)} components over {len(tr_idx)} training posteriors")
    head, head_cfg, members = None, None, None
    if not cfg.density_only:
        if ds.config.family != "structured":
            raise DatasetError(f"{fit.data}: the member path head needs a structured-family dataset")
        members = ds.config.structured
        model = GaitModel(
            model.net,
            config.model_copy(update={"density": density, "members": members, "member_head": None}),
            model.path,
        )
        gaits = None
        if fit.gaits_path is not None and Path(fit.gaits_path).exists():
            gaits = load_side_file(fit.gaits_path, SAMPLER_GAITS, _drawn(cfg), list(GAIT_KEYS), model.robot)
            # The draws are this checkpoint's density's (a retrained model draws other z_B).
            drawn_z = model.sample_z_b(cfg.samples, cfg.seed)[gaits["z_index"]]
            gap = np.abs(gaits["z_b"] - drawn_z).max() if gaits["z_b"].shape == drawn_z.shape else np.inf
            if gap > 1e-6:
                raise DatasetError(
                    f"{fit.gaits_path}: its gaits were drawn from another checkpoint's slider density (z_B "
                    f"differs by up to {gap:.3g}); remove the file or name another one to replay them"
                )
            fit.say(f"reusing {len(gaits['z_b'])} replayed sampler gaits from {fit.gaits_path}")
        if gaits is None:
            t0 = time.perf_counter()
            gaits = replay_sampler_gaits(model, cfg, fit)
            summary["replay_s"] = time.perf_counter() - t0
            if fit.gaits_path is not None:
                save_side_file(fit.gaits_path, _drawn(cfg), model.robot, **gaits)
        summary["broken"] = 2 * cfg.samples - len(gaits["z_b"])
        support = np.asarray(config.shape_support or np.ones((model.robot.n_joints, len(config.freqs)), bool))
        held = np.random.default_rng(cfg.seed).permutation(cfg.samples)[
            : max(1, round(cfg.samples * cfg.val_fraction))
        ]
        g_val = np.isin(gaits["z_index"], held)
        rec_tr, rec_va = record_members(ds, tr_idx, members), record_members(ds, va_idx, members)

        def norm(body: np.ndarray) -> np.ndarray:
            return (np.asarray(body, np.float64) - model._body_mean) / model._body_std

        z_va, z_tr_all, z_va_all, z_g_val = None, None, None, None  # z_B inputs: only a head that reads them
        if cfg.head_sees_z_b:
            z_va, z_g_val = model.encode(ds.shape[va_idx], ds.body_ds[va_idx])[0], gaits["z_b"][g_val]
            z_tr_all = np.concatenate([z_post, gaits["z_b"][~g_val]])
            z_va_all = np.concatenate([z_va, z_g_val])
        g_members = project_many(gaits["shape"], members, model.robot)[0]  # exact: each projects onto itself
        g_va_members = [m for m, v in zip(g_members, g_val, strict=True) if v]
        tr_members = rec_tr + [m for m, v in zip(g_members, g_val, strict=True) if not v]
        va_members = rec_va + g_va_members
        y = np.concatenate([ds.body_ds[tr_idx], gaits["body"][~g_val]])
        if cfg.mirror:
            tr_members, y = with_mirror_images(tr_members, y, members)
        x = member_inputs(tr_members, support, z_tr_all, cfg.head_inputs, model.robot)
        vx = member_inputs(va_members, support, z_va_all, cfg.head_inputs, model.robot)
        vy = np.concatenate([ds.body_ds[va_idx], gaits["body"][g_val]])
        scales = None if cfg.xy_floor is None else (path_scales(y), path_scales(vy))
        balance = (
            (kind_weights(tr_members), kind_weights(tr_members, va_members)) if cfg.balance_kinds else None
        )
        y, vy = norm(y), norm(vy)
        t0 = time.perf_counter()
        head, head_fit = fit_member_head(
            x,
            y,
            vx,
            vy,
            support,
            input_kind=cfg.head_inputs,
            mirrored=cfg.mirror,
            z_b_dim=model.z_b_dim if cfg.head_sees_z_b else 0,
            epochs=cfg.epochs,
            lr=cfg.lr,
            hidden=cfg.hidden,
            seed=cfg.seed,
            xy_scale=scales,
            xy_floor=cfg.xy_floor or 0.0,
            example_weights=balance,
            path=cfg.head_path,
            body_norm=(model._body_mean, model._body_std),
            log=fit.log,
        )
        head_fit["fit_s"] = time.perf_counter() - t0
        model = GaitModel(
            model.net, model.config.model_copy(update={"member_head": head.cfg}), model.path, head
        )
        pred = model.members.predict_paths(g_va_members, z_g_val)
        head_fit["held_out_xy_r2_median"] = float(np.median(_path_r2(pred, gaits["body"][g_val])))
        head_fit["held_out_by_kind"] = by_kind(g_va_members, pred, gaits["body"][g_val])
        pred = model.members.predict_paths(rec_va, z_va)
        head_fit["val_records_xy_r2_median"] = float(np.median(_path_r2(pred, ds.body_ds[va_idx])))
        head_cfg = head.cfg.model_copy(update={"summary": head_fit})
        summary["member_head"] = head_fit
        fit.say(
            f"member path head: held-out sampler gaits xy R² median {head_fit['held_out_xy_r2_median']:.3f}, "
            f"validation records {head_fit['val_records_xy_r2_median']:.3f}"
        )
    # Names: where each component's mean gait goes (z_k = 0), as this checkpoint predicts it, and of
    # which kind its member is where the family has more than one.
    means = np.asarray(density.means)
    kinds = None
    if model.projects:
        found, _, _, body, _ = model.decode_members(means)
        if sum(w > 0 for w in model.config.members.kind_weights) > 1:
            kinds = [m.kind for m in found]
    else:
        _, body = model.decode(means)
    ends = np.stack([body[:, -1, 1], body[:, -1, 2], np.degrees(body[:, -1, 5] - body[:, 0, 5])], axis=1)
    density = density.model_copy(update={"names": name_components(ends, kinds, density.weights)})
    summary["names"] = density.names
    summary["wall_time_s"] = time.perf_counter() - t_start
    summary["data"] = str(fit.data)
    new_summary = config.summary.model_copy(update={"sampler": summary})
    final = config.model_copy(
        update={"density": density, "members": members, "member_head": head_cfg, "summary": new_summary}
    )
    save_checkpoint(fit.out, model.net, final, head.requires_grad_(False) if head is not None else None)
    fit.say(f"components: {', '.join(density.names)}; wrote {fit.out}")
    return summary
