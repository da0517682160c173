"""The browser side of ``snakeloco bench load``: one process per simulated user, driving a Chromium page.

Why processes of their own: Playwright's sync API is Python work on every pointer move (the
protocol's JSON, its event loop). Run in the server's process, that driver thread shares the
server's GIL, and held at nice +10 (the browsers are load, not the system under test) it is often
descheduled *while holding the GIL*: every server thread then waits for it. And one driver for all
pages moves them in turn, so the slowest page sets every page's pace. In use each browser sits on
its own machine; here each at least sits in its own process, all at nice +10 (children inherit it).

This module imports only numpy and Playwright (not the server, torch or MuJoCo), so the spawned
process starts fast and small. It answers commands sent over a ``multiprocessing`` pipe: see
``_COMMANDS``; every answer is ``("ok", value)`` or ``("error", message)``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import threading
import time
import traceback

import numpy as np

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
LOAD_ARGS = [
    *CHROMIUM_ARGS,
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
]
POINTER_HZ = 60.0
"""Most pointer moves per second per page, as a 60 Hz display delivers them during a drag."""
DWELL_S = 3.0
"""Seconds a page rests with the mouse up after each drag (``--dwell``): a person looks at the
gait they let go of. Without rests (0) a replay finishes only when the drags stop (1-4 a page in
60 s), and the replay-ready figures are a handful of samples."""
VIEWPORT = {"width": 960, "height": 600}
PAGE_SAMPLE_S = 30.0
"""How often a dragging page's own state is sampled (JS heap, DOM size, long tasks, pointer moves);
a third of the drags' time where that is shorter."""
PAGE_PROBE = """() => {
  if (!window.__slLong) {
    window.__slLong = [];
    new PerformanceObserver((l) => { for (const e of l.getEntries()) window.__slLong.push(e.duration); })
      .observe({type: "longtask", buffered: true});
  }
  const long = window.__slLong.splice(0);
  return {heap_mb: performance.memory ? performance.memory.usedJSHeapSize / 1e6 : null,
          dom_nodes: document.getElementsByTagName("*").length,
          long_tasks: long.length, long_ms: long.reduce((a, b) => a + b, 0)};
}"""
"""Page-side figures since the last probe: the JS heap in use, the DOM's element count and the main
thread's long tasks (> 50 ms; Chromium's Long Tasks API), so a page that slows over a long run shows
where its time goes."""
"""Each page's size: software WebGL's cost grows with the pixels, and the browsers are only load."""


def wait_until(predicate, timeout: float = 60.0) -> bool:
    """Poll ``predicate`` every 50 ms until it is true (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


class _Dragger:
    """One page's mouse, dragging a random z_B slider thumb to random targets in small steps."""

    def __init__(self, page, n_sliders: int, rng: np.random.Generator, dwell: float = 0.0) -> None:
        self.page = page
        self.dwell = dwell  # seconds with the mouse up after each drag, looking at the replay
        self._rest_until = 0.0
        self.n_sliders = n_sliders
        self.rng = rng
        self.moves = 0
        self.slowest_step_s = 0.0  # the longest a page took to take one pointer move
        self.step_s: list[float] = []  # each pointer move: dispatched until the page took it
        self.sampled = 0  # moves already in a page sample
        self.stalls = 0  # times the page did not show its sliders within 30 s
        self._steps_left = 0
        self._x = self._y = 0.0
        self._target = 0.0

    def step(self) -> bool:
        """One pointer move of the current drag (True), or a rest (False)."""
        mouse = self.page.mouse
        if self._steps_left == 0 and self.dwell > 0 and self._rest_until == 0.0 and self.moves:
            mouse.up()  # a drag ends: the released value's replay gets ``dwell`` seconds to finish
            self._rest_until = time.perf_counter() + self.dwell
            return False
        if time.perf_counter() < self._rest_until:
            return False
        if self._steps_left == 0:
            self._rest_until = 0.0
            mouse.up()
            from playwright.sync_api import TimeoutError as PlaywrightTimeout

            thumb = self.page.get_by_role("slider").nth(int(self.rng.integers(self.n_sliders)))
            try:  # a page starved of CPU may not lay out its sliders within Playwright's 30 s
                thumb.scroll_into_view_if_needed()  # below the readout in a short window
                box = thumb.bounding_box()
                track = thumb.locator("xpath=..").bounding_box()
            except PlaywrightTimeout:
                self.stalls += 1
                return False
            if box is None or track is None:
                return False
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
        return True

    def release(self) -> None:
        self.page.mouse.up()
        self._steps_left = 0


class _Driver:
    """Pages driven from this process, one browser each (as each user has their own: pages of one
    browser share its input and rendering pipeline, and background pages are throttled). The
    benchmark opens one page per process."""

    def __init__(self, playwright, url: str, render: bool) -> None:
        self.playwright, self.url, self.render = playwright, url, render
        self.browsers, self.pages, self.page_errors = [], [], []
        self.processes: list[tuple[subprocess.Popen, str]] = []

    def open(self) -> int:
        """Open one more page on the designer; returns its index once its sliders are shown."""
        browser = self._launch()
        context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
        page = context.new_page()
        page.on("pageerror", lambda exc: self.page_errors.append(str(exc)))
        page.goto(self.url)
        page.get_by_role("slider").first.wait_for(timeout=90000)
        # The clients are load: they receive and apply every message but draw no pixels and stop
        # the 20 Hz snake animation (as a user may). With both on, 4 software-WebGL pages on a
        # 2-core machine stopped answering and each tab sent 1-2 slider updates a minute.
        if not self.render:
            page.add_style_tag(content="canvas { display: none !important; }")
            page.get_by_role("button", name="Pause").click()
        self.pages.append(page)
        return len(self.pages) - 1

    def _launch(self):
        """Start Chromium as a child of this process and attach Playwright to it over CDP.

        Not ``chromium.launch``: Playwright starts the browser in a new session, and where the kernel
        groups sessions for scheduling (``sched_autogroup_enabled``) a thread's nice then only
        counts inside its group while the groups share the CPUs equally: 4 browsers held the server
        to a fifth of the machine, or, with their groups niced, the server's background physics
        starved the browsers. In this session the order is the intended one: the server's
        interactive threads (nice 0) before the browsers (+10) before the physics (+15).
        """
        profile = tempfile.mkdtemp(prefix="snakeloco-load-")
        proc = subprocess.Popen(
            [CHROMIUM, *LOAD_ARGS, "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.processes.append((proc, profile))
        endpoint = _devtools_endpoint(proc, timeout=60.0)
        threading.Thread(target=proc.stderr.read, daemon=True).start()  # keep the pipe drained
        browser = self.playwright.chromium.connect_over_cdp(endpoint)
        self.browsers.append(browser)
        return browser

    def drag(self, seconds: float, n_sliders: int, seeds: list[int], dwell: float = 0.0) -> list[dict]:
        """Every page drags sliders for ``seconds``, resting ``dwell`` seconds after each drag; then
        every mouse is released."""
        draggers = [
            _Dragger(p, n_sliders, np.random.default_rng(s), dwell)
            for p, s in zip(self.pages, seeds, strict=True)
        ]
        start = time.perf_counter()
        samples: list[list[dict]] = [[] for _ in draggers]
        for page in self.pages:
            page.evaluate(PAGE_PROBE)  # installs the long-task observer
        period = min(PAGE_SAMPLE_S, seconds / 3)  # a short run gets its samples too
        next_sample = start + period
        while time.perf_counter() - start < seconds:
            round_start = time.perf_counter()
            if round_start >= next_sample:
                next_sample += period
                for dr, page, out in zip(draggers, self.pages, samples, strict=True):
                    window, dr.sampled = dr.step_s[dr.sampled :], len(dr.step_s)
                    out.append(
                        page.evaluate(PAGE_PROBE)
                        | {
                            "t_s": round_start - start,
                            "moves": len(window),
                            "move_p95_ms": float(np.percentile(window, 95)) * 1e3 if window else float("nan"),
                        }
                    )
            for dr in draggers:
                t0 = time.perf_counter()
                if not dr.step():
                    continue
                dr.step_s.append(time.perf_counter() - t0)
                dr.slowest_step_s = max(dr.slowest_step_s, dr.step_s[-1])
            time.sleep(max(0.0, 1.0 / POINTER_HZ - (time.perf_counter() - round_start)))
        for dr in draggers:
            dr.release()
        return [
            {
                "mouse_moves": dr.moves,
                "stalls": dr.stalls,
                "slowest_move_s": dr.slowest_step_s,
                "move_p50_ms": float(np.percentile(dr.step_s, 50)) * 1e3 if dr.step_s else float("nan"),
                "move_p95_ms": float(np.percentile(dr.step_s, 95)) * 1e3 if dr.step_s else float("nan"),
                "page_samples": out,
            }
            for dr, out in zip(draggers, samples, strict=True)
        ]

    def shown(self, index: int) -> list[float]:
        """The slider values page ``index`` shows (aria-valuenow)."""
        values = (
            self.pages[index]
            .get_by_role("slider")
            .evaluate_all("els => els.map(e => e.getAttribute('aria-valuenow'))")
        )
        return [float(v) for v in values]

    def export(self, index: int, path: str, timeout_s: float) -> bool:
        """Press "Export CSV" on page ``index`` and save the download to ``path``; False if it did not
        arrive within ``timeout_s``."""
        from playwright.sync_api import TimeoutError as PlaywrightTimeout

        try:
            with self.pages[index].expect_download(timeout=1000 * timeout_s) as info:
                self.pages[index].get_by_role("button", name="Export CSV").click()
        except PlaywrightTimeout:
            return False
        info.value.save_as(path)
        return True

    def errors(self) -> list[str]:
        return list(self.page_errors)

    def close(self) -> None:
        for browser in self.browsers:
            try:
                browser.close()
            except Exception:  # the connection may already be gone; the process is ended below
                pass
        for proc, profile in self.processes:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
            shutil.rmtree(profile, ignore_errors=True)
        self.browsers, self.pages, self.processes = [], [], []


def _devtools_endpoint(proc: subprocess.Popen, timeout: float) -> str:
    """The ws:// address Chromium prints on stderr once its DevTools server listens."""
    found: list[str] = []

    def scan() -> None:
        for line in proc.stderr:
            if "DevTools listening on " in line:
                found.append(line.split("DevTools listening on ", 1)[1].strip())
                return

    reader = threading.Thread(target=scan, daemon=True)
    reader.start()
    reader.join(timeout)
    if not found:
        proc.kill()
        raise RuntimeError(
            f"{CHROMIUM} printed no DevTools address within {timeout:g} s (exit code {proc.poll()})"
        )
    return found[0]


_COMMANDS = ("open", "drag", "shown", "export", "errors", "close")


def main(conn, url: str, render: bool, nice: int, cpus: list[int] | None) -> None:
    """Process entry: serve commands ``(name, *args)`` from ``conn`` until ``("quit",)`` or EOF."""
    if nice and hasattr(os, "nice"):
        os.nice(nice)  # Playwright's driver and every Chromium inherit it
    if cpus and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, cpus)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        driver = _Driver(p, url, render)
        try:
            while True:
                try:
                    name, *args = conn.recv()
                except EOFError:
                    return
                if name == "quit":
                    return
                try:
                    if name not in _COMMANDS:
                        raise ValueError(f"unknown command {name!r}")
                    conn.send(("ok", getattr(driver, name)(*args)))
                except Exception as exc:  # reported to the benchmark, which raises it there
                    conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"))
        finally:
            driver.close()
