"""Fitting the physics head (``model.heads.physics_head``): ``snakeloco calibrate --physics-head``.

It replays the sampler's members on their robots (``member_robots``) in chunks (resumable: the
folder ``--gaits DIR`` keeps every finished chunk, and a run of the same draw reads them back),
fits the head, saves it, then scores it on ``eval_samples`` further sampler positions (z_k = 0)
replayed on the default set and once with the ensemble's command noise: predicted vs replayed end
point over the replayed distance, per kind and per variation, beside the nominal member head's
prediction of the same replays (what the fan would be without the physics); and how far each
variation moves the end point, per kind, against the noise's own move (``sim.scores.robustness.change_table``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from snakeloco.model.heads.member_path import fit_member_head, member_inputs
from snakeloco.model.heads.physics_head import (
    PHYSICS_FEATURES,
    mirror_features,
    physics_features,
    save_physics_head,
)
from snakeloco.model.options import PhysicsHeadConfig
from snakeloco.sim.physics.body import mirror_body
from snakeloco.sim.robot.variations import DEFAULT_SET, Variation, sampled_set
from snakeloco.sim.scores.consistency import ENSEMBLE_NOISE, perturbed_commands
from snakeloco.sim.scores.robustness import change_table

PHYSICS_GAITS = "physics-gaits"
NOISE = f"command noise {ENSEMBLE_NOISE:g}"
"""The scoring replays' noise-floor row: the member's commands with the ensemble's relative noise,
on the robot itself (what physics alone moves)."""


def replay_count(cfg: PhysicsHeadConfig) -> int:
    """Replays ``fit_physics_head`` runs (chunks already replayed count too)."""
    return 2 * cfg.samples * (1 + len(DEFAULT_SET) + cfg.sampled) + cfg.eval_samples * (2 + len(DEFAULT_SET))


Row = Variation | str | None
"""What a replay runs on: a variation, the robot itself (None) or the robot itself with noisy commands (``NOISE``)."""


def member_robots(cfg: PhysicsHeadConfig, index: int, sampled: int, noise: bool = False) -> list[Row]:
    """The robots member ``index`` is replayed on: the nominal one (None), with ``noise`` the
    nominal one again with noisy commands (``NOISE``), every variation of the default set, then
    ``sampled`` combined variations of its own (seeded by the member)."""
    return [
        None,
        *([NOISE] if noise else []),
        *DEFAULT_SET,
        *sampled_set(sampled, seed=cfg.seed + 7919 * (index + 1)),
    ]


def row_robot(robot, row: Row):
    return row.apply(robot) if isinstance(row, Variation) else robot


def row_name(row: Row) -> str:
    return "nominal" if row is None else row if isinstance(row, str) else row.name


def simulate_rows(simulator, job: tuple) -> tuple[np.ndarray, list[str | None]]:
    """A backend job: commands (B, T, J), each on its row's robot (``Row``); the body series at the
    model's rate (B, 500, 6) and each replay's break reason."""
    from snakeloco.sim.data.dataset import BODY_DOWNSAMPLE

    commands, variations = job
    robots = [row_robot(simulator.robot, v) for v in variations]
    result = simulator.simulate(commands, robots=robots)
    return result.body[:, ::BODY_DOWNSAMPLE].astype(np.float32), result.failures


def replay_members_on_physics(
    model,
    z_b: np.ndarray,
    modes: tuple,
    cfg: PhysicsHeadConfig,
    sampled: int,
    folder: Path,
    fit,
    label: str,
    noise: bool = False,
    replay: bool = True,
) -> dict[str, np.ndarray]:
    """Decode z_B (N, Db) in each mode (None: z_k = 0; a temperature: sampled), project, and replay
    every member on its robots (``member_robots``), ``cfg.chunk`` members per chunk file in
    ``folder`` (a finished chunk of the same draw is read back, not replayed).

    Returns, one row per replay: member index (into the draws x modes), z_index, mode, the member's
    commanded shape, the robot's physics features, the variation's name, the body series and ok.
    ``replay=False``: only the chunks replayed already are read (none: an empty result)."""
    from snakeloco.model.replays import check_same_gaits, load_side_file, save_side_file

    folder.mkdir(parents=True, exist_ok=True)
    members, modes_of, z_index = [], [], []
    for mode, temperature in enumerate(modes):
        z_j = model.joint_latents(z_b, temperature, seed=cfg.seed + 1)
        found, _, _, _, _ = model.decode_members(z_b, z_j, with_stats=False)
        members += found
        modes_of += [mode] * len(found)
        z_index += list(range(len(found)))
    shapes = np.stack([m.shape(model.robot) for m in members])
    drawn = {"label": label, "samples": len(z_b), "seed": cfg.seed, "sampled": sampled, "modes": len(modes)}
    if noise:
        drawn["noise_row"] = True
    parts, runner = [], None
    try:
        starts = list(range(0, len(members), cfg.chunk))
        todo = []
        for s in starts:
            path = folder / f"{label}-{s:05d}.npz"
            if path.exists():
                part = load_side_file(
                    path, PHYSICS_GAITS, drawn | {"start": s}, ["shape", "body"], model.robot
                )
                check_same_gaits(path, part["shape"], shapes[part["member"]], "physics-head members")
                parts.append(part)
            else:
                todo.append(s)
        if fit is not None:
            fit.say(f"{label}: {len(starts) - len(todo)} of {len(starts)} chunks replayed already")
        if not replay:
            todo = []
        elif todo:
            runner = fit.open_backend(model.robot, model.world)

        rows_of = {  # each chunk's (member, variation) rows, in replay order
            s: [
                (i, v)
                for i in range(s, min(len(members), s + cfg.chunk))
                for v in member_robots(cfg, i, sampled, noise)
            ]
            for s in todo
        }

        def commands(i: int, row: Row) -> np.ndarray:
            """Member i's own commands, as the designer replays them (no second projection)."""
            c = members[i].commands(model.robot)
            return perturbed_commands(c, 2, seed=cfg.seed + i)[1] if row == NOISE else c

        def jobs():
            for s in todo:
                rows = rows_of[s]
                yield np.stack([commands(i, v) for i, v in rows]), [v for _, v in rows]

        for k, (body, failures) in runner.map(simulate_rows, jobs()) if todo else ():
            s = todo[k]
            rows = rows_of[s]
            robots = [row_robot(model.robot, v) for _, v in rows]
            part = {
                "member": np.array([i for i, _ in rows]),
                "z_index": np.array([z_index[i] for i, _ in rows]),
                "mode": np.array([modes_of[i] for i, _ in rows]),
                "shape": shapes[[i for i, _ in rows]],
                "features": physics_features(robots, model.robot),
                "variation": np.array([row_name(v) for _, v in rows]),
                "body": body,
                "ok": np.array([f is None for f in failures]),
            }
            save_side_file(folder / f"{label}-{s:05d}.npz", drawn | {"start": s}, model.robot, **part)
            parts.append(part)
            if fit.progress is not None:
                fit.progress(len(rows))
    finally:
        if runner is not None:
            runner.close()
    keys = ("member", "z_index", "mode", "shape", "features", "variation", "body", "ok")
    parts.sort(key=lambda p: int(np.min(p["member"])))
    if not parts:
        return {"members": members, **{k: np.zeros(0) for k in keys}}
    out = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in keys}
    out["members"] = members
    return out


def head_examples(model, replays: dict, rows: np.ndarray, mirror: bool):
    """Inputs and normalised bodies of replay ``rows`` (and their mirror images where they are members)."""
    head_cfg = model.config.member_head
    members = [replays["members"][i] for i in replays["member"][rows]]
    feats, body = replays["features"][rows], replays["body"][rows].astype(np.float64)
    if mirror:
        images = np.array([model.config.members.mirrors(m.kind) for m in members], bool)
        members = members + [m.mirrored() for m, k in zip(members, images, strict=True) if k]
        feats = np.concatenate([feats, mirror_features(feats[images])])
        body = np.concatenate([body, mirror_body(body[images])])
    x = member_inputs(members, np.asarray(head_cfg.support), None, head_cfg.inputs, model.robot)
    x = np.concatenate([x, feats], axis=1)
    return x, (body - model._body_mean) / model._body_std, members


def end_errors(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """|predicted - replayed end point| over the replayed distance (floored at 0.05 m), per path."""
    p, t = pred[:, -1, 1:3] - pred[:, 0, 1:3], true[:, -1, 1:3] - true[:, 0, 1:3]
    return np.linalg.norm(p - t, axis=-1) / np.maximum(np.linalg.norm(t, axis=-1), 0.05)


def score(model, replays: dict, rows: np.ndarray, z_b: np.ndarray) -> dict:
    """Predicted (physics head) and nominal-head end errors over replays ``rows``: medians over the
    varied robots ("all"), per kind of member (varied robots) and per variation (nominal and the
    noise row too); and, where the rows hold each member's nominal replay, how far every variation
    moves its end point (``robustness``: ``sim.scores.robustness.change_table``, the noise row its floor).
    ``z_b``: the draws the replays' members were decoded from (for a member head that reads them)."""
    members = [replays["members"][i] for i in replays["member"][rows]]
    true = replays["body"][rows].astype(np.float64)
    pred = model.members.predict_physics_paths(members, replays["features"][rows])
    nominal = model.members.predict_paths(members, np.asarray(z_b)[replays["z_index"][rows]])
    err, base = end_errors(pred, true), end_errors(nominal, true)
    kinds = np.array([m.kind for m in members])
    names = replays["variation"][rows]

    def med(mask):
        return {
            "n": int(mask.sum()),
            "rel_median": float(np.median(err[mask])),
            "nominal_head_rel_median": float(np.median(base[mask])),
        }

    varied = (names != "nominal") & (names != NOISE)
    return {
        "all": med(varied),
        "by_kind": {k: med(varied & (kinds == k)) for k in sorted(set(kinds.tolist()))},
        "by_variation": {v: med(names == v) for v in dict.fromkeys(names.tolist())},
        "robustness": robustness_of(replays, rows),
    }


def robustness_of(replays: dict, rows: np.ndarray) -> dict | None:
    """``change_table`` of the replays ``rows`` (a member's broken replays count as NaN); None where
    no member has its nominal replay among them."""
    member, names = replays["member"][rows], replays["variation"][rows]
    index = {m: k for k, m in enumerate(dict.fromkeys(member[names == "nominal"].tolist()))}
    if not index:
        return None
    variations = list(dict.fromkeys(names.tolist()))
    ends = {v: np.full((len(index), 2), np.nan) for v in variations}
    body = replays["body"][rows]
    for r, (m, v) in enumerate(zip(member, names, strict=True)):
        if m in index and replays["ok"][rows[r]]:
            ends[v][index[m]] = body[r, -1, 1:3] - body[r, 0, 1:3]
    kinds = [replays["members"][m].kind for m in index]
    return change_table(kinds, ends, floor=NOISE if NOISE in ends else None)


def fit_physics_head(fit, cfg: PhysicsHeadConfig | None = None) -> dict:
    """Replay, fit and score the physics head of ``fit.checkpoint``; write it into ``fit.out`` (the
    checkpoint's own folder, or a copy of it made there). ``fit.gaits_path``: the folder of replay
    chunks (default: ``fit.out``/physics-gaits). Returns the summary (also in the head's config)."""
    import shutil

    from snakeloco.model.api import GaitModel, load_pretrained
    from snakeloco.model.checkpoint import resolve_checkpoint
    from snakeloco.model.heads.sampler import ZK_TEMPERATURE

    cfg = cfg or PhysicsHeadConfig()
    t_start = time.perf_counter()
    model = load_pretrained(fit.checkpoint)
    if model.member_head is None or not model.projects:
        raise ValueError(
            f"checkpoint {model.path}: the physics head extends a member path head; this checkpoint has "
            "none (calibrate --sampler fits one, on a structured-family checkpoint)"
        )
    out = Path(fit.out)
    source = resolve_checkpoint(fit.checkpoint)
    if out.resolve() != source.resolve():
        shutil.copytree(source, out, dirs_exist_ok=True)
    folder = Path(fit.gaits_path) if fit.gaits_path is not None else out / PHYSICS_GAITS
    z = model.sample_z_b(cfg.samples, cfg.seed)
    train = replay_members_on_physics(
        model, z, (None, ZK_TEMPERATURE), cfg, cfg.sampled, folder, fit, "train"
    )
    held = np.random.default_rng(cfg.seed).permutation(cfg.samples)[
        : max(1, round(cfg.samples * cfg.val_fraction))
    ]
    is_val = np.isin(train["z_index"], held)
    tr_rows, va_rows = np.flatnonzero(train["ok"] & ~is_val), np.flatnonzero(train["ok"] & is_val)
    head = fitted_already(out, model, cfg)
    if head is not None:  # an interrupted scoring: the head of these replays and this config is saved
        fit.say("physics head: fitted already on these replays with this config; scoring it")
        summary = dict(head.cfg.summary)
    else:
        head, summary = _fit(model, train, tr_rows, va_rows, z, cfg, fit)
        save_physics_head(out, head)  # usable now; the scoring replays below can take an hour
    model = GaitModel(model.net, model.config, model.path, model.member_head, physics_head=head)
    if cfg.eval_samples:
        z_eval = model.sample_z_b(cfg.eval_samples, cfg.eval_seed)
        evaluated = replay_members_on_physics(model, z_eval, (None,), cfg, 0, folder, fit, "eval", noise=True)
        summary["eval"] = score(model, evaluated, np.flatnonzero(evaluated["ok"]), z_eval)
        summary["eval"]["broken"] = int((~evaluated["ok"]).sum())
    summary["wall_time_s"] = summary.get("wall_time_s", 0.0) + time.perf_counter() - t_start
    head.cfg = head.cfg.model_copy(update={"summary": summary})
    save_physics_head(out, head)
    fit.say(f"physics head: {json.dumps(summary.get('eval', summary['validation'])['all'])}; wrote {out}")
    return summary


def fitted_already(out: Path, model, cfg: PhysicsHeadConfig):
    """The physics head saved in ``out`` when it was fitted with ``cfg`` (its summary's config and
    validation: the fit finished) on this checkpoint's member head; None otherwise. Its replays are
    the chunks ``replay_members_on_physics`` has just checked against this checkpoint's decodes, and
    the fit is seeded: fitting again would give the same head."""
    from snakeloco.model.checkpoint import CheckpointError
    from snakeloco.model.heads.physics_head import load_physics_head

    try:
        head = load_physics_head(out, model.member_head)
    except CheckpointError:
        return None
    if head is None or "validation" not in head.cfg.summary:
        return None
    same = json.loads(json.dumps(head.cfg.summary.get("config"))) == json.loads(cfg.model_dump_json())
    return head if same else None


def _fit(model, train: dict, tr_rows: np.ndarray, va_rows: np.ndarray, z: np.ndarray, cfg, fit):
    """Fit the head on replays ``tr_rows``, validate on ``va_rows``: the head and its summary."""
    from snakeloco.model.api import GaitModel

    head_cfg = model.config.member_head
    sampler = model.config.summary.sampler or {}
    x, y, _ = head_examples(model, train, tr_rows, head_cfg.mirrored)
    vx, vy, _ = head_examples(model, train, va_rows, False)

    def scales(body):
        from snakeloco.model.heads.member_path import path_scales

        return path_scales(body * model._body_std + model._body_mean)

    floor = sampler.get("xy_floor")
    t0 = time.perf_counter()
    head, summary = fit_member_head(
        x,
        y,
        vx,
        vy,
        np.asarray(head_cfg.support),
        input_kind=head_cfg.inputs,
        mirrored=head_cfg.mirrored,
        epochs=cfg.epochs,
        lr=cfg.lr,
        hidden=cfg.hidden,
        layers=head_cfg.layers,
        seed=cfg.seed,
        xy_scale=None if floor is None else (scales(y), scales(vy)),
        xy_floor=floor or 0.0,
        path=head_cfg.path,
        body_norm=(model._body_mean, model._body_std),
        physics=PHYSICS_FEATURES,
        base=model.member_head if cfg.residual and head_cfg.z_b_dim == 0 else None,
        log=fit.log,
    )
    feats = train["features"][tr_rows]
    summary |= {
        "fit_s": time.perf_counter() - t0,
        "config": cfg.model_dump(),
        "broken": int((~train["ok"]).sum()),
        # The physics it was trained on, per feature (``GaitModel.members.covers``); mirrored pairs add -slope_left.
        "feature_range": {
            "low": np.minimum(feats.min(0), mirror_features(feats).min(0)).tolist(),
            "high": np.maximum(feats.max(0), mirror_features(feats).max(0)).tolist(),
        },
    }
    scored = GaitModel(model.net, model.config, model.path, model.member_head, physics_head=head)
    summary["validation"] = score(scored, train, va_rows, z)
    head.cfg = head.cfg.model_copy(update={"summary": summary})
    return head, summary
