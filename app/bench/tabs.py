"""``snakeloco bench tabs``: several designer tabs animating in one headless Chromium.

The pages render (software WebGL) and animate the snake the whole time, as tabs tiled side by side
on one screen do; nothing is hidden or paused. Round after round, each tab in turn is brought to the
front and gets one arrow key on its first z_B slider, as a person switches tabs and types; the
others keep animating behind it. What is timed (from bringing the tab to the front):

- key press -> the new value at the server (``press_to_server``: the page handled the key, sent
  the value, the server applied it), per tab p50/p95, and how long the press itself took in the
  page (``press_call``: a starved page takes long to handle input at all); a press the page did
  not take within 30 s, or whose value did not reach the server within ``VALUE_TIMEOUT_S``, counts
  as lost;
- after the rounds, each tab's Export CSV: click -> the browser holds the downloaded file (a valid
  gait file of that tab's current z_B).

The browser runs at ``browser_nice`` (default 0), it and its scheduling group: a person's browser
beside the server on one machine, where the server's physics sits at nice +10/+15 inside the
server's group. At +10, as ``bench load`` puts its load generators to measure the server, the
browser's whole group weighs a tenth of the server's: while the server replays and fans out a
new gait (seconds of both cores per key press), software WebGL gets ~10% of the machine, every
frame's readback (``preserveDrawingBuffer``, software compositing) takes ~0.6 s, the page's main
thread waits on it in "Commit", and a key press waits seconds (a Chromium trace of 3 tabs: the
GPU process's main thread busy 94% of the time, nearly all of it in ``readPixels``). At nice 0
what a frame costs decides it: each page ticks "Light rendering" itself in software WebGL (no
shadows, environment map or shaded grid: 12.4 frames/s against 5.6), and ``rendering`` measures
the page's choice, or every tab full, or every tab light (docs/load.md).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from snakeloco.app.bench.users.load_browser import comment_numbers, percentile, require_browser
from snakeloco.app.bench.users.load_driver import CHROMIUM, CHROMIUM_ARGS, wait_until
from snakeloco.app.bench.users.processes import BrowserNice, RssSampler
from snakeloco.app.export.gait_csv import read_gait_csv
from snakeloco.app.server.lifecycle import DesignerServer, freeze_started, tune_process
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE

LAYOUT_TIMEOUT_S = 120.0
"""How long a page may take to lay out its controls before the rounds start."""
RENDERINGS = ("page", "full", "light")
"""How the tabs draw: as each page chose, or all full, or all light (``bench_tabs``)."""
VALUE_TIMEOUT_S = 30.0
"""How long a key press may take to reach the server before it counts as lost."""


def _changed(read, old: float, timeout: float) -> bool:
    """Poll ``read()`` every 2 ms until it differs from ``old`` (True) or ``timeout`` s pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if read() != old:
            return True
        time.sleep(0.002)
    return False


def bench_tabs(
    tabs: int = 3,
    rounds: int = 10,
    checkpoint=None,
    ensemble: int = ENSEMBLE_SIZE,
    log=print,
    browser_nice: int = 0,
    rendering: str = "page",
) -> dict:
    """Open ``tabs`` rendering pages in one Chromium and time key presses and exports (module doc).

    ``rendering``: "page" leaves "Light rendering" as each page set it (on where WebGL renders in
    software, as here), "full" or "light" sets every tab's once the pages are laid out.
    """
    if rendering not in RENDERINGS:
        raise ValueError(f"rendering {rendering!r}: one of {RENDERINGS}")
    require_browser("bench tabs")
    from playwright.sync_api import TimeoutError as PlaywrightTimeout
    from playwright.sync_api import sync_playwright

    tune_process()
    # Without the Variations fan: the figures stay comparable with docs/load.md (the fan runs after
    # the ensemble at the pool's lowest turn but design; docs/variations.md has its own timing).
    server = DesignerServer(
        port=0, checkpoint=checkpoint, ensemble=ensemble, verbose=False, variations=False, closed_loop=False
    )
    freeze_started()  # as `snakeloco serve` does
    rss = RssSampler()
    nice = BrowserNice(browser_nice)
    press_server: list[list[float]] = [[] for _ in range(tabs)]
    press_call: list[list[float]] = [[] for _ in range(tabs)]
    lost = [0] * tabs
    light: list[bool] = []
    exports: list[float] = []
    export_ok: list[bool] = []
    export_errors: list[str | None] = []
    try:
        with sync_playwright() as p, tempfile.TemporaryDirectory() as tmp:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            context = browser.new_context(viewport={"width": 1280, "height": 800}, accept_downloads=True)
            pages, designers = [], []
            for _ in range(tabs):
                before = set(server.clients)
                page = context.new_page()
                page.goto(f"http://127.0.0.1:{server.port}")
                if not wait_until(lambda b=before: set(server.clients) - b, 90):
                    raise RuntimeError("a browser page never connected to the designer")
                designers.append(server.clients[(set(server.clients) - before).pop()])
                pages.append(page)
            for d in designers:
                d.wait_idle(120)
            for page in pages:  # laid out: on a busy machine a page can take tens of seconds
                page.get_by_role("button", name="Export CSV").wait_for(timeout=LAYOUT_TIMEOUT_S * 1e3)
            if rendering != "page":
                time.sleep(2.0)  # the pages' own choice first (made once, as soon as they are laid out)
                for d in designers:
                    d.controls.light.value = rendering == "light"
            light = [bool(d.controls.light.value) for d in designers]
            if log:
                log(
                    f"{tabs} tabs open and animating (light rendering {light}); "
                    f"{rounds} rounds of one key press per tab"
                )
            sliders = [page.get_by_role("slider").first for page in pages]
            for r in range(rounds):
                for i, (page, slider, d) in enumerate(zip(pages, sliders, designers, strict=True)):
                    key = "ArrowRight" if (r // 5) % 2 == 0 else "ArrowLeft"  # stay inside the range
                    value = d.sliders[0].value
                    t0 = time.monotonic()
                    try:
                        page.bring_to_front()  # as a person switches to the tab they type in
                        slider.press(key)
                    except PlaywrightTimeout:  # the page did not take the key within 30 s
                        lost[i] += 1
                        continue
                    t1 = time.monotonic()
                    press_call[i].append(1e3 * (t1 - t0))
                    if _changed(lambda d=d: d.sliders[0].value, value, VALUE_TIMEOUT_S):
                        press_server[i].append(1e3 * (time.monotonic() - t0))
                    else:
                        lost[i] += 1
                if log:
                    log(f"  round {r + 1}/{rounds}")
            for i, (page, d) in enumerate(zip(pages, designers, strict=True)):
                t0 = time.monotonic()

                # The tab's current gait: the one drawn, or the slider's newer value still being
                # decoded (a starved tab's last key press can reach the server late); either is
                # its own, and what Export CSV writes is the drawn one.
                def current(d=d) -> set[float]:
                    return {d.sliders[0].value, *([d.decoded.latents.sliders[0]] if d.decoded else [])}

                own = current()
                try:
                    page.bring_to_front()
                    with page.expect_download(timeout=60_000) as info:
                        page.get_by_role("button", name="Export CSV").click(timeout=60_000)
                    path = Path(tmp) / f"tab{i}.csv"
                    info.value.save_as(path)
                    exports.append(time.monotonic() - t0)
                    read_gait_csv(
                        path.read_bytes(), DEFAULT_ROBOT
                    )  # a whole, valid gait file, of this tab's gait
                    own |= current()
                    text = path.read_text()
                    first = [
                        numbers[0]
                        for ln in text.splitlines()
                        if ln.startswith(("# z_B: [", "# sliders: [")) and (numbers := comment_numbers(ln))
                    ]
                    export_ok.append(any(abs(f - v) < 5e-5 for f in first for v in own))
                    export_errors.append(
                        None
                        if export_ok[-1]
                        else "the file is not of the tab's current gait (z_B 1 of none of "
                        f"{sorted(own)}): {next((ln for ln in text.splitlines() if 'z_B' in ln), 'no z_B line')}"
                    )
                except Exception as exc:  # a timeout or a bad file: reported, not raised
                    exports.append(time.monotonic() - t0)
                    export_ok.append(False)
                    export_errors.append(f"{type(exc).__name__}: {exc}")
                if log and export_errors[-1]:
                    log(f"  tab {i + 1}: export failed: {export_errors[-1]}")
            browser.close()
    finally:
        nice.stop()
        rss.stop()
        server.stop()
    every = [v for per in press_server for v in per]
    return {
        "tabs": tabs,
        "rounds": rounds,
        "browser_nice": browser_nice,
        "rendering": rendering,
        "light_rendering": light,
        "cpus": len(os.sched_getaffinity(0)),
        "press_to_server_p50_ms": [percentile(v, 50) for v in press_server],
        "press_to_server_p95_ms": [percentile(v, 95) for v in press_server],
        "press_to_server_p95_all_ms": percentile(every, 95),
        "press_call_p95_ms": [percentile(v, 95) for v in press_call],
        "lost_presses": lost,
        "export_s": exports,
        "export_ok": export_ok,
        "export_errors": export_errors,
        "server_exceptions": len(server.errors),
        "exception_messages": server.errors[:10],
    }
