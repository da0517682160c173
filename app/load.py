"""``snakeloco bench load``: real browser tabs drag sliders on one designer server at the same time.

The server runs in this process; each client is a Chromium page (Playwright, Debian ``chromium``)
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
  least-squares line over the multi-client phase, MB/min).

In use the browsers sit on other machines; here they share this one. So the thread driving them
(and with it Playwright and every Chromium it starts) runs at nice +10, and every browser thread is
held there (Chromium raises its renderers' priority itself). Unless ``render``, the pages hide their
3D canvas and pause the snake animation: they still receive and apply every scene and GUI message
of each slider move, but software WebGL on a small machine otherwise handles so few mouse events
that the load is no load. A page's pointer moves come no faster than a 60 Hz display delivers
them. ``pin_cpus`` also pins every server thread to the first half of the CPUs and the browsers to
the second half.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from app.gait_csv import read_gait_csv
from app.server import DesignerClient, DesignerServer
from sim.physics import lower_thread_priority, set_thread_nice

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


BROWSER_NICE = 10
POINTER_HZ = 60.0
"""Most pointer moves per second per page, as a 60 Hz display delivers them during a drag."""
CATCH_UP_S = 120.0
"""How long a page may take, after the drags end, to show the final sliders and deliver an export."""
VIEWPORT = {"width": 960, "height": 600}
"""Each page's size: software WebGL's cost grows with the pixels, and the browsers are only load."""
LOAD_ARGS = [
    *CHROMIUM_ARGS,
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
]


def split_cpus() -> tuple[list[int], list[int]] | None:
    """(server CPUs, browser CPUs): the first and second half of this process's CPUs, or None
    where there are fewer than two or affinity cannot be set (then everything shares them)."""
    if not hasattr(os, "sched_getaffinity") or not Path("/proc/self/task").is_dir():
        return None
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return None
    half = len(cpus) // 2
    return cpus[:half], cpus[half:]


def _pin_process(cpus) -> None:
    """Pin every thread of this process to ``cpus`` (threads started later inherit their creator's)."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:  # the thread ended meanwhile
            pass


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc (Linux) or the peak from getrusage."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _descendant_tasks(root: int) -> list[int]:
    """Thread ids of every process descended from ``root`` (Linux /proc)."""
    parent = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            parent[int(stat.parent.name)] = int(fields[1])
        except (OSError, ValueError, IndexError):
            continue
    found, frontier = set(), {root}
    while frontier:
        frontier = {pid for pid, pp in parent.items() if pp in frontier} - found
        found |= frontier
    tasks = []
    for pid in found:
        try:
            tasks += [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
    return tasks


class _BrowserNice:
    """Keeps every thread of the browsers this process started at nice >= ``nice``.

    Chromium sets its renderers' priority itself (as root, to nice -8 for visible pages), which
    would put the load generators above the server they are measuring.
    """

    def __init__(self, nice: int, period: float = 0.5) -> None:
        self._nice, self._period = nice, period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="browser-nice", daemon=True)
        if hasattr(os, "setpriority") and Path("/proc/self/task").is_dir():
            self._thread.start()

    def _run(self) -> None:
        me = os.getpid()
        while not self._stop.wait(self._period):
            for tid in _descendant_tasks(me):
                try:
                    if os.getpriority(os.PRIO_PROCESS, tid) < self._nice:
                        os.setpriority(os.PRIO_PROCESS, tid, self._nice)
                except OSError:
                    continue

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)


class _RssSampler:
    def __init__(self, period: float = 0.5) -> None:
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._period = period
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.monotonic() - self._t0, rss_mb()))
            self._stop.wait(self._period)

    def window(self, start: float, end: float) -> np.ndarray:
        a = np.asarray(self.samples)
        return a[(a[:, 0] >= start - self._t0) & (a[:, 0] <= end - self._t0)]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


class _Dragger:
    """One page's mouse, dragging a random z_B slider thumb to random targets in small steps."""

    def __init__(self, page, n_sliders: int, rng: np.random.Generator) -> None:
        self.page = page
        self.n_sliders = n_sliders
        self.rng = rng
        self.moves = 0
        self.slowest_step_s = 0.0  # the longest a page took to take one pointer move
        self._steps_left = 0
        self._x = self._y = 0.0
        self._target = 0.0

    def step(self) -> None:
        mouse = self.page.mouse
        if self._steps_left == 0:
            mouse.up()
            thumb = self.page.get_by_role("slider").nth(int(self.rng.integers(self.n_sliders)))
            box = thumb.bounding_box()
            track = thumb.locator("xpath=..").bounding_box()
            if box is None or track is None:
                return
            self._x, self._y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            self._lo, self._hi = track["x"] + 2, track["x"] + track["width"] - 2
            mouse.move(self._x, self._y)
            mouse.down()
            self._target = float(self.rng.uniform(self._lo, self._hi))
            self._steps_left = int(self.rng.integers(10, 30))
        dx = (self._target - self._x) / self._steps_left
        self._x = min(max(self._x + dx + float(self.rng.normal(0, 2)), self._lo), self._hi)
        mouse.move(self._x, self._y)
        self._steps_left -= 1
        self.moves += 1

    def release(self) -> None:
        self.page.mouse.up()
        self._steps_left = 0


def wait_until(predicate, timeout: float = 60.0) -> bool:
    """Poll ``predicate`` every 50 ms until it is true (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _p(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def _stale_checks(page, d: DesignerClient, tmp: Path, index: int) -> list[str]:
    """Everything this tab shows or exports must match its final slider values; returns mismatches."""
    problems = []
    z = tuple(float(s.value) for s in d.sliders)

    def shown() -> list[float]:
        values = page.get_by_role("slider").evaluate_all(
            "els => els.map(e => e.getAttribute('aria-valuenow'))"
        )
        return [float(v) for v in values[: len(z)]]

    # A page may still be working through the messages of the last burst: give it time to catch up.
    wait_until(lambda: np.allclose(shown(), z, atol=1e-9), CATCH_UP_S)
    if not np.allclose(shown(), z, atol=1e-9):
        problems.append(f"browser sliders {shown()} != server sliders {list(z)} after {CATCH_UP_S:g} s")
    if d.decoded is None or d.decoded.latents is None or d.decoded.latents.z_b != z:
        problems.append(f"current gait decoded from {getattr(d.decoded, 'latents', None)}, sliders at {z}")
        return problems
    shape, body = d.model.decode(np.asarray(z)[None])
    commands = d.model.commands(shape[0])
    if not np.allclose(d.plots["forward (m)"].data[1], body[0, :, 1], atol=1e-9):
        problems.append("drawn generated path is not the decode of the final sliders")
    if d.simulated is None:
        problems.append("no replay drawn for the final sliders")
    elif not np.allclose(d.plots["forward (m)"].data[2], d.simulated.body[::4, 1], atol=1e-12):
        problems.append("drawn simulated path is not the final replay")
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        with page.expect_download(timeout=1000 * CATCH_UP_S) as info:
            page.get_by_role("button", name="Export CSV").click()
    except PlaywrightTimeout:
        problems.append(f"the exported CSV did not arrive in the browser within {CATCH_UP_S:g} s")
        return problems
    path = tmp / f"client{index}.csv"
    info.value.save_as(path)
    text = path.read_text()
    exported = read_gait_csv(text.encode()).commands
    if not np.array_equal(exported, commands):
        problems.append("exported commands are not those of the final sliders")
    if "# z_B: [" + ", ".join(f"{v:.4f}" for v in z) + "]" not in text:
        problems.append("exported z_B comment does not match the final sliders")
    return problems


def _phase(
    playwright, server: DesignerServer, n: int, seconds: float, rng, tmp: Path, log, render: bool
) -> dict:
    pages, designers, page_errors, browsers = [], [], [], []
    for _ in range(n):
        before = set(server.clients)
        # One browser per client, as each user has their own: pages of one browser share its input
        # and rendering pipeline, and background pages are throttled.
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=LOAD_ARGS)
        browsers.append(browser)
        page = browser.new_page(viewport=VIEWPORT, accept_downloads=True)
        page.on("pageerror", lambda exc: page_errors.append(str(exc)))
        page.goto(f"http://127.0.0.1:{server.port}")
        if not wait_until(lambda b=before: set(server.clients) - b, 90):
            raise RuntimeError("a browser page never connected to the designer")
        designers.append(server.clients[(set(server.clients) - before).pop()])
        page.get_by_role("slider").first.wait_for(timeout=90000)
        # The clients are load: they receive and apply every message but draw no pixels and stop
        # the 20 Hz snake animation (as a user may). With both on, 4 software-WebGL pages on a
        # 2-core machine stopped answering and each tab sent 1-2 slider updates a minute.
        if not render:
            page.add_style_tag(content="canvas { display: none !important; }")
            page.get_by_role("button", name="Pause").click()
        pages.append(page)
    for d in designers:
        d.wait_idle(120)
    errors_before = len(server.errors)
    n_sliders = designers[0].model.z_b_dim
    draggers = [_Dragger(p, n_sliders, np.random.default_rng(rng.integers(2**32))) for p in pages]
    start = time.perf_counter()
    t_start = time.monotonic()
    while time.perf_counter() - start < seconds:
        round_start = time.perf_counter()
        for dr in draggers:
            t0 = time.perf_counter()
            dr.step()
            dr.slowest_step_s = max(dr.slowest_step_s, time.perf_counter() - t0)
        time.sleep(max(0.0, 1.0 / POINTER_HZ - (time.perf_counter() - round_start)))
    for dr in draggers:
        dr.release()
    t_end = time.monotonic()
    settled = all(d.wait_idle(180) for d in designers)
    time.sleep(0.5)  # any slider message still in flight
    settled = settled and all(d.wait_idle(180) for d in designers)
    clients = []
    for i, (page, d, dr) in enumerate(zip(pages, designers, draggers, strict=True)):
        ts = [t for t in list(d.timings) if t.submitted >= start]
        dec = np.array([1e3 * (t.decoded - t.submitted) for t in ts if np.isfinite(t.decoded)])
        rep = np.array([1e3 * (t.replayed - t.submitted) for t in ts if np.isfinite(t.replayed)])
        drawn = [t for t in ts if np.isfinite(t.decoded) and np.isfinite(t.started)]
        # Where a decoded view's latency goes: waiting for the decode worker, decoding, drawing.
        wait = np.array([1e3 * (t.started - t.submitted) for t in drawn])
        work = np.array([t.decode_ms for t in drawn])
        draw = np.array([1e3 * (t.decoded - t.started) - t.decode_ms for t in drawn])
        stale = _stale_checks(page, d, tmp, i) if settled else ["did not settle within 180 s"]
        clients.append(
            {
                "mouse_moves": dr.moves,
                "slowest_move_s": dr.slowest_step_s,
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
                "stale": stale,
            }
        )
        if log:
            log(
                f"  client {i + 1}/{n}: {len(ts)} updates, decoded p95 {clients[-1]['decoded_p95_ms']:.1f} ms"
            )
    for browser in browsers:
        browser.close()
    wait_until(lambda: not server.clients, 30)
    return {
        "clients": clients,
        "server_exceptions": server.errors[errors_before:],
        "page_errors": page_errors,
        "t_start": t_start,
        "t_end": t_end,
    }


def bench_load(
    clients: int = 4,
    seconds: float = 60.0,
    checkpoint=None,
    ensemble: int = 8,
    seed: int = 0,
    log=print,
    render: bool = False,
    pin_cpus: bool = False,
) -> dict:
    """Run the single-client and ``clients``-client phases and summarise them (see module docstring)."""
    import tempfile

    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        raise RuntimeError(f"bench load drives Debian chromium at {CHROMIUM}: apt-get install -y chromium")
    split = split_cpus() if pin_cpus else None
    all_cpus = sorted(os.sched_getaffinity(0)) if split else None
    if split:
        _pin_process(split[0])  # before the server starts: its threads inherit the server half
    server = DesignerServer(port=0, checkpoint=checkpoint, ensemble=ensemble, verbose=False)
    rss = _RssSampler()
    browser_nice = _BrowserNice(BROWSER_NICE)
    # In use the browsers run on other machines. The driving thread (and so the Playwright driver
    # and every Chromium it starts) moves to the other CPUs, at nice +10.
    if split:
        os.sched_setaffinity(threading.get_native_id(), split[1])
    previous_nice = lower_thread_priority(BROWSER_NICE)
    rng = np.random.default_rng(seed)
    phases = {}
    try:
        with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
            for n in sorted({1, clients}):
                if log:
                    log(f"{n} client(s) dragging sliders for {seconds:g} s")
                phases[n] = _phase(p, server, n, seconds, rng, Path(tmp), log, render)
    finally:
        rss.stop()
        browser_nice.stop()
        server.stop()
        set_thread_nice(previous_nice)  # lowering needs no privilege; raising back may (then it stays)
        if all_cpus:
            _pin_process(all_cpus)
    multi = phases[clients]
    single = phases[1]["clients"][0]
    window = rss.window(multi["t_start"], multi["t_end"])
    slope = float(np.polyfit(window[:, 0], window[:, 1], 1)[0] * 60.0) if len(window) > 2 else float("nan")
    all_rss = np.asarray(rss.samples)[:, 1]
    p95s = [c["decoded_p95_ms"] for c in multi["clients"]]
    result = {
        "clients": clients,
        "seconds": seconds,
        "rendered": render,
        "server_cpus": split[0] if split else None,
        "browser_cpus": split[1] if split else None,
        "single_decoded_p50_ms": single["decoded_p50_ms"],
        "single_decoded_p95_ms": single["decoded_p95_ms"],
        "single_replay_p95_ms": single["replay_p95_ms"],
        "multi_decoded_p50_ms": [c["decoded_p50_ms"] for c in multi["clients"]],
        "multi_decoded_p95_ms": p95s,
        "multi_replay_p95_ms": [c["replay_p95_ms"] for c in multi["clients"]],
        "single_breakdown_p95_ms": {k: single[f"{k}_p95_ms"] for k in ("wait", "decode", "draw")},
        "multi_breakdown_p95_ms": {
            k: [c[f"{k}_p95_ms"] for c in multi["clients"]] for k in ("wait", "decode", "draw")
        },
        "p95_ratio": float(np.nanmax(p95s) / single["decoded_p95_ms"]),
        "updates": [c["updates"] for c in multi["clients"]],
        "mouse_moves": [c["mouse_moves"] for c in multi["clients"]],
        "slowest_move_s": [c["slowest_move_s"] for c in multi["clients"]],
        "server_exceptions": len(phases[1]["server_exceptions"]) + len(multi["server_exceptions"]),
        "exception_messages": (phases[1]["server_exceptions"] + multi["server_exceptions"])[:10],
        "page_errors": len(phases[1]["page_errors"]) + len(multi["page_errors"]),
        "stale_draws": sum(bool(c["stale"]) for ph in phases.values() for c in ph["clients"]),
        "stale_details": [c["stale"] for ph in phases.values() for c in ph["clients"] if c["stale"]],
        "rss_start_mb": float(all_rss[0]),
        "rss_end_mb": float(all_rss[-1]),
        "rss_peak_mb": float(all_rss.max()),
        "rss_multi_start_mb": float(window[0, 1]) if len(window) else float("nan"),
        "rss_multi_end_mb": float(window[-1, 1]) if len(window) else float("nan"),
        "rss_slope_mb_per_min": slope,
    }
    return result
