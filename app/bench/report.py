"""``snakeloco bench NAME``: the figures of a benchmark, printed for a person.

``snakeloco bench NAME`` calls ``bench_NAME`` of ``BENCH_MODULES[NAME]`` (``app/bench/NAME.py``, ``sim/physics/bench.py``, ``model/bench.py``) with the command's options
(``options``) and prints the figures it returns with the function ``NAME`` here (and as JSON with
``--json``).
"""

from __future__ import annotations

import numpy as np


def options(cmd) -> dict:
    """A bench command's options as its function's keyword arguments: each field is the parameter of
    the same name (tests/test_cli.py checks every pair), all but ``--json``, which is the report's."""
    return {name: getattr(cmd, name) for name in type(cmd).model_fields if name != "json"}


def sim(r: dict) -> None:
    """The simulator against bare MuJoCo (``sim/physics/bench.py``)."""
    print(
        f"threads {r['workers']}, {r['samples']} records of {r['steps_per_sample']} steps\n"
        f"raw mujoco.rollout   {r['raw_steps_per_s']:12.0f} steps/s\n"
        f"generator end-to-end {r['generator_steps_per_s']:12.0f} steps/s"
        f"   ratio {r['ratio']:.3f} (generator / raw, goal >= 0.9)\n"
        f"bare mj_step loop    {r['bare_ms']:9.1f} ms\n"
        f"sim.replay           {r['replay_ms']:9.1f} ms"
        f"   replay_ratio {r['replay_ratio']:.3f} (replay time / bare time)"
    )


def model(r: dict) -> None:
    """Decode latency and throughput (``model/bench.py``)."""
    print(
        f"decode one z_B: p50 {r['decode_p50_ms']:.2f} ms, p95 {r['decode_p95_ms']:.2f} ms; "
        f"batch of {r['batch']}: {r['batch_decodes_per_s']:.0f} decodes/s"
    )
    if "decode_raw_p50_ms" in r:
        print(
            f"the network's own decode (no projection, no member path): p50 {r['decode_raw_p50_ms']:.2f} ms, "
            f"p95 {r['decode_raw_p95_ms']:.2f} ms; projection and path prediction cost "
            f"{r['projection_cost_ratio']:.2f}x"
        )


def app(r: dict) -> None:
    """One client's latency through a real designer server (``bench/app.py``)."""
    print(
        f"{r['moves']} slider moves: decoded view p50 {r['decoded_p50_ms']:.1f} ms, p95 {r['decoded_p95_ms']:.1f} ms; "
        f"first motion p50 {r['first_motion_p50_ms']:.0f} ms, p95 {r['first_motion_p95_ms']:.0f} ms; "
        f"replay ready p50 {r['replay_ready_p50_ms']:.0f} ms, p95 {r['replay_ready_p95_ms']:.0f} ms; "
        f"replay_ratio {r['replay_ratio']:.3f} (replay / bare mj_step), "
        f"ensemble_ratio {r['ensemble_ratio']:.3f} (ensemble / bare mujoco.rollout); "
        f"a tab receives {r['animating_bytes_per_s'] / 1e3:.1f} kB/s while the snake animates and "
        f"{r['bytes_per_move'] / 1e3:.0f} kB per slider move"
    )


def tabs(r: dict) -> None:
    """Several rendering tabs in one Chromium (``bench/tabs.py``)."""
    print(
        f"{r['tabs']} tabs animating in one Chromium (nice {r['browser_nice']}) on {r['cpus']} CPUs, "
        f"{r['rounds']} key presses each; light rendering {r['light_rendering']} ({r['rendering']})\n"
        "key press -> value at the server p50 / p95 per tab (ms): "
        + ", ".join(
            f"{a:.0f} / {b:.0f}"
            for a, b in zip(r["press_to_server_p50_ms"], r["press_to_server_p95_ms"], strict=True)
        )
        + f"; all tabs p95 {r['press_to_server_p95_all_ms']:.0f} ms (goal <= 1000); lost {r['lost_presses']}\n"
        "Export CSV click -> file (s): "
        + ", ".join(
            f"{t:.1f}{'' if ok else ' FAILED'}" for t, ok in zip(r["export_s"], r["export_ok"], strict=True)
        )
        + f" (goal <= 10); server exceptions {r['server_exceptions']}"
    )


def load(r: dict) -> None:
    """Several browser tabs on one server (``bench/load.py``)."""
    where = (
        f"server on CPUs {r['server_cpus']}, browsers on CPUs {r['browser_cpus']}"
        if r["server_cpus"]
        else "server and browsers share the CPUs"
    )

    def split(stages: tuple[str, ...], digits: int) -> str:
        return "; ".join(
            f"{k} {r['single_breakdown_p95_ms'][k]:.{digits}f} -> "
            + "/".join(f"{v:.{digits}f}" for v in r["multi_breakdown_p95_ms"][k])
            for k in stages
        )

    breakdown, motion = split(("wait", "decode", "draw"), 1), split(("physics", "motion_draw"), 0)
    print(
        f"{where}\n"
        f"1 client: decoded view p50 {r['single_decoded_p50_ms']:.1f} ms, p95 {r['single_decoded_p95_ms']:.1f} ms\n"
        f"{r['clients']} clients: decoded view p95 per client "
        + ", ".join(f"{v:.1f}" for v in r["multi_decoded_p95_ms"])
        + f" ms; worst / single p95 = {r['p95_ratio']:.2f} (goal <= 2)\n"
        f"p95 breakdown (ms), 1 client -> each of {r['clients']}: {breakdown}\n"
        f"every decoded view drawn, server side: p95 {r['single_views_p95_ms']:.1f} -> "
        f"{r['multi_views_p95_ms']:.1f} ms, p99 {r['single_views_p99_ms']:.1f} -> {r['multi_views_p99_ms']:.1f} "
        f"ms ({r['views_drawn']} views with {r['clients']} clients)\n"
        f"first motion p95: 1 client {r['single_first_motion_p95_ms']:.0f} ms, each of {r['clients']} "
        + ", ".join(f"{v:.0f}" for v in r["multi_first_motion_p95_ms"])
        + f" ms (worst / single {r['first_motion_p95_ratio']:.2f}, worst / best {r['first_motion_worst_best']:.2f})\n"
        f"first motion p95 breakdown (ms), 1 client -> each of {r['clients']}: {motion}\n"
        f"replay ready p95: 1 client {r['single_replay_p95_ms']:.0f} ms, each of {r['clients']} "
        + ", ".join(f"{v:.0f}" for v in r["multi_replay_p95_ms"])
        + f" ms (worst / single {r['replay_p95_ratio']:.2f}, worst / best {r['replay_worst_best']:.2f}; "
        f"replays finished: 1 client {r['single_replays_drawn']}, each of {r['clients']} "
        + ", ".join(str(v) for v in r["replays_drawn"])
        + f"; {r['dwell_s']:g} s rest after each drag; browsers at nice +{r['browser_nice']}"
        + (", idle class" if r.get("browser_idle") else "")
        + ")\n"
        f"browser side, a page taking a pointer move p95: 1 client {r['single_move_p95_ms']:.0f} ms, each of "
        f"{r['clients']} " + ", ".join(f"{v:.0f}" for v in r["multi_move_p95_ms"]) + " ms\n"
        f"cores used over the drags (of {r['cpus']}): 1 client: server {r['single_cores']['server']:.2f}, "
        f"browsers {r['single_cores']['browsers']:.2f}; {r['clients']} clients: server "
        f"{r['multi_cores']['server']:.2f}, browsers {r['multi_cores']['browsers']:.2f}\n"
        f"updates per client {r['updates']}; server exceptions {r['server_exceptions']}, "
        f"page errors {r['page_errors']}, stale draws {r['stale_draws']}\n"
        f"server RSS {r['rss_start_mb']:.0f} MB at start, {r['rss_multi_start_mb']:.0f} -> "
        f"{r['rss_multi_end_mb']:.0f} MB over the {r['clients']}-client phase "
        f"(slope {r['rss_slope_mb_per_min']:+.1f} MB/min; second half {r['rss_late_start_mb']:.0f} -> "
        f"{r['rss_late_end_mb']:.0f} MB, slope {r['rss_late_slope_mb_per_min']:+.1f} MB/min; settled, "
        f"from the {r['rss_settle_s']:.0f}th s, {r['rss_settled_slope_mb_per_min']:+.1f} MB/min: this process "
        f"{r['rss_settled_parts_slope_mb_per_min']['server_process']:+.1f}, the decode processes "
        f"{r['rss_settled_parts_slope_mb_per_min']['decode_processes']:+.1f}), "
        f"peak {r['rss_peak_mb']:.0f} MB; tabs idle before / after the drags "
        f"{r['rss_idle_before_mb']:.0f} / {r['rss_idle_after_mb']:.0f} MB"
    )
    if r["driver"] == "protocol":
        print(
            f"protocol clients: kB received per decoded view, 1 client {r['single_kb_per_move']:.0f}, each of "
            f"{r['clients']} "
            + ", ".join(f"{v:.0f}" for v in r["kb_per_move"])
            + " (per drag "
            + ", ".join(f"{v:.0f}" for v in r["kb_per_drag"])
            + f"); the clients' process used {r['single_driver_cores']:.3f} / {r['driver_cores']:.3f} cores; "
            f"server part of the decoded view p95 "
            + ", ".join(f"{v:.0f}" for v in r["multi_decoded_server_p95_ms"])
            + " ms, delivery p95 "
            + ", ".join(f"{v:.1f}" for v in r["delivery_p95_ms"])
            + " ms, send timer late p95 "
            + ", ".join(f"{v:.1f}" for v in r.get("send_late_p95_ms", []))
            + " ms"
            + (
                f"; the Chromium page beside them: stale {r['browser_page']['stale'] or 'none'}"
                if r["browser_page"]
                else ""
            )
        )
    pages = [("the Chromium page", (r["browser_page"] or {}).get("page_samples"))]
    pages += [(f"page {i + 1}", samples) for i, samples in enumerate(r.get("page_samples", []))]
    for name, samples in pages:
        if samples:
            print(
                f"{name} over time (s: JS heap MB / DOM elements / long tasks ms / pointer move p95 ms): "
                + "; ".join(
                    f"{x['t_s']:.0f}: {x['heap_mb'] or float('nan'):.0f} / {x['dom_nodes']} / "
                    f"{x['long_ms']:.0f} / {x['move_p95_ms']:.0f}"
                    for x in samples
                )
            )
    if r.get("minute_p95_ms"):
        print(
            "per minute of the multi-client phase, p95 (ms): "
            + "; ".join(
                f"{k} "
                + "/".join(f"{v:.0f}" for v in vals)
                + f" (last / first {r['last_over_first_minute'][k]:.2f})"
                for k, vals in r["minute_p95_ms"].items()
            )
        )
    for details in r["stale_details"]:
        print("stale:", "; ".join(details))
    for message in r["exception_messages"]:
        print("exception:", message)


def scale(r: dict) -> None:
    """The Ray backend against the local one, zarr against .npz (``bench/scale.py``)."""
    print(
        f"{r['records']} {r['family']} records, {r['workers']} CPUs: local {r['local_records_per_s']:.2f} records/s, "
        f"ray {r['ray_records_per_s']:.2f} records/s (start-up included); ratio {r['ratio']:.3f} (ray / local, "
        f"goal >= 0.85); arrays identical: {r['identical']}; Ray start-up alone {r['ray_startup_s']:.1f} s"
    )
    if r["memory"]:
        m = r["memory"]
        print(
            f"{r['memory_records']} records written and trained on: peak RSS npz {m['npz']['peak_rss_mib']:.0f} MiB, "
            f"zarr {m['zarr']['peak_rss_mib']:.0f} MiB (ratio {r['memory_ratio']:.2f}); after writing "
            f"{m['npz']['peak_rss_after_write_mib']:.0f} / {m['zarr']['peak_rss_after_write_mib']:.0f} MiB; "
            f"same first-epoch loss: {r['same_first_epoch_loss']}"
        )


def design(r: dict) -> None:
    """Inverse design against the same physics budget spent on random draws (``bench/design.py``)."""
    print(f"targets: {r['target_source']}")
    for name in ("design", "design_first_round", "baseline", "baseline_first_round_budget"):
        f = r[name]
        heading = (
            f", heading error median {f['heading_error_deg_median']:.1f} deg, p90 {f['heading_error_deg_p90']:.1f} deg"
            if f["heading_error_deg_median"] is not None
            else ""
        )
        print(
            f"{name:27s}: end error / target distance median {f['error_rel_median']:.3f}, p90 {f['error_rel_p90']:.3f}, "
            f"met {f['met_share']:.0%}"
            f"{heading}"
            + (
                f"; ensemble spread median {f['spread_m_median']:.2f} m"
                if f["spread_m_median"] is not None
                else ""
            )
        )
    u = r["unreachable"]
    print(
        f"{r['targets']} targets, {np.median(r['physics_budget_replays']):.0f} replays each (median, the "
        f"baseline's too; {r['candidates']} in the first round and its baseline); time to an answer p50 {r['seconds_p50']:.1f} s, p95 {r['seconds_p95']:.1f} s (search "
        f"{r['search_s_median']:.1f} s + physics {r['physics_s_median']:.1f} s, medians); a {u['target_m']:.0f} m "
        f"target: met {u['met']}, closest reached {u['closest_reached_m']} ({u['error_m']:.1f} m off)"
    )


def robust(r: dict) -> None:
    """Robust design against nominal design on the same targets (``bench/robust.py``)."""

    def pct(f: dict) -> str:
        return f"median {100 * f['median']:.0f}%, p90 {100 * f['p90']:.0f}%"

    print(
        f"{r['targets']} targets {r['reach_m'][0]:g}-{r['reach_m'][1]:g} m all round; robust search: {r['searched_with']}"
    )
    print(
        f"nominal design: error {pct(r['nominal_error_rel'])}; worst over the default set {pct(r['nominal_worst_rel'])}"
    )
    print(
        f"robust design : error {pct(r['robust_error_rel'])}; worst over the default set {pct(r['robust_worst_rel'])} "
        f"(predicted {pct(r['robust_predicted_worst_rel'])})"
    )
    print(
        f"worst robust / nominal: median {r['worst_ratio']['median']:.2f}; halved or better on "
        f"{100 * r['worst_halved_share']:.0f}% of targets; time to an answer p50 {r['nominal_s']['p50']:.0f} s "
        f"nominal, {r['robust_s']['p50']:.0f} s robust (p95 {r['nominal_s']['p95']:.0f} / {r['robust_s']['p95']:.0f} s)"
    )


def screen(r: dict) -> None:
    """The structured family's cheap screen against the full one (``bench/screen.py``)."""
    for name, f in r["rates"].items():
        print(
            f"{name:9s} {f['records']:4d} records: {f['records_per_s']:.3f} records/s, rejection "
            f"{f['rejection_rate']:.3f} ({f['wall_s']:.0f} s)"
        )
    print(
        f"cheap / full {r['ratio_full']:.2f}x, cheap / undulate {r['ratio_undulate']:.2f}x "
        f"(goal: >= 0.5 records/s on 2 cores; {r['workers']} threads here)"
    )
    a = r["agreement"]
    if a:
        print(
            f"{a['draws']} draws replayed in full: kept cheap {a['cheap_kept']}, full {a['full_kept']}; verdicts "
            f"differ on {a['disagree']} ({a['cheap_keeps_full_rejects']} kept only by the cheap screen, "
            f"{a['cheap_rejects_full_keeps']} only by the full one); rejected at "
            f"{a['early_seconds']:g} s: {a['early_rejects']}, of which the full screen kept {a['early_rejects_full_keeps']}"
        )


def fit(r: dict) -> None:
    """Robots of known physics fitted from synthetic runs (``sim/fit/bench.py``)."""
    if "single_runs" in r:
        for gait, rows in r["single_runs"].items():
            said = "; ".join(
                f"{p} "
                + ", ".join(
                    f"{100 * row[p]['error_rel']:+.0f}%{' (det.)' if row[p]['determined'] else ''}"
                    for row in rows
                )
                for p in rows[0]
            )
            print(f"{gait} alone, per robot: {said}")
        return
    for row in r["robots"]:
        fields = ", ".join(
            f"{name} {100 * p['error_rel']:+.0f}% ({'determined' if p['determined'] else 'not determined'})"
            for name, p in row["params"].items()
        )
        held = np.median([[h["fitted_rel"], h["nominal_rel"]] for h in row["held_out"].values()], axis=0)
        print(
            f"{row['robot']}: {fields}; {len(row['held_out'])} held-out gaits' end error median "
            f"{100 * held[0]:.1f}% (nominal {100 * held[1]:.0f}%); {row['seconds']:.0f} s"
        )
    for name, h in r["held_out_per_gait"].items():
        print(
            f"  held out {name}: {100 * h['fitted_rel']:.1f}% fitted, {100 * h['nominal_rel']:.0f}% nominal, "
            f"{100 * h['near_rel']:.1f}% with every field within 3% of the truth (medians over the robots)"
        )
    print(
        f"fitted runs {', '.join(r['fit_gaits'])}, "
        + ("with measured joint angles; " if r.get("joints") else "the body's path alone; ")
        + f"determined fields within 15% of the truth: {r['determined_within_15pct']} of {r['determined']}; held-out end "
        f"error median {100 * r['held_out_fitted_rel_median']:.1f}% fitted vs {100 * r['held_out_nominal_rel_median']:.0f}% "
        f"nominal, {100 * r['held_out_near_rel_median']:.1f}% with every field within 3% of the truth; fit time median {r['seconds_median']:.0f} s ({r['workers']} threads)"
    )


def loop(r: dict) -> None:
    """Closed loop against open loop (``bench/loop.py``)."""

    def pct(v) -> str:
        return "-" if v is None else f"{100 * v:.1f}%"

    for name, f in r.get("library", {}).items():
        print(
            f"library {name}: {f['steering']}; path {f['distance_m']:.1f} m; open loop median {pct(f['open']['median'])}, "
            f"worst {pct(f['open']['max'])}; closed loop arrived {f['arrived']}/{f['runs']}, "
            f"{f['within_3pct_of_arrived']} of them within 3% (median {pct(f['closed_arrived']['median'])}, "
            f"worst {pct(f['closed_arrived']['max'])}); late: {', '.join(f['late']) or 'none'}"
        )
    for name, f in r.get("sensing", {}).items():
        print(
            f"sensing {name}: end error median {f['clean_m']['median']:.3f} m -> {f['noisy_m']['median']:.3f} m "
            f"(worst {f['clean_m']['max']:.3f} -> {f['noisy_m']['max']:.3f} m), arrived {f['arrived_clean']} / {f['arrived_noisy']}"
        )
    for name, f in r.get("off_path", {}).items():
        bl = f["settled_body_lengths"]
        print(
            f"off path {name} (1 m, 30 deg): within 0.1 m for good after {'never' if bl is None else f'{bl:.1f} body lengths'}"
            f", end {pct(f['end_error_rel'])} off"
        )
    if "timing" in r:
        t = r["timing"]
        print(
            f"12 replays: open loop {t['open_s']:.1f} s, closed loop {t['closed_s']:.1f} s, ratio {t['ratio']:.2f} (goal <= 1.5)"
        )
    if "sampler" in r:
        s = r["sampler"]
        print(
            f"sampler: {s['gaits']} gaits, {100 * s['steered_share']:.0f}% with a steering input; open loop median of "
            f"medians {pct(s['open_median_of_medians'])}, of worsts {pct(s['open_median_of_worst'])}; closed loop "
            f"{pct(s['closed_median_of_medians'])}, {pct(s['closed_median_of_worst'])}"
        )
    for name, f in r.get("designer", {}).items():
        s = f["seconds"]
        print(
            f"designer {name}: closed-loop fan drawn {'never' if s is None else f'{s:.1f} s'} after the replay (goal <= 15 s)"
        )


def terrain(r: dict) -> None:
    """What a world costs and what crosses what (``bench/terrain.py``)."""
    for name, g in r.get("library", {}).items():
        cells = ", ".join(
            f"{w} {'y' if f['open']['arrives'] else 'n'}/{'-' if 'closed' not in f else 'y' if f['closed']['arrives'] else 'n'}"
            for w, f in g["worlds"].items()
        )
        print(f"library {name} ({g['distance_m']:.1f} m; {g['steering']}): arrives open/closed: {cells}")
    for key in ("library_per_world", "sampler"):
        table = r.get(key, {})
        table = table.get("per_world", {}) if key == "sampler" else table
        for w, f in table.items():
            med = f["closed_rel_median"]
            print(
                f"{key.split('_')[0]} on {w}: arrive open {f['open_arrives']}, closed {f['closed_arrives']} of "
                f"{f['steered']} steered; closed-loop end error median {'-' if med is None else f'{100 * med:.1f}%'}"
            )
    replay = r.get("replay", {})
    for name, f in replay.items():
        if name in ("rough_numpy", "native"):
            continue
        print(
            f"replay on {name:<8} {f['world_s']:6.2f} s, flat {f['flat_s']:6.2f} s: {f['ratio']:.2f}x (goal <= 2)"
        )
    if not replay:  # --sections without replay
        return
    step = "native" if replay["native"] else "numpy (no C compiler)"
    print(
        f"rough with the numpy step {replay['rough_numpy']['world_s']:.2f} s: {replay['rough_numpy']['ratio']:.2f}x; used: {step}"
    )
    for name, f in r.get("first_view", {}).items():
        print(
            f"designer on {name}: first view {f['decoded_s']:.2f} s, first replay {f['replayed_s']:.2f} s after connecting (goal <= 5 s)"
        )
