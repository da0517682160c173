"""``snakeloco evaluate``'s report: the figures of ``model.evaluate.evaluate`` as text."""

from __future__ import annotations

from snakeloco.sim.scores.consistency import PREDICTABLE


def _interval(c: dict, key: str, part: str) -> str:
    lo, hi = c.get(f"{key}_{part}_ci90", (float("nan"), float("nan")))
    return f"[{lo:.3f}-{hi:.3f}]"


def _where(d: dict) -> str:
    """Where a set of replays went (``sim.scores.consistency.diversity``), in one line."""
    q, v = d["heading_quadrants"], d["speed_bl_s_quantiles"]
    return (
        "heading quadrants "
        + ", ".join(f"{k} {n}" for k, n in q.items())
        + f"; speed p10/p50/p90/max {v['p10']:.3f}/{v['p50']:.3f}/{v['p90']:.3f}/{v['max']:.3f} body lengths/s "
        f"({100 * d['share_speed_ge_0.15_bl_s']:.0f}% >= 0.15); {100 * d.get('share_travel_ge_2m', float('nan')):.0f}% "
        f"travel >= 2 m, {100 * d['share_travel_ge_5m']:.0f}% >= 5 m; {100 * d['share_rolling']:.0f}% roll"
    )


def format_report(r: dict) -> str:
    """Human-readable evaluation report."""
    lines = [f"WARNING: {r['robot_warning']}"] if r.get("robot_warning") else []
    lines += [
        f"checkpoint {r['checkpoint']} on {r['data']} ({r['n_samples']} samples)",
        f"R^2 joint shape {r['r2_shape']:.3f}; per frequency: "
        + ", ".join(
            f"{k} Hz " + ("not excited" if v is None else f"{v:.3f}")
            for k, v in r["r2_shape_per_freq"].items()
        )
        + "; per joint: "
        + ", ".join(f"{v:.3f}" for v in r["r2_shape_per_joint"]),
        f"R^2 joint shape from z_B alone (z_k = 0, what the sliders draw at a record's z_B) "
        f"{r['r2_shape_zk_zero']:.3f}",
        f"R^2 body {r['r2_body']:.3f}; per channel: "
        + ", ".join(f"{k} {v:.3f}" for k, v in r["r2_body_per_channel"].items()),
    ]
    if "r2_body_raw" in r and r["r2_body_raw"] != r["r2_body"]:
        lines.append(
            f"  (that is the path predicted for each decode's member from the gait alone; the network's "
            f"own decode, which sees the recorded path through the encoder: R^2 body {r['r2_body_raw']:.3f}; "
            + ", ".join(f"{k} {v:.3f}" for k, v in r["r2_body_raw_per_channel"].items())
            + ")"
        )
    if "r2_body_floor" in r:
        lines.append(
            f"physics' floor ({r['floor_records']} records replayed with {r['floor_noise']:g} relative "
            f"command noise, {r['floor_broken']} broke): R^2 body {r['r2_body_floor']:.3f}; per channel: "
            + ", ".join(f"{k} {v:.3f}" for k, v in r["r2_body_floor_per_channel"].items())
        )
    lines += [
        "body statistics predicted for the records' own shapes, median relative error: "
        + ", ".join(f"{k} {v:.3f}" for k, v in r["stats_median_rel_err"].items()),
        f"MMD(q(z_B) || N(0, I)) {r['mmd_zb']:.5f} (null 95th percentile {r['mmd_zb_null95']:.5f})",
        f"active units: z_B {r['active_units_zb']}, z_j {r['active_units_zj']}; "
        f"inter/intra body variance {r['inter_intra_ratio']:.2f}",
    ]
    lines += consistency_lines(r.get("consistency", {}))
    return "\n".join(lines)


def consistency_lines(consistency: dict) -> list[str]:
    """The generated-gait consistency part of the report (``model.evaluate.consistency``)."""
    lines = []
    for mode, c in consistency.items():
        lines.append(
            f"consistency ({mode}, z_B from the {c.get('positions', 'prior')}, "
            f"{100 * c.get('off_data_fraction', 0.0):.0f}% flagged off the data): {c['n_gaits']} gaits, "
            f"{c['n_broken']} whose own replay broke "
            f"({100 * c.get('broken_replay_fraction', float('nan')):.1f}% of all replays broke); medians:"
        )
        for c_name, p in c.get("per_component", {}).items():
            lines.append(
                f"  component {c_name}: {p['n_gaits']} gaits ({p['n_broken']} broke), xy-path R^2 "
                f"{p['xy_r2']:.3f}, final-position error {100 * p['final_error_rel']:.1f}% of the distance, "
                f"ensemble spread {p['final_spread']:.3f}"
            )
        for kind, p in c.get("per_kind", {}).items():
            lines.append(
                f"  kind {kind}: {p['n_gaits']} gaits (of {p['n_drawn']} drawn), xy-path R^2 {p['xy_r2']:.3f}, "
                f"final-position error {100 * p['final_error_rel']:.1f}% of the distance, ensemble spread "
                f"{p['final_spread']:.3f}, {p['displacement_m']:.1f} m travelled, net yaw error "
                f"{100 * p.get('net_yaw_error_rel', float('nan')):.1f}% (medians)"
                + (f"; {_where(p['diversity'])}" if p["diversity"] else "")
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
            f"spread in {100 * c['final_inside_fraction']:.0f}% (median distance {c.get('final_z', float('nan')):.1f} x RMS spread); "
            f"final-position error {100 * c.get('final_error_rel', float('nan')):.1f}% of the distance travelled"
        )
        d = c.get("diversity")
        if d:
            lines.append(f"  where the replays went: {_where(d)}")
        if c.get("robustness"):
            lines.append("  end-point change on other robots, |d_var - d_nom| / max(|d_nom|, 0.5 m), median:")
            lines += ["    " + line for line in change_lines(c["robustness"])]
        if c.get("closed_loop"):
            lines += closed_loop_lines(c["closed_loop"])
    return lines


def closed_loop_lines(table: dict) -> list[str]:
    """``sim.scores.closed_loop.closed_loop_table`` as lines, a kind a line."""
    lines = ["  closed loop on the default set (steered share; median of medians / of worsts; arrived):"]
    for kind, k in table.items():
        figures = (
            f"{100 * k['closed_median']:.1f}% / {100 * k['closed_worst']:.1f}%; {100 * k['arrived']:.0f}% arrived"
            if k["closed_median"] is not None
            else "no gait steered"
        )
        lines.append(f"    {kind}: {k['n']} gaits, {100 * k['steered']:.0f}% steered; {figures}")
    return lines


def change_lines(table: dict) -> list[str]:
    """``sim.scores.robustness.change_table`` as a markdown table: a row per replay name, a column per kind."""
    kinds = list(table)
    names = list(table[kinds[0]]["median"])

    def cell(kind: str, name: str) -> str:
        m = table[kind]["median"].get(name)
        broken = table[kind]["broken"].get(name, 0.0)
        return ("-" if m is None else f"{m:.2f}") + (f" ({100 * broken:.0f}% broke)" if broken else "")

    lines = ["| variation | " + " | ".join(f"{k} ({table[k]['n']})" for k in kinds) + " |"]
    lines.append("|---" * (len(kinds) + 1) + "|")
    lines += [f"| {n} | " + " | ".join(cell(k, n) for k in kinds) + " |" for n in names]
    lines.append(
        "| nominal distance (m, median) | "
        + " | ".join(f"{table[k]['distance_m_median']:.1f}" for k in kinds)
        + " |"
    )
    return lines
