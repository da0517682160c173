"""``snakeloco figures``: PNG figures in the manner of the paper's Figs. 5-8."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from snakeloco.model.api import load_pretrained
from snakeloco.sim import BODY_CHANNELS, BODY_TIMES, load_dataset

_STAT_LABELS = {
    "path_length": "path length over 100 s (m)",
    "median_speed": "median speed (m/s)",
    "vertical_std": "vertical oscillation std (m)",
    "net_roll": "net roll (rad)",
}


class ReportError(ValueError):
    """An ``--report`` file that is not a ``snakeloco evaluate --report`` file with consistency gaits."""


def load_report(path: str | Path) -> dict:
    """Read and check an evaluate report for the consistency figure.

    Raises:
        ReportError: unreadable, not JSON, or without per-gait consistency results (e.g. evaluated
            with ``--prior-samples 0``), naming what is missing.
    """
    import json

    try:
        r = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ReportError(f"report {path}: not a readable JSON file ({exc})") from None
    modes = r.get("consistency") if isinstance(r, dict) else None
    if not isinstance(modes, dict) or not modes:
        raise ReportError(
            f"report {path}: no 'consistency' results (write one with snakeloco evaluate "
            "--prior-samples N --report FILE, N > 0)"
        )
    need = [k + s for k in _STAT_LABELS for s in ("_simulated", "_decoded")]
    for mode, c in modes.items():
        gaits = c.get("gaits") if isinstance(c, dict) else None
        if not isinstance(gaits, list):
            raise ReportError(f"report {path}: consistency mode {mode!r} has no per-gait results")
        missing = sorted({k for g in gaits for k in need if not isinstance(g, dict) or k not in g})
        if gaits:  # a mode whose every replay broke has no medians, and no points to draw
            missing += [k + "_err" for k in _STAT_LABELS if k + "_err" not in c]
        if missing:
            raise ReportError(f"report {path}: consistency mode {mode!r} lacks {', '.join(missing)}")
    return r


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figures(
    checkpoint: str | Path | None,
    data: str | Path,
    out: str | Path,
    seed: int = 0,
    report: str | Path | None = None,
) -> list[Path]:
    """Write fit, prior-sweep, z_k-sample and joint-shape figures to ``out``; returns their paths.

    With ``report`` (JSON from ``snakeloco evaluate --report``), also the consistency figure.
    """
    plt = _plt()
    report_data = load_report(report) if report is not None else None  # before any figure is written
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = load_pretrained(checkpoint)
    ds = load_dataset(data)
    rng = np.random.default_rng(seed)
    paths = []
    cmap = plt.get_cmap("viridis")

    # Fig. 5: training fit on three samples (joint shape in the complex plane; body channels).
    idx = rng.choice(len(ds), 3, replace=False)
    shape, body = ds.shape[idx].astype(np.float64), ds.body_ds[idx].astype(np.float64)
    z_b, z_j = model.encode(shape, body)
    s_hat, b_hat = model.decode(z_b, z_j)
    fig, axes = plt.subplots(3, 7, figsize=(21, 8))
    for row in range(3):
        ax = axes[row, 0]
        n_joints = shape.shape[1]
        for k in range(n_joints):
            c = cmap(k / max(n_joints - 1, 1))
            ax.scatter(shape[row, k, :, 0], shape[row, k, :, 1], color=c, s=14)
            ax.scatter(s_hat[row, k, :, 0], s_hat[row, k, :, 1], color=c, s=14, marker="x")
        ax.set_title(f"sample {idx[row]}: joint shape (o data, x model)")
        ax.set_xlabel("real (rad)")
        ax.set_ylabel("imag (rad)")
        for ch in range(6):
            ax = axes[row, ch + 1]
            ax.plot(BODY_TIMES, body[row, :, ch], "k", lw=1, label="data")
            ax.plot(BODY_TIMES, b_hat[row, :, ch], "r", lw=1, label="model")
            ax.set_title(BODY_CHANNELS[ch])
            ax.set_xlabel("t (s)")
        axes[row, 1].legend()
    fig.tight_layout()
    paths.append(out / "fig5_fit.png")
    fig.savefig(paths[-1], dpi=80)
    plt.close(fig)

    # Fig. 6: prior sweep of each z_B dimension with z_k = 0 (decoded horizontal paths).
    d = model.z_b_dim
    fig, axes = plt.subplots(1, d, figsize=(3.2 * d, 3.4), squeeze=False)
    values = np.linspace(-2.5, 2.5, 7)
    for i in range(d):
        z = np.zeros((len(values), d))
        z[:, i] = values
        _, b = model.decode(z)
        ax = axes[0, i]
        for j in range(len(values)):
            ax.plot(b[j, :, 1], b[j, :, 2], color=plt.get_cmap("coolwarm")(j / (len(values) - 1)), lw=1.2)
        ax.set_title(f"z_B[{i}] from -2.5 to 2.5")
        ax.set_xlabel("forward (m)")
        ax.set_aspect("equal", adjustable="datalim")
    axes[0, 0].set_ylabel("sideways (m)")
    fig.tight_layout()
    paths.append(out / "fig6_prior_sweep.png")
    fig.savefig(paths[-1], dpi=80)
    plt.close(fig)

    # Figs. 7-8: two z_B, each with 8 z_k drawn from the learned prior: body paths and joint shapes.
    zb = rng.standard_normal((2, d))
    zj = model.sample_joint_latents(zb, 8, seed=seed)  # (2, 8, K, Dj)
    fig7, axes7 = plt.subplots(1, 2, figsize=(10, 4.5))
    fig8, axes8 = plt.subplots(2, 8, figsize=(24, 6))
    for r in range(2):
        shapes, bodies = model.decode(np.repeat(zb[r : r + 1], 8, axis=0), zj[r])
        _, b0 = model.decode(zb[r : r + 1])
        ax = axes7[r]
        for s in range(8):  # the 8 draws of z_k
            ax.plot(bodies[s, :, 1], bodies[s, :, 2], lw=1, alpha=0.8)
        ax.plot(b0[0, :, 1], b0[0, :, 2], "k", lw=2, label="z_k = 0")
        ax.set_title(f"z_B #{r + 1}: 8 draws of z_k")
        ax.set_xlabel("forward (m)")
        ax.set_ylabel("sideways (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend()
        for s in range(8):
            ax = axes8[r, s]
            for k in range(shapes.shape[1]):  # each joint
                ax.scatter(
                    shapes[s, k, :, 0], shapes[s, k, :, 1], color=cmap(k / max(shapes.shape[1] - 1, 1)), s=10
                )
            ax.set_title(f"z_B #{r + 1}, z_k draw {s + 1}", fontsize=9)
            lim = np.abs(shapes[:, :, :, :]).max() * 1.1
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim, lim)
            ax.set_aspect("equal")
    fig7.tight_layout()
    fig8.tight_layout()
    paths.append(out / "fig7_zk_samples.png")
    fig7.savefig(paths[-1], dpi=80)
    paths.append(out / "fig8_joint_shapes.png")
    fig8.savefig(paths[-1], dpi=80)
    plt.close(fig7)
    plt.close(fig8)
    if report is not None:
        paths.append(consistency_figure(report_data, out / "fig9_consistency.png"))
        if all(
            {"direction_deg", "heading_deg"} & set(g)
            for c in report_data["consistency"].values()
            for g in c["gaits"]
        ):  # heading_deg: a report written before the direction of travel had its one name
            paths.append(diversity_figure(report_data, out / "fig10_diversity.png"))
    return paths


def _floor_text(summary: dict, key: str) -> str:
    """ ", physics' floor N%" where the report has it (reports before the floor was measured lack it)."""
    floor = summary.get(key + "_floor")
    return "" if floor is None else f", physics' floor {100 * floor:.0f}%"


def consistency_figure(report: str | Path | dict, path: Path) -> Path:
    """Predicted vs simulated body statistics of prior-generated gaits, with the physics' spread.

    ``report``: an evaluate report's path (checked by ``load_report``) or its loaded contents.
    """
    plt = _plt()
    r = report if isinstance(report, dict) else load_report(report)
    fig, axes = plt.subplots(1, 4, figsize=(20, 5))
    for (mode, c), marker in zip(r["consistency"].items(), ("o", "x"), strict=False):
        gaits = c["gaits"]
        if not gaits:
            continue
        for ax, (key, label) in zip(axes, _STAT_LABELS.items(), strict=True):
            sim = np.array([g[key + "_simulated"] for g in gaits])
            dec = np.array([g[key + "_decoded"] for g in gaits])
            # The ensemble's std in the statistic's units. Reports written before it was stored
            # hold only std / |ensemble mean|, which cannot be turned back into it (the mean is
            # not stored; near zero net roll it is no scale at all): no bars for them.
            std = (
                np.array([g[key + "_std"] for g in gaits]) if all(key + "_std" in g for g in gaits) else None
            )
            ax.errorbar(
                sim,
                dec,
                xerr=std,
                fmt=marker,
                ms=3,
                alpha=0.5,
                elinewidth=0.5,
                label=f"{mode} (median error {100 * c[key + '_err']:.0f}%" + _floor_text(c, key) + ")",
            )
            ax.set_xlabel(f"simulated {label}")
            ax.set_ylabel("model")
            ax.set_title(label)
    for ax in axes:
        lo, hi = ax.get_xlim()
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.legend(fontsize=8)
    fig.suptitle(
        "Generated gaits (z_B from the prior): the model's statistics vs MuJoCo's; bars: ensemble std"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def diversity_figure(report: dict, path: Path) -> Path:
    """Where the generated gaits' replays went: final positions in the start frame, final heading
    (polar histogram) and speed, per z_k mode of an evaluate report (``sim.scores.consistency.diversity``)."""
    plt = _plt()
    fig = plt.figure(figsize=(16, 4.8))
    scatter = fig.add_subplot(1, 3, 1)
    polar = fig.add_subplot(1, 3, 2, projection="polar")
    speeds = fig.add_subplot(1, 3, 3)
    bins = np.radians(np.arange(-180, 181, 15))
    for (mode, c), colour in zip(report["consistency"].items(), ("tab:blue", "tab:orange"), strict=False):
        gaits = c["gaits"]
        if not gaits:
            continue
        heading = np.radians([g.get("direction_deg", g.get("heading_deg")) for g in gaits])
        dist = np.array([g["displacement_m"] for g in gaits])
        rolls = np.array([g["rolls"] for g in gaits], bool)
        x, y = dist * np.cos(heading), dist * np.sin(heading)
        scatter.scatter(x[~rolls], y[~rolls], s=8, color=colour, alpha=0.6, label=f"{mode}, not rolling")
        scatter.scatter(
            x[rolls], y[rolls], s=14, color=colour, marker="x", alpha=0.6, label=f"{mode}, rolling"
        )
        counts, _ = np.histogram(heading, bins=bins)
        polar.bar(bins[:-1], counts, width=np.diff(bins), align="edge", alpha=0.5, color=colour, label=mode)
        d = c["diversity"]
        speeds.hist(
            [g["speed_bl_s"] for g in gaits],
            bins=30,
            alpha=0.5,
            color=colour,
            label=f"{mode}: {100 * d['share_travel_ge_5m']:.0f}% travel >= 5 m, "
            f"{100 * d['share_rolling']:.0f}% roll",
        )
    scatter.plot(0, 0, "k+", ms=12)
    scatter.set_xlabel("forward (m)")
    scatter.set_ylabel("sideways, left + (m)")
    scatter.set_aspect("equal", adjustable="datalim")
    scatter.set_title("final positions of the unperturbed replays (start frame)")
    scatter.legend(fontsize=7)
    polar.set_title("final heading (0: forward, 90: left)")
    polar.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    speeds.axvline(0.15, color="k", ls="--", lw=1)
    speeds.set_xlabel("speed over 100 s (body lengths/s)")
    speeds.set_ylabel("gaits")
    speeds.set_title("speed")
    speeds.legend(fontsize=7)
    fig.suptitle("Generated gaits (z_B from the prior): where MuJoCo took them")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
