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
  least-squares line over the multi-client phase and over its second half, MB/min), and with the
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
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snakeloco.app import panel
from snakeloco.app.bench import load_driver
from snakeloco.app.bench.load_driver import CHROMIUM, CHROMIUM_ARGS, DWELL_S, wait_until  # noqa: F401 (the browser tests' too)
from snakeloco.app.bench.processes import (
    BrowserNice,
    CpuSplit,
    RssSampler,
    pin_process,
    rss_mb,
    slope_mb_per_min,
    split_cpus,
)
from snakeloco.app.gait_csv import read_gait_csv
from snakeloco.app.gui import PATH_PLOT_STEP, plot_series
from snakeloco.app.server import DesignerServer, tune_process
from snakeloco.app.tab import DesignerClient
from snakeloco.sim import BODY_DOWNSAMPLE
from snakeloco.sim.consistency import ENSEMBLE_SIZE

BROWSER_NICE = 10
"""Nice of the load generators (each driver, its Chromium and their scheduling group): below the
server's own threads, level with its replays (+10), above its ensembles (+15)."""


@dataclass(frozen=True)
class Pages:
    """How the simulated users' pages run: drawing or not, on which CPUs, resting how long after
    each drag, at what nice."""

    render: bool
    cpus: list[int] | None
    dwell: float
    nice: int


CATCH_UP_S = 120.0
"""How long a page may take, after the drags end, to show the final sliders and deliver an export."""


class MissingBrowserError(RuntimeError):
    """``bench load`` needs Playwright and Debian chromium; one of them is missing."""


def require_browser(what: str) -> None:
    """Fail with one line, before any server starts, where Playwright or Debian chromium is missing."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        raise MissingBrowserError(
            f"{what} drives Chromium through Playwright, which is not installed: pip install -e '.[test]'"
        ) from None
    if not Path(CHROMIUM).exists():
        raise MissingBrowserError(
            f"{what} drives Debian chromium at {CHROMIUM}, which is missing: apt-get install -y chromium"
        )


def _p(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def _ratio(pick, values: list[float], reference: float) -> float:
    return float(pick(values) / reference) if reference > 0 else float("nan")


def _spread(values: list[float]) -> float:
    """Worst over best of the clients' figures."""
    return (
        float(np.nanmax(values) / np.nanmin(values))
        if len(values) and np.nanmin(values) > 0
        else float("nan")
    )


class _Browser:
    """One user: a Chromium page driven from a process of its own (``load_driver``), so that
    every page drags at its own pace, as users' browsers on their own machines do."""

    def __init__(self, url: str, pages: Pages) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # no fork of a process with server threads
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(
            target=load_driver.main,
            args=(child, url, pages.render, pages.nice, pages.cpus),
            name="bench-load-browser",
        )
        self._process.start()
        child.close()

    def send(self, name: str, *args) -> None:
        try:
            self._conn.send((name, *args))
        except OSError as exc:
            raise RuntimeError(
                f"the browser driver process ended (exit code {self._process.exitcode})"
            ) from exc

    def receive(self, name: str, timeout: float):
        """The answer to the command ``name`` sent last; RuntimeError with the driver's message if it failed."""
        try:
            if not self._conn.poll(timeout):
                raise RuntimeError(f"the browser driver did not answer {name!r} within {timeout:g} s")
            status, value = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise RuntimeError(
                f"the browser driver process ended (exit code {self._process.exitcode}) during {name!r}"
            ) from exc
        if status != "ok":
            raise RuntimeError(f"browser driver, {name!r}: {value}")
        return value

    def call(self, name: str, *args, timeout: float = 600.0):
        self.send(name, *args)
        return self.receive(name, timeout)

    def close(self) -> None:
        try:
            self._conn.send(("quit",))
        except OSError:
            pass
        self._process.join(60)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(10)
        self._conn.close()


MOVED = "the server's sliders moved during these checks"


def _wait_quiet(designers: list[DesignerClient], quiet_s: float = 2.0, timeout_s: float = 180.0) -> bool:
    """Wait until no tab's sliders have changed for ``quiet_s`` and every tab is idle.

    A CPU-starved page can deliver its last slider messages seconds after its driver's final
    pointer move returned (a move took up to 30 s in a 4-tab run): checking before then would
    compare what is drawn with values that are about to change.
    """
    deadline = time.monotonic() + timeout_s
    last = [tuple(float(s.value) for s in d.sliders) for d in designers]
    since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.1)
        now = [tuple(float(s.value) for s in d.sliders) for d in designers]
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return all(d.wait_idle(max(1.0, deadline - time.monotonic())) for d in designers)
    return False


def _stale_checks(
    browser: _Browser, d: DesignerClient, tmp: Path, index: int, attempts: int = 3
) -> list[str]:
    """``_check_final_state``, again from the new values if a late browser event moved the sliders
    while it ran (that is not a stale draw: the state it checked was not yet final)."""
    for _ in range(attempts):
        problems = _check_final_state(browser, d, tmp, index)
        if not (problems and problems[-1].startswith(MOVED)):
            return problems
        _wait_quiet([d])
    return problems


def replay_problems(d: DesignerClient) -> list[str]:
    """Whether a settled tab shows the replay of its current gait: its simulated path, or, where
    physics refused the gait (thrown, diverged), the panel saying so for that gait."""
    if d.simulated is not None:
        drawn = d.controls.plots["forward (m)"].data[2]
        if np.array_equal(drawn, plot_series(d.simulated.body[:: BODY_DOWNSAMPLE * PATH_PLOT_STEP, 1])[0]):
            return []
        return ["drawn simulated path is not the final replay"]
    last = d.timings[-1] if d.timings else None
    if last is None or last.failed is None or not d.is_current(last.version):
        return ["no replay drawn for the final sliders"]
    if d.controls.panel.content != panel.failed_text(d.decoded, last.failed):
        return [f"the final replay failed ({last.failed}) but the panel does not say so"]
    return []


def _check_final_state(browser: _Browser, d: DesignerClient, tmp: Path, index: int) -> list[str]:
    """Everything this tab shows or exports must match its final slider values; returns mismatches."""
    problems = []
    z = tuple(float(s.value) for s in d.sliders)

    def shown() -> list[float]:
        return browser.call("shown", 0)[: len(z)]

    # A page may still be working through the messages of the last burst: give it time to catch up.
    wait_until(lambda: np.allclose(shown(), z, atol=1e-9), CATCH_UP_S)
    if not np.allclose(shown(), z, atol=1e-9):
        problems.append(f"browser sliders {shown()} != server sliders {list(z)} after {CATCH_UP_S:g} s")
    if d.decoded is None or d.decoded.latents is None or d.decoded.latents.sliders != z:
        problems.append(f"current gait decoded from {getattr(d.decoded, 'latents', None)}, sliders at {z}")
        return problems
    z_b = np.asarray(d.decoded.latents.z_b)[None]
    if d.model.projects:  # the exact member the decode projects onto: its commands, to the bit
        members, _, _, body, _ = d.model.decode_members(z_b)
        commands = members[0].commands()
    else:
        shape, body = d.model.decode(z_b)
        commands = d.model.commands(shape[0])
    if not np.array_equal(
        d.controls.plots["forward (m)"].data[1], plot_series(body[0, ::PATH_PLOT_STEP, 1])[0]
    ):
        problems.append("drawn generated path is not the decode of the final sliders")
    problems += replay_problems(d)
    path = tmp / f"client{index}.csv"
    if not browser.call("export", 0, str(path), CATCH_UP_S, timeout=CATCH_UP_S + 60):
        problems.append(f"the exported CSV did not arrive in the browser within {CATCH_UP_S:g} s")
        return problems
    text = path.read_text()
    exported = read_gait_csv(text.encode()).commands
    if not np.array_equal(exported, commands):
        problems.append("exported commands are not those of the final sliders")
    key = "# sliders: [" if d.decoded.latents.axes is not None else "# z_B: ["
    if key + ", ".join(f"{v:.4f}" for v in z) + "]" not in text:
        line = next((ln for ln in text.splitlines() if ln.startswith(key[:-2])), f"no {key[2:-3]} line")
        problems.append(f"exported z_B comment does not match the final sliders {list(z)}: {line!r}")
    now = tuple(float(s.value) for s in d.sliders)
    if problems and now != z:  # says whether a late browser event moved the sliders during the checks
        problems.append(f"{MOVED}: {list(z)} -> {list(now)}")
    return problems


def _phase(server: DesignerServer, n: int, seconds: float, rng, tmp: Path, log, pages: Pages) -> dict:
    browsers: list[_Browser] = []
    try:
        return _drive(browsers, server, n, seconds, rng, tmp, log, pages)
    finally:
        for browser in browsers:
            try:
                browser.call("close", timeout=60)
            except RuntimeError:
                pass
            browser.close()
        wait_until(lambda: not server.clients, 30)


def _drive(
    browsers: list, server: DesignerServer, n: int, seconds: float, rng, tmp, log, pages: Pages
) -> dict:
    designers = []
    for _ in range(n):
        before = set(server.clients)
        browsers.append(_Browser(f"http://127.0.0.1:{server.port}", pages))
        browsers[-1].call("open", timeout=180)
        if not wait_until(lambda b=before: set(server.clients) - b, 90):
            raise RuntimeError("a browser page never connected to the designer")
        designers.append(server.clients[(set(server.clients) - before).pop()])
    for d in designers:
        d.wait_idle(120)
    rss_idle_before = rss_mb()  # every tab connected, its first gait replayed, nothing running
    errors_before = len(server.errors)
    n_sliders = designers[0].model.z_b_dim
    seeds = [int(rng.integers(2**32)) for _ in designers]
    start = time.perf_counter()
    t_start = time.monotonic()
    cpu = CpuSplit()
    for browser, seed in zip(browsers, seeds, strict=True):
        browser.send("drag", seconds, n_sliders, [seed], pages.dwell)
    moves = [browser.receive("drag", timeout=seconds + 600)[0] for browser in browsers]
    cores = cpu.stop()
    t_end = time.monotonic()
    settled = _wait_quiet(designers)  # slider messages a starved page sends late
    rss_idle_after = rss_mb()  # the same tabs, idle again after the drags
    clients = []
    for i, (browser, d, dr) in enumerate(zip(browsers, designers, moves, strict=True)):
        ts = [t for t in list(d.timings) if t.submitted >= start]
        dec = np.array([1e3 * (t.decoded - t.submitted) for t in ts if np.isfinite(t.decoded)])
        rep = np.array([1e3 * (t.replayed - t.submitted) for t in ts if np.isfinite(t.replayed)])
        motion = np.array([1e3 * (t.first_motion - t.submitted) for t in ts if np.isfinite(t.first_motion)])
        drawn = [t for t in ts if np.isfinite(t.decoded) and np.isfinite(t.started)]
        # Where a decoded view's latency goes: waiting for the decode worker, decoding, drawing.
        wait = np.array([1e3 * (t.started - t.submitted) for t in drawn])
        work = np.array([t.decode_ms for t in drawn])
        draw = np.array([1e3 * (t.decoded - t.started) - t.decode_ms for t in drawn])
        stale = _stale_checks(browser, d, tmp, i) if settled else ["did not settle within 180 s"]
        clients.append(
            {
                **dr,
                "updates": len(ts),
                "decoded_drawn": int(dec.size),
                "replays_drawn": int(rep.size),
                "decoded_p50_ms": _p(dec, 50),
                "decoded_p95_ms": _p(dec, 95),
                "wait_p95_ms": _p(wait, 95),
                "decode_p95_ms": _p(work, 95),
                "draw_p95_ms": _p(draw, 95),
                "replay_p50_ms": _p(rep, 50),
                "replay_p95_ms": _p(rep, 95),
                "first_motion_p50_ms": _p(motion, 50),
                "first_motion_p95_ms": _p(motion, 95),
                "stale": stale,
            }
        )
        if log:
            log(
                f"  client {i + 1}/{n}: {len(ts)} updates, {rep.size} replays finished, "
                f"decoded p95 {clients[-1]['decoded_p95_ms']:.1f} ms"
            )
    return {
        "clients": clients,
        "server_exceptions": server.errors[errors_before:],
        "page_errors": [e for browser in browsers for e in browser.call("errors")],
        "t_start": t_start,
        "t_end": t_end,
        "rss_idle_before_mb": rss_idle_before,
        "rss_idle_after_mb": rss_idle_after,
        "cores": cores,
    }


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
    browser_nice: int = BROWSER_NICE,
    driver: str = "protocol",
    browser_page: bool = True,
) -> dict:
    """Run the single-client and ``clients``-client phases and summarise them (see module docstring).
    ``driver``: "protocol" (``bench.protocol`` clients; ``browser_page``: one Chromium page beside
    the multi-client phase's) or "browser" (a Chromium page each)."""
    import tempfile

    from snakeloco.app.bench.load_protocol import protocol_phase

    if driver not in ("protocol", "browser"):
        raise ValueError(f"driver must be protocol or browser, got {driver!r}")
    if driver == "browser" or browser_page:
        require_browser("bench load")
    split = split_cpus() if pin_cpus else None
    all_cpus = sorted(os.sched_getaffinity(0)) if split else None
    if split:
        pin_process(split[0])  # before the server starts: its threads inherit the server half
    tune_process()  # as `snakeloco serve` runs it
    server = DesignerServer(port=0, checkpoint=checkpoint, ensemble=ensemble, verbose=False)
    rss = RssSampler()
    browser_group = BrowserNice(browser_nice)
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
                    phases[n] = protocol_phase(server, n, length, rng, Path(tmp), log, pages, with_page)
                else:
                    phases[n] = _phase(server, n, length, rng, Path(tmp), log, pages)
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
    all_rss = np.asarray(rss.samples)[:, 1]
    p95s = [c["decoded_p95_ms"] for c in multi["clients"]]
    pages_checked = [ph["page"] for ph in phases.values() if ph.get("page")]
    result = {
        "driver": driver,
        "clients": clients,
        "seconds": seconds,
        "rendered": render,
        "dwell_s": dwell,
        "browser_nice": browser_nice,
        "server_cpus": split[0] if split else None,
        "browser_cpus": split[1] if split else None,
        "single_decoded_p50_ms": single["decoded_p50_ms"],
        "single_decoded_p95_ms": single["decoded_p95_ms"],
        "single_replay_p95_ms": single["replay_p95_ms"],
        "multi_decoded_p50_ms": [c["decoded_p50_ms"] for c in multi["clients"]],
        "multi_decoded_p95_ms": p95s,
        "multi_replay_p95_ms": [c["replay_p95_ms"] for c in multi["clients"]],
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
        "single_breakdown_p95_ms": {k: single[f"{k}_p95_ms"] for k in ("wait", "decode", "draw")},
        "multi_breakdown_p95_ms": {
            k: [c[f"{k}_p95_ms"] for c in multi["clients"]] for k in ("wait", "decode", "draw")
        },
        "p95_ratio": float(np.nanmax(p95s) / single["decoded_p95_ms"]),
        "updates": [c["updates"] for c in multi["clients"]],
        # Replays that finished before a newer slider value superseded them (their latencies above).
        "replays_drawn": [c["replays_drawn"] for c in multi["clients"]],
        "single_replays_drawn": single["replays_drawn"],
        "mouse_moves": [c["mouse_moves"] for c in multi["clients"]],
        "slowest_move_s": [c["slowest_move_s"] for c in multi["clients"]],
        "page_stalls": [c["stalls"] for c in multi["clients"]],
        # Browser side: how long a page took to take a pointer move (dispatch -> handled).
        # Cores used over the drags (of ``cpus``): the server's process and the browsers'.
        "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "single_cores": phases[1]["cores"],
        "multi_cores": multi["cores"],
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
        "rss_series_mb": [[round(float(t), 1), round(float(mb), 1)] for t, mb in rss.samples[::10]],
    }
    return result
