"""bench load's end-of-run checks: they wait for late slider messages and re-check a moving state."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

import snakeloco.app.bench.users.load_browser as load


class _Tab:
    """Stands in for a DesignerClient: sliders with values, and an idle wait."""

    def __init__(self, values):
        self.sliders = [SimpleNamespace(value=v) for v in values]

    def wait_idle(self, timeout):
        return True


def test_wait_quiet_waits_for_a_late_slider_message():
    tab = _Tab([0.0, 1.0])

    def late_message():
        time.sleep(0.4)
        tab.sliders[0].value = 0.5  # a starved page's last pointer move arrives after the drag ended

    t = threading.Thread(target=late_message)
    start = time.monotonic()
    t.start()
    assert load.wait_quiet([tab], quiet_s=0.6, timeout_s=10)
    t.join()
    assert time.monotonic() - start >= 0.4 + 0.6  # quiet counted from the late message, not the start


def test_wait_quiet_gives_up_on_sliders_that_never_settle():
    tab = _Tab([0.0])
    stop = threading.Event()

    def keep_moving():
        while not stop.is_set():
            tab.sliders[0].value += 1.0
            time.sleep(0.05)

    t = threading.Thread(target=keep_moving)
    t.start()
    try:
        assert not load.wait_quiet([tab], quiet_s=0.5, timeout_s=1.0)
    finally:
        stop.set()
        t.join()


def test_stale_checks_recheck_a_state_that_moved_but_report_real_mismatches(monkeypatch):
    monkeypatch.setattr(load, "wait_quiet", lambda designers: True)
    results = iter(
        [["exported commands are not those of the final sliders", f"{load.MOVED}: [0] -> [1]"], []]
    )
    monkeypatch.setattr(load, "check_final_state", lambda *a: next(results))
    assert load.stale_checks(None, None, None, 0) == []  # the second look, at the final values, is clean

    real = ["drawn generated path is not the decode of the final sliders"]
    monkeypatch.setattr(load, "check_final_state", lambda *a: list(real))
    assert load.stale_checks(None, None, None, 0) == real  # no movement: a stale draw is reported as such

    moving = ["x", f"{load.MOVED}: [0] -> [1]"]
    calls = []
    monkeypatch.setattr(load, "check_final_state", lambda *a: calls.append(1) or list(moving))
    assert load.stale_checks(None, None, None, 0, attempts=3) == moving  # never settles: reported
    assert len(calls) == 3


def test_the_breakdown_splits_a_decoded_view_and_a_first_motion_into_their_stages():
    from snakeloco.app.designer.session import Timing

    t = Timing(1, submitted=0.0, started=0.002, decoded=0.010, first_chunk=0.060, first_motion=0.065)
    t.decode_ms = 5.0
    young = Timing(2, submitted=1.0, started=1.001, decoded=1.009)  # superseded before it moved
    young.decode_ms = 4.0
    got = load.breakdown_p95([t, young])
    assert set(got) == {f"{k}_p95_ms" for k in load.BREAKDOWN}
    assert abs(got["physics_p95_ms"] - 50.0) < 1e-6 and abs(got["motion_draw_p95_ms"] - 5.0) < 1e-6
    assert abs(got["draw_p95_ms"] - 3.95) < 1e-6  # 8 - 5 and 8 - 4 ms: their p95


def test_browser_nice_puts_the_browsers_threads_at_its_nice_and_in_the_idle_class():
    """The page beside the protocol clients stands for a browser on another machine: nice 19 and
    ``SCHED_IDLE``, every thread of every process this one started (not its decode processes)."""
    import os
    import subprocess
    import sys

    import pytest

    from snakeloco.app.bench.users.load_driver import wait_until
    from snakeloco.app.bench.users.processes import BrowserNice

    if not hasattr(os, "SCHED_IDLE") or not os.path.isdir("/proc/self/task"):
        pytest.skip("no idle scheduling class here")
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import threading, time; threading.Thread(target=time.sleep, args=(30,)).start(); time.sleep(30)",
        ]
    )
    idle, plain = BrowserNice(19, period=0.05, idle=True), None
    try:

        def settled(pid: int) -> bool:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
            return len(tids) == 2 and all(
                os.getpriority(os.PRIO_PROCESS, t) == 19 and os.sched_getscheduler(t) == os.SCHED_IDLE
                for t in tids
            )

        assert wait_until(lambda: settled(child.pid), 10)
        assert os.sched_getscheduler(0) != os.SCHED_IDLE  # this process keeps its class
        idle.stop()
        plain = BrowserNice(10, period=0.05)  # without idle: a browser's class is left as it is
        time.sleep(0.3)
        assert os.sched_getscheduler(child.pid) == os.SCHED_IDLE
    finally:
        idle.stop()
        if plain is not None:
            plain.stop()
        child.kill()
        child.wait()


def test_every_view_a_tab_drew_is_timed_server_side_and_the_superseded_ones_are_not():
    from snakeloco.app.designer.session import Timing

    drawn, superseded, late = Timing(1, 10.0), Timing(2, 10.05), Timing(3, 10.1)
    drawn.decoded, late.decoded = 10.012, 10.125  # the second value was overtaken before its draw
    assert load.view_times_ms([drawn, superseded, late]) == pytest.approx([12.0, 25.0])
    assert load.view_times_ms([]) == []
