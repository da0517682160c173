"""The browser side of ``snakeloco bench load``: users as Chromium pages, each driven from a process of
its own (``load_driver``), and the checks that nothing a tab shows or exports is stale.

``--driver browser`` runs a page per user; ``--driver protocol`` runs one page beside its protocol
clients (``load_protocol``), checked the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snakeloco.app.bench.users import load_driver
from snakeloco.app.bench.users.load_driver import CHROMIUM, wait_until
from snakeloco.app.bench.users.processes import CpuSplit, rss_mb
from snakeloco.app.designer import panel
from snakeloco.app.designer.gui import path_plot_values
from snakeloco.app.designer.tab import DesignerClient
from snakeloco.app.export.gait_csv import read_gait_csv
from snakeloco.app.server.lifecycle import DesignerServer
from snakeloco.sim import BODY_DOWNSAMPLE


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


def comment_numbers(line: str) -> list[float] | None:
    """The numbers of a gait CSV's list comment ("# z_B: [0.1, -0.3]", "# sliders: [...] in cluster
    2"), or None where they are not numbers (z_B is written exactly, the slider values to 4 places)."""
    inside = line[line.find("[") + 1 : line.find("]")] if "[" in line and "]" in line else ""
    try:
        return [float(v) for v in inside.split(",")]
    except ValueError:
        return None


def percentile(values, q: float) -> float:
    """The q-th percentile of ``values`` (a list or array); NaN for none."""
    v = np.asarray(values, np.float64)
    return float(np.percentile(v, q)) if v.size else float("nan")


BREAKDOWN = ("wait", "decode", "draw", "physics", "motion_draw")
"""The stages ``breakdown_p95`` times: a decoded view's (waiting for a decode turn, decoding,
drawing) and its first motion's (decoded view drawn -> first chunk simulated, that chunk drawn)."""


def breakdown_p95(timings) -> dict[str, float]:
    """Where a tab's decoded views and first motions went (p95, ms; ``BREAKDOWN``)."""
    drawn = [t for t in timings if np.isfinite(t.decoded) and np.isfinite(t.started)]
    moved = [t for t in drawn if np.isfinite(t.first_motion) and np.isfinite(t.first_chunk)]
    return {
        "wait_p95_ms": percentile([1e3 * (t.started - t.submitted) for t in drawn], 95),
        "decode_p95_ms": percentile([t.decode_ms for t in drawn], 95),
        "draw_p95_ms": percentile([1e3 * (t.decoded - t.started) - t.decode_ms for t in drawn], 95),
        "physics_p95_ms": percentile([1e3 * (t.first_chunk - t.decoded) for t in moved], 95),
        "motion_draw_p95_ms": percentile([1e3 * (t.first_motion - t.first_chunk) for t in moved], 95),
    }


def view_times_ms(timings) -> list[float]:
    """Every decoded view a tab drew, server side (value in -> view drawn; ms): each value a drag
    passed through, not only its last, so that a phase has thousands where it has ~100 drags (the
    tail of the server's own time, steady from run to run where the worst client's p95 is not)."""
    return [1e3 * (t.decoded - t.submitted) for t in timings if np.isfinite(t.decoded)]


class Browser:
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


def wait_quiet(designers: list[DesignerClient], quiet_s: float = 2.0, timeout_s: float = 180.0) -> bool:
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


def stale_checks(browser: Browser, d: DesignerClient, tmp: Path, index: int, attempts: int = 3) -> list[str]:
    """``check_final_state``, again from the new values if a late browser event moved the sliders
    while it ran (that is not a stale draw: the state it checked was not yet final)."""
    for _ in range(attempts):
        problems = check_final_state(browser, d, tmp, index)
        if not (problems and problems[-1].startswith(MOVED)):
            return problems
        wait_quiet([d])
    return problems


def replay_problems(d: DesignerClient) -> list[str]:
    """Whether a settled tab shows the replay of its current gait: its simulated path, or, where
    physics refused the gait (thrown, diverged), the panel saying so for that gait."""
    if d.simulated is not None:
        drawn = d.controls.plots["forward (m)"].data[2]
        if np.array_equal(drawn, path_plot_values(d.simulated.body[::BODY_DOWNSAMPLE, 1])):
            return []
        return ["drawn simulated path is not the final replay"]
    last = d.timings[-1] if d.timings else None
    if last is None or last.failed is None or not d.is_current(last.version):
        return ["no replay drawn for the final sliders"]
    if d.controls.panel.content != panel.failed_text(d.decoded, last.failed):
        return [f"the final replay failed ({last.failed}) but the panel does not say so"]
    return []


def check_final_state(browser: Browser, d: DesignerClient, tmp: Path, index: int) -> list[str]:
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
        commands = members[0].commands(d.session.robot)
    else:
        shape, body = d.model.decode(z_b)
        commands = d.model.commands(shape[0])
    if not np.array_equal(d.controls.plots["forward (m)"].data[1], path_plot_values(body[0, :, 1])):
        problems.append("drawn generated path is not the decode of the final sliders")
    problems += replay_problems(d)
    path = tmp / f"client{index}.csv"
    if not browser.call("export", 0, str(path), CATCH_UP_S, timeout=CATCH_UP_S + 60):
        problems.append(f"the exported CSV did not arrive in the browser within {CATCH_UP_S:g} s")
        return problems
    text = path.read_text()
    exported = read_gait_csv(text.encode(), d.session.robot).commands
    if not np.array_equal(exported, commands):
        problems.append("exported commands are not those of the final sliders")
    key = "# sliders: [" if d.decoded.latents.axes is not None else "# z_B: ["
    line = next((ln for ln in text.splitlines() if ln.startswith(key)), None)
    written = comment_numbers(line) if line is not None else None
    if written is None or len(written) != len(z) or not np.allclose(written, z, atol=5e-5):
        problems.append(
            f"exported z_B comment does not match the final sliders {list(z)}: {line or f'no {key[2:-3]} line'!r}"
        )
    now = tuple(float(s.value) for s in d.sliders)
    if problems and now != z:  # says whether a late browser event moved the sliders during the checks
        problems.append(f"{MOVED}: {list(z)} -> {list(now)}")
    return problems


def browser_phase(server: DesignerServer, n: int, seconds: float, rng, tmp: Path, log, pages: Pages) -> dict:
    browsers: list[Browser] = []
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
        browsers.append(Browser(f"http://127.0.0.1:{server.port}", pages))
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
    settled = wait_quiet(designers)  # slider messages a starved page sends late
    rss_idle_after = rss_mb()  # the same tabs, idle again after the drags
    clients = []
    for i, (browser, d, dr) in enumerate(zip(browsers, designers, moves, strict=True)):
        ts = [t for t in list(d.timings) if t.submitted >= start]
        dec = np.array([1e3 * (t.decoded - t.submitted) for t in ts if np.isfinite(t.decoded)])
        rep = np.array([1e3 * (t.replayed - t.submitted) for t in ts if np.isfinite(t.replayed)])
        motion = np.array([1e3 * (t.first_motion - t.submitted) for t in ts if np.isfinite(t.first_motion)])
        stale = stale_checks(browser, d, tmp, i) if settled else ["did not settle within 180 s"]
        clients.append(
            {
                **dr,
                "updates": len(ts),
                "decoded_drawn": int(dec.size),
                "replays_drawn": int(rep.size),
                "decoded_p50_ms": percentile(dec, 50),
                "decoded_p95_ms": percentile(dec, 95),
                **breakdown_p95(ts),
                "view_ms": view_times_ms(ts),
                "replay_p50_ms": percentile(rep, 50),
                "replay_p95_ms": percentile(rep, 95),
                "first_motion_p50_ms": percentile(motion, 50),
                "first_motion_p95_ms": percentile(motion, 95),
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
