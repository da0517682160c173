"""``snakeloco bench load``: real browser tabs drag sliders on one designer server at the same time.

The server runs in this process; each client is a Chromium page (Playwright, Debian ``chromium``,
driven from a separate process: ``load_driver`` says why)
whose mouse drags a z_B slider thumb back and forth without pause. Two phases run side by side in
one call: one client alone, then ``clients`` at once, each for ``seconds``. Reported per client:

- update latency: slider value arriving at the server -> decoded view drawn (p50/p95, ms), and
  -> replay drawn;
- exceptions: every error a tab's callbacks or workers raised on the server, and JavaScript errors
  in the pages;
- stale draws: after the last drag, for each tab, whether anything shown or exported does not match
  its final slider values: the browser's slider positions vs the server's, the drawn generated path
  and the exported CSV (downloaded through the browser) vs an independent decode of those values,
  and the simulated path vs the replay of those commands;
- server memory: resident set size sampled every 0.5 s (start, end, peak, and the slope of a
  least-squares line over the multi-client phase, over its second half, and from its
  ``RSS_SETTLE_S``-th second on in phases three times as long, there for this process and the
  decode processes apart, MB/min;
  ``rss_series_mb`` rows: seconds, MB in all, this process, the decode processes), and with the
  tabs connected and idle just before and just after the drags: what load leaves behind, without
  the replays in flight (each holds its physics steps for a moment) that make the samples jump;
- cores used over each phase's drags by this process (the server) and by the browsers it started:
  where both share the CPUs, how much of the figures is the browsers'.

In use the browsers sit on other machines; here they share this one. So the process driving them
(and with it Playwright and every Chromium it starts) runs at nice +10, and every browser thread is
held there (Chromium raises its renderers' priority itself). Unless ``render``, the pages hide their
3D canvas and pause the snake animation: they still receive and apply every scene and GUI message
of each slider move, but software WebGL on a small machine otherwise handles so few mouse events
that the load is no load. A page's pointer moves come no faster than a 60 Hz display delivers
them. ``pin_cpus`` also pins every server thread to the first half of the CPUs and the browser
process to the second half.

With the protocol driver (``load_protocol``) every client, alone or among others, drags through the
same gaits in the same order (drawn from ``seed``), each at times of its own (when it starts, how
long it rests): a ratio to the single client compares the same work (gaits of each client's own made
the worst client the one whose gaits cost most: docs/load.md, "Same gaits for every client").
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from snakeloco.app.bench.users.load_browser import (
    BREAKDOWN,
    Pages,
    browser_phase,
    percentile,
    require_browser,
)
from snakeloco.app.bench.users.load_driver import DWELL_S
from snakeloco.app.bench.users.processes import (
    BrowserNice,
    RssSampler,
    pin_process,
    slope_mb_per_min,
    split_cpus,
)
from snakeloco.app.server.lifecycle import DesignerServer, freeze_started, tune_process
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE

BROWSER_NICE = {"browser": 10, "protocol": 19}
"""Nice of the browsers by driver (each browser process, its threads and scheduling group). The
browser driver's pages are the load: level with the server's physics pool (+10), below its decoding.
Beside the protocol clients one page checks what a page draws; it stands for a user's browser on
another machine, so it takes what the server leaves: +19 and the idle scheduling class too
(``BrowserNice(idle=True)``; docs/load.md, "BROWSER_NICE")."""

RSS_SETTLE_S = 60.0
"""Seconds into the multi-client phase from which its RSS counts as settled: the tabs' first replays
and ensembles allocate what a tab keeps, and a line fitted through that step reads as a creep that is
none (docs/load.md, "RSS_SETTLE_S")."""


def _ratio(pick, values: list[float], reference: float) -> float:
    return float(pick(values) / reference) if reference > 0 else float("nan")


def _spread(values: list[float]) -> float:
    """Worst over best of the clients' figures."""
    return (
        float(np.nanmax(values) / np.nanmin(values))
        if len(values) and np.nanmin(values) > 0
        else float("nan")
    )


def bench_load(
    clients: int = 4,
    seconds: float = 60.0,
    checkpoint=None,
    ensemble: int = ENSEMBLE_SIZE,
    seed: int = 0,
    log=print,
    render: bool = False,
    pin_cpus: bool = False,
    single_seconds: float | None = None,
    dwell: float = DWELL_S,
    browser_nice: int | None = None,
    driver: str = "protocol",
    browser_page: bool = True,
    pattern: str = "drags",
    variations: bool = False,
    held_wait: float = 60.0,
) -> dict:
    """Run the single-client and ``clients``-client phases and summarise them (see module docstring).
    ``driver``: "protocol" (``bench.users.protocol`` clients; ``browser_page``: one Chromium page beside
    the multi-client phase's) or "browser" (a Chromium page each)."""
    import tempfile

    from snakeloco.app.bench.users.load_protocol import protocol_phase

    if driver not in ("protocol", "browser"):
        raise ValueError(f"driver must be protocol or browser, got {driver!r}")
    browser_nice = BROWSER_NICE[driver] if browser_nice is None else browser_nice
    if driver == "browser" or browser_page:
        require_browser("bench load")
    split = split_cpus() if pin_cpus else None
    all_cpus = sorted(os.sched_getaffinity(0)) if split else None
    if split:
        pin_process(split[0])  # before the server starts: its threads inherit the server half
    tune_process()  # as `snakeloco serve` runs it
    # Without the Variations fan unless asked (--variations), and then with the closed-loop fan too:
    # the figures stay comparable with docs/load.md (the fans run after the ensemble at the pool's
    # lowest turns but design and fits).
    server = DesignerServer(
        port=0,
        checkpoint=checkpoint,
        ensemble=ensemble,
        verbose=False,
        variations=variations,
        closed_loop=variations,
    )
    freeze_started()  # as `snakeloco serve` does
    rss = RssSampler()
    browser_idle = driver == "protocol"  # the page stands for a browser on another machine
    browser_group = BrowserNice(browser_nice, idle=browser_idle)
    pages = Pages(render, split[1] if split else None, dwell, browser_nice)
    rng = np.random.default_rng(seed)
    phases = {}
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for n in sorted({1, clients}):
                length = single_seconds if n == 1 and single_seconds else seconds
                if log:
                    log(f"{n} client(s) dragging sliders for {length:g} s")
                if driver == "protocol":
                    with_page = browser_page and n == clients and clients > 1
                    phases[n] = protocol_phase(
                        server, n, length, rng, Path(tmp), log, pages, with_page, seed, pattern, held_wait
                    )
                else:
                    phases[n] = browser_phase(server, n, length, rng, Path(tmp), log, pages)
    finally:
        rss.stop()
        browser_group.stop()
        server.stop()
        if all_cpus:
            pin_process(all_cpus)
    multi = phases[clients]
    single = phases[1]["clients"][0]
    window = rss.window(multi["t_start"], multi["t_end"])
    slope = slope_mb_per_min(window)
    # The first replays of every tab allocate what a tab keeps (its simulator's pool, its gait and
    # replay arrays): a step, then flat. The second half of the phase shows which.
    late = (
        window[window[:, 0] >= window[0, 0] + (window[-1, 0] - window[0, 0]) / 2] if len(window) else window
    )
    # Settled only in a phase three times as long: else a fit through a few seconds' noise.
    long_enough = len(window) and window[-1, 0] - window[0, 0] >= 3 * RSS_SETTLE_S
    settled = window[window[:, 0] >= window[0, 0] + RSS_SETTLE_S] if long_enough else window[:0]
    all_rss = np.asarray(rss.samples)[:, 1]
    p95s = [c["decoded_p95_ms"] for c in multi["clients"]]
    pages_checked = [ph["page"] for ph in phases.values() if ph.get("page")]
    result = {
        "driver": driver,
        "pattern": pattern,
        "variations": variations,
        "clients": clients,
        "seconds": seconds,
        "rendered": render,
        "dwell_s": dwell,
        "browser_nice": browser_nice,
        "browser_idle": browser_idle,
        "server_cpus": split[0] if split else None,
        "browser_cpus": split[1] if split else None,
        "single_decoded_p50_ms": single["decoded_p50_ms"],
        "single_decoded_p95_ms": single["decoded_p95_ms"],
        "single_replay_p95_ms": single["replay_p95_ms"],
        "multi_decoded_p50_ms": [c["decoded_p50_ms"] for c in multi["clients"]],
        "multi_decoded_p95_ms": p95s,
        "multi_replay_p95_ms": [c["replay_p95_ms"] for c in multi["clients"]],
        # --pattern held: each client's moves to the value held, send -> the panel's next "· replay"
        "single_held_ms": single.get("held_ms", []),
        "multi_held_ms": [c.get("held_ms", []) for c in multi["clients"]],
        "single_first_motion_p95_ms": single["first_motion_p95_ms"],
        "multi_first_motion_p95_ms": [c["first_motion_p95_ms"] for c in multi["clients"]],
        # Fairness: the worst client against one alone and against the best client.
        "replay_p95_ratio": _ratio(
            max, [c["replay_p95_ms"] for c in multi["clients"]], single["replay_p95_ms"]
        ),
        "first_motion_p95_ratio": _ratio(
            max, [c["first_motion_p95_ms"] for c in multi["clients"]], single["first_motion_p95_ms"]
        ),
        "replay_worst_best": _spread([c["replay_p95_ms"] for c in multi["clients"]]),
        "first_motion_worst_best": _spread([c["first_motion_p95_ms"] for c in multi["clients"]]),
        "single_breakdown_p95_ms": {k: single[f"{k}_p95_ms"] for k in BREAKDOWN},
        "multi_breakdown_p95_ms": {k: [c[f"{k}_p95_ms"] for c in multi["clients"]] for k in BREAKDOWN},
        "p95_ratio": float(np.nanmax(p95s) / single["decoded_p95_ms"]),
        # Every decoded view drawn in a phase, pooled over its tabs (``view_times_ms``).
        "views_drawn": len(views := [v for c in multi["clients"] for v in c["view_ms"]]),
        "single_views_p95_ms": percentile(single["view_ms"], 95),
        "single_views_p99_ms": percentile(single["view_ms"], 99),
        "multi_views_p95_ms": percentile(views, 95),
        "multi_views_p99_ms": percentile(views, 99),
        "updates": [c["updates"] for c in multi["clients"]],
        # Replays that finished before a newer slider value superseded them (their latencies above).
        "replays_drawn": [c["replays_drawn"] for c in multi["clients"]],
        "single_replays_drawn": single["replays_drawn"],
        "mouse_moves": [c["mouse_moves"] for c in multi["clients"]],
        "slowest_move_s": [c["slowest_move_s"] for c in multi["clients"]],
        "page_stalls": [c["stalls"] for c in multi["clients"]],
        # Each page's own state every 30 s of its drags (JS heap, DOM size, long tasks, pointer moves).
        "page_samples": [c.get("page_samples", []) for c in multi["clients"]],
        # Browser side: how long a page took to take a pointer move (dispatch -> handled).
        # Cores used over the drags (of ``cpus``): the server's process and the browsers'.
        "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "single_cores": phases[1]["cores"],
        "multi_cores": multi["cores"],
        # the physics pool's thread time per class of work (first motion, settled, dragged, ensemble)
        "single_physics_cores": phases[1].get("physics_cores"),
        "multi_physics_cores": multi.get("physics_cores"),
        "single_move_p95_ms": single["move_p95_ms"],
        "multi_move_p95_ms": [c["move_p95_ms"] for c in multi["clients"]],
        "server_exceptions": len(phases[1]["server_exceptions"]) + len(multi["server_exceptions"]),
        "exception_messages": (phases[1]["server_exceptions"] + multi["server_exceptions"])[:10],
        "page_errors": len(phases[1]["page_errors"]) + len(multi["page_errors"]),
        "stale_draws": sum(bool(c["stale"]) for ph in phases.values() for c in ph["clients"])
        + sum(bool(p["stale"]) for p in pages_checked),
        "stale_details": [c["stale"] for ph in phases.values() for c in ph["clients"] if c["stale"]]
        + [p["stale"] for p in pages_checked if p["stale"]],
        "browser_page": pages_checked[0] if pages_checked else None,
        # Protocol driver: bytes each client received for one slider move (the median of its last
        # MOVES moves, each once the previous replay was done), and while dragging per decoded view
        # the server drew for it and per drag; cores the load generators' process used.
        "kb_per_view": [c.get("kb_per_view", float("nan")) for c in multi["clients"]],
        "kb_per_move": [c.get("kb_per_move", float("nan")) for c in multi["clients"]],
        "single_kb_per_move": single.get("kb_per_move", float("nan")),
        "kb_per_drag": [c.get("kb_per_drag", float("nan")) for c in multi["clients"]],
        "driver_cores": multi.get("driver_cores", multi["cores"]["browsers"]),
        "single_driver_cores": phases[1].get("driver_cores", phases[1]["cores"]["browsers"]),
        "delivery_p95_ms": [c.get("delivery_p95_ms", float("nan")) for c in multi["clients"]],
        # Protocol driver: how late each client's 50 ms send timer fired (the driver's own delay).
        "send_late_p95_ms": [c.get("send_late_p95_ms", float("nan")) for c in multi["clients"]],
        # Slider values within 1 ms of the one before, and that share for independent users.
        "arrivals_within_1ms": multi.get("bunched", (float("nan"),) * 2)[0],
        "arrivals_within_1ms_if_independent": multi.get("bunched", (float("nan"),) * 2)[1],
        # Protocol driver: each stage's p95 per minute of the multi-client phase (all clients' drags),
        # and the last minute's over the first's.
        "minute_p95_ms": multi.get("minutes", {}),
        "last_over_first_minute": {
            k: v[-1] / v[0] if v and v[0] > 0 else float("nan") for k, v in multi.get("minutes", {}).items()
        },
        "multi_decoded_server_p95_ms": [
            c.get("decoded_server_p95_ms", float("nan")) for c in multi["clients"]
        ],
        "multi_replay_server_p95_ms": [c.get("replay_server_p95_ms", float("nan")) for c in multi["clients"]],
        "rss_start_mb": float(all_rss[0]),
        "rss_end_mb": float(all_rss[-1]),
        "rss_peak_mb": float(all_rss.max()),
        "rss_multi_start_mb": float(window[0, 1]) if len(window) else float("nan"),
        "rss_multi_end_mb": float(window[-1, 1]) if len(window) else float("nan"),
        "rss_slope_mb_per_min": slope,
        "rss_idle_before_mb": multi["rss_idle_before_mb"],
        "rss_idle_after_mb": multi["rss_idle_after_mb"],
        "rss_late_slope_mb_per_min": slope_mb_per_min(late),
        "rss_late_start_mb": float(late[0, 1]) if len(late) else float("nan"),
        "rss_late_end_mb": float(late[-1, 1]) if len(late) else float("nan"),
        "rss_settle_s": RSS_SETTLE_S,
        "rss_settled_slope_mb_per_min": slope_mb_per_min(settled),
        "rss_settled_parts_slope_mb_per_min": {
            "server_process": slope_mb_per_min(settled, 2),
            "decode_processes": slope_mb_per_min(settled, 3),
        },
        "rss_series_mb": [[round(float(v), 1) for v in row] for row in rss.samples[::10]],
    }
    return result
