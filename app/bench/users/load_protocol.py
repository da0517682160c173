"""One phase of ``snakeloco bench load --driver protocol``: protocol clients (``bench.users.protocol``),
all in one process at the browsers' nice, and optionally one real Chromium page beside them.

Latencies are the clients' own: from a drag's trailing value leaving the client to the frame that
carried its decoded view, first motion and replay ready (``protocol.Drag``), split into server time
(the frame's timestamp) and delivery. Stale checks use what each client's stream last said (its
readout is for its final sliders and says done or failed) and what the server drew for it (the
generated path of an independent decode of those values, the simulated path of its replay), and
for the Chromium page the browser driver's checks of what it drew and exported.
"""

from __future__ import annotations

import multiprocessing
import time
from pathlib import Path

import numpy as np

from snakeloco.app.bench.users import protocol, protocol_run
from snakeloco.app.bench.users.load_browser import (
    Browser,
    breakdown_p95,
    percentile,
    replay_problems,
    stale_checks,
    view_times_ms,
    wait_quiet,
)
from snakeloco.app.bench.users.load_driver import wait_until
from snakeloco.app.bench.users.processes import SPARED, CpuSplit, rss_mb
from snakeloco.app.designer.gui import path_plot_values
from snakeloco.app.designer.tab import DesignerClient
from snakeloco.app.server.lifecycle import DesignerServer

CLIENT_NICE = 0
"""Nice of the protocol clients' process: the server's own (0.02 cores). They stand for users on
other machines, whose messages do not wait for this machine's physics."""
SETTLE_S = 120.0
"""How long a client waits, after its last drag, for that drag's replay to be done."""


def bunched_arrivals(tabs: list[DesignerClient], within_s: float = 1e-3) -> tuple[float, float]:
    """(share, share if independent): of the slider values the server received from these tabs, the
    share that came within ``within_s`` of the one before (another tab's, as one tab sends every 50
    ms), and what independent arrivals at the same rate would give (Poisson: 1 - exp(-rate x
    within_s)). Values that come in bunches queue for the decode stage together."""
    t = np.sort([x.submitted for d in tabs for x in d.timings])
    if len(t) < 3 or t[-1] <= t[0]:
        return float("nan"), float("nan")
    rate = (len(t) - 1) / (t[-1] - t[0])
    return float(np.mean(np.diff(t) < within_s)), float(1.0 - np.exp(-rate * within_s))


def by_minute(summaries: list[dict]) -> dict[str, list[float]]:
    """p95 (ms) of decoded view, first motion and replay ready over all clients' drags, per minute of
    the run (by when each drag's last value went out): whether a long run slows down."""
    sent = np.concatenate([s["sent"] for s in summaries]) if summaries else np.zeros(0)
    if not sent.size:
        return {}
    stages = np.concatenate([np.asarray(s["stages_ms"], np.float64).reshape(-1, 3) for s in summaries])
    minute = ((sent - sent.min()) // 60).astype(int)
    out = {}
    for i, name in enumerate(("decoded", "first_motion", "replay")):
        out[name] = [
            percentile(stages[(minute == m) & np.isfinite(stages[:, i]), i], 95)
            for m in range(minute.max() + 1)
        ]
    return out


def server_problems(d: DesignerClient, s: dict) -> list[str]:
    """What the server shows a protocol client that is not of its final sliders (``s``: the
    client's summary)."""
    z = [float(v.value) for v in d.sliders]
    if not np.allclose(z, s["final_values"], atol=5e-5):
        return [f"server sliders {z} != the client's final values {s['final_values']}"]
    if d.decoded is None or d.decoded.latents is None:
        return ["no gait decoded for the final sliders"]
    _, body = d.model.decode(np.asarray(d.decoded.latents.z_b)[None])
    problems = []
    want = path_plot_values(body[0, :, 1])
    if s["generated"] is None or not np.array_equal(np.asarray(s["generated"], want.dtype), want):
        problems.append("the generated path the client received is not the decode of its final sliders")
    return problems + replay_problems(d)


def _match(server: DesignerServer, before: set, summaries: list[dict]) -> list[DesignerClient | None]:
    """The server tab of each client: the one whose sliders sit at its final values."""
    tabs = [server.clients[k] for k in set(server.clients) - before if k in server.clients]
    out = []
    for s in summaries:
        found = [
            d for d in tabs if np.allclose([float(v.value) for v in d.sliders], s["final_values"], atol=5e-5)
        ]
        out.append(found[0] if found else None)
        if found:
            tabs.remove(found[0])
    return out


def protocol_phase(
    server: DesignerServer,
    n: int,
    seconds: float,
    rng,
    tmp: Path,
    log,
    pages,
    with_page: bool,
    gaits_seed: int,
    pattern: str = "drags",
    held_wait: float = 60.0,
) -> dict:
    """``n`` protocol clients drag for ``seconds`` (plus, ``with_page``, one Chromium page); the
    phase in ``bench_load``'s form. ``gaits_seed``: every client drags through the same gaits
    (``ProtocolClient``), each at times of its own seed from ``rng``."""

    before = set(server.clients)
    browser, page_tab, process = None, None, None
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    seeds = [int(rng.integers(2**32)) for _ in range(n)]
    errors_before = len(server.errors)
    try:
        if with_page:
            browser = Browser(f"http://127.0.0.1:{server.port}", pages)
            browser.call("open", timeout=180)
            if not wait_until(lambda: set(server.clients) - before, 90):
                raise RuntimeError("the Chromium page never connected to the designer")
            page_tab = server.clients[(set(server.clients) - before).pop()]
            page_tab.wait_idle(120)
        seen = set(server.clients)
        rss_idle_before = rss_mb()
        cpu = CpuSplit()
        busy_before = dict(server.physics.busy_s)
        t_start = time.monotonic()
        process = ctx.Process(
            target=protocol_run.main,
            args=(
                child,
                f"http://127.0.0.1:{server.port}",
                seeds,
                seconds,
                pages.dwell,
                CLIENT_NICE,
                SETTLE_S,
                gaits_seed,
                pattern,
                held_wait,
            ),
            name="bench-load-protocol",
        )
        process.start()
        SPARED.add(process.pid)
        child.close()
        if browser is not None:
            browser.send("drag", seconds, page_tab.model.z_b_dim, [int(rng.integers(2**32))], pages.dwell)
        if not conn.poll(seconds + SETTLE_S + 300):
            raise RuntimeError("the protocol clients did not finish")
        status, result = conn.recv()
        if status != "ok":
            raise RuntimeError(f"protocol clients: {result}")
        page_moves = browser.receive("drag", timeout=600)[0] if browser is not None else None
        cores = cpu.stop()
        t_end = time.monotonic()
        physics_cores = {  # the physics pool's thread time per class of work over the drags
            turn.name.lower(): (busy - busy_before[turn]) / (t_end - t_start)
            for turn, busy in server.physics.busy_s.items()
        }
        tabs = [d for k, d in server.clients.items() if k in seen and d is not page_tab]
        settled = wait_quiet(tabs + ([page_tab] if page_tab else []))
        rss_idle_after = rss_mb()
        clients = []
        matched = _match(
            server, before | ({k for k, d in server.clients.items() if d is page_tab}), result["clients"]
        )
        for i, (s, d) in enumerate(zip(result["clients"], matched, strict=True)):
            stale = protocol.stream_problems(s)
            stale += server_problems(d, s) if d is not None else ["no server tab at its values"]
            views = max(1, d.views_drawn if d else 0)
            clients.append(
                {
                    "updates": d.values_received if d else 0,
                    "decoded_drawn": len(s["decoded_ms"]),
                    "replays_drawn": len(s["replay_ms"]),
                    "decoded_p50_ms": percentile(s["decoded_ms"], 50),
                    "decoded_p95_ms": percentile(s["decoded_ms"], 95),
                    "decoded_server_p95_ms": percentile(s["decoded_server_ms"], 95),
                    "replay_p50_ms": percentile(s["replay_ms"], 50),
                    "replay_p95_ms": percentile(s["replay_ms"], 95),
                    "replay_server_p95_ms": percentile(s["replay_server_ms"], 95),
                    "held_ms": s["held_ms"],
                    "first_motion_p50_ms": percentile(s["first_motion_ms"], 50),
                    "first_motion_p95_ms": percentile(s["first_motion_ms"], 95),
                    "delivery_p95_ms": s["delivery_p95_ms"],
                    "send_late_p95_ms": s["send_late_p95_ms"],
                    **breakdown_p95(d.timings if d else []),
                    "view_ms": view_times_ms(d.timings if d else []),
                    "drags": s["drags"],
                    "kb_per_drag": s["bytes_dragging"] / 1e3 / max(1, s["drags"]),
                    "kb_per_view": s["bytes_dragging"] / 1e3 / views,
                    "kb_per_move": float(np.median(s["bytes_per_move"])) / 1e3,
                    "mouse_moves": 0,
                    "stalls": 0,
                    "slowest_move_s": float("nan"),
                    "move_p95_ms": float("nan"),
                    "stale": stale if settled else ["did not settle within 180 s", *stale],
                }
            )
            if log:
                c = clients[-1]
                log(
                    f"  client {i + 1}/{n}: {c['drags']} drags, {c['replays_drawn']} replays ready, decoded "
                    f"p95 {c['decoded_p95_ms']:.0f} ms, replay p95 {c['replay_p95_ms']:.0f} ms, "
                    f"{c['kb_per_move']:.0f} kB per slider move ({c['kb_per_view']:.0f} per decoded view dragging)"
                    + (
                        "; moves to the value held: the panel's next '· replay' after "
                        + ", ".join(f"{t / 1e3:.1f}" for t in c["held_ms"])
                        + " s"
                        if c["held_ms"]
                        else ""
                    )
                )
        conn.send("close")  # the clients may leave now
        process.join(60)
        page = None
        if browser is not None:
            page = {
                **page_moves,
                "stale": stale_checks(browser, page_tab, tmp, 0) if settled else ["did not settle"],
            }
        return {
            "clients": clients,
            "minutes": by_minute(result["clients"]),
            "page": page,
            "server_exceptions": server.errors[errors_before:],
            "page_errors": browser.call("errors") if browser is not None else [],
            "t_start": t_start,
            "t_end": t_end,
            "rss_idle_before_mb": rss_idle_before,
            "rss_idle_after_mb": rss_idle_after,
            "cores": cores,
            "physics_cores": physics_cores,
            "driver_cores": result["driver_cores"],
            "bunched": bunched_arrivals([d for d in matched if d is not None]),
        }
    finally:
        conn.close()
        if process is not None and process.is_alive():
            process.kill()
            process.join(10)
        if browser is not None:
            try:
                browser.call("close", timeout=60)
            except RuntimeError:
                pass
            browser.close()
