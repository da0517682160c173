"""What ``bench load`` does to processes and threads on Linux: CPU halves for server and browsers,
priorities of the browsers it starts, and the server's resident memory over time."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from snakeloco.app.server.decode_process import decode_pids


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


def pin_process(cpus) -> None:
    """Pin every thread of this process to ``cpus`` (threads started later inherit their creator's)."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:  # the thread ended meanwhile
            pass


def server_pids() -> list[int]:
    """This process (the server) and its decode processes (``app.server.decode_process``)."""
    return [os.getpid(), *sorted(decode_pids())]


SPARED: set[int] = set()
"""Processes this one started that ``BrowserNice`` leaves at their own priority (the protocol clients)."""


def browser_pids() -> list[int]:
    """Every process this one started but its decode processes: the browsers and what they started."""
    server = decode_pids()
    return [pid for pid in descendants(os.getpid()) if pid not in server]


def rss_mb() -> float:
    """Resident set size of the server: this process and its decode processes (MB)."""
    return sum(rss_split_mb())


def rss_split_mb() -> tuple[float, float]:
    """Resident set sizes (MB) of this process and of its decode processes together."""
    import psutil

    sizes = []
    for pid in server_pids():
        try:
            sizes.append(psutil.Process(pid).memory_info().rss / 2**20)
        except psutil.NoSuchProcess:
            sizes.append(0.0)
    return sizes[0], sum(sizes[1:])


def descendants(root: int) -> list[int]:
    """Process ids of every process descended from ``root``."""
    import psutil

    try:
        return sorted(p.pid for p in psutil.Process(root).children(recursive=True))
    except psutil.NoSuchProcess:
        return []


def cpu_seconds(pid: int | None = None) -> float:
    """User plus system CPU time of a process so far (s; None: this one); NaN where it is gone."""
    import psutil

    try:
        t = psutil.Process(pid).cpu_times()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return float("nan")
    return t.user + t.system


class CpuSplit:
    """Cores the server (this process and its decode processes) and the processes it started (the
    browsers) used between construction and ``stop()``: what the load figures owe to the server and
    what to the browsers where both share the CPUs."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()
        self._server = {pid: cpu_seconds(pid) for pid in server_pids()}
        self._them = {pid: cpu_seconds(pid) for pid in browser_pids()}

    def stop(self) -> dict[str, float]:
        wall = time.monotonic() - self._t0
        # A process started since counts from 0; one that ended meanwhile is missed (none should).
        used = lambda before, now: sum(t - before.get(p, 0.0) for p, t in now.items() if np.isfinite(t))  # noqa: E731
        server = used(self._server, {pid: cpu_seconds(pid) for pid in server_pids()})
        browsers = used(self._them, {pid: cpu_seconds(pid) for pid in browser_pids()})
        return {"server": server / wall, "browsers": browsers / wall}


def autogroup(pid: int | str) -> tuple[str, int] | None:
    """(name, nice) of a process's scheduler autogroup, or None where the kernel has none."""
    try:
        name, nice = Path(f"/proc/{pid}/autogroup").read_text().split()[:3:2]
        return name, int(nice)
    except (OSError, ValueError):
        return None


class BrowserNice:
    """Keeps every thread of the browsers this process started at nice >= ``nice``.

    Chromium sets its renderers' priority itself (as root, to nice -8 for visible pages), which
    would put the load generators above the server they are measuring. And Playwright starts each
    browser in a session of its own: where the kernel groups sessions for scheduling
    (``sched_autogroup_enabled``, the default on desktop kernels), a thread's nice only counts
    inside its group and the groups share the CPUs equally, so 4 browsers held the server to a
    fifth of the machine whatever their threads' nice. Each browser's group gets the nice too.

    ``idle``: the threads also go to the idle scheduling class (``SCHED_IDLE``, Linux), where any
    other thread that wakes takes the core at once; at nice 19 alone a woken thread may wait out the
    browser's slice. For the one page beside the protocol clients, a user's browser on another
    machine: at nice 19 it took 0.34-0.44 of the 2 cores (8 clients), idle 0.22 (docs/load.md).
    """

    def __init__(self, nice: int, period: float = 0.5, idle: bool = False) -> None:
        self._nice, self._period = nice, period
        self._idle = idle and hasattr(os, "SCHED_IDLE")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="browser-nice", daemon=True)
        if hasattr(os, "setpriority") and Path("/proc/self/task").is_dir():
            self._thread.start()

    def _run(self) -> None:
        mine = autogroup("self")
        while not self._stop.wait(self._period):
            for pid in set(browser_pids()) - SPARED:  # not the server's decode processes
                group = autogroup(pid)
                if group is not None and group[0] != (mine and mine[0]) and group[1] < self._nice:
                    try:
                        Path(f"/proc/{pid}/autogroup").write_text(str(self._nice))
                    except OSError:
                        pass
                try:
                    tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
                except OSError:
                    continue
                for tid in tids:
                    try:
                        if os.getpriority(os.PRIO_PROCESS, tid) < self._nice:
                            os.setpriority(os.PRIO_PROCESS, tid, self._nice)
                        if self._idle and os.sched_getscheduler(tid) != os.SCHED_IDLE:
                            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
                    except OSError:
                        continue

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)


class RssSampler:
    """The server's RSS every ``period`` s: ``samples`` rows (seconds, MB in all, this process's MB,
    the decode processes' MB)."""

    def __init__(self, period: float = 0.5) -> None:
        self.samples: list[tuple[float, float, float, float]] = []
        self._stop = threading.Event()
        self._period = period
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            this, decode = rss_split_mb()
            self.samples.append((time.monotonic() - self._t0, this + decode, this, decode))
            self._stop.wait(self._period)

    def window(self, start: float, end: float) -> np.ndarray:
        a = np.asarray(self.samples)
        return a[(a[:, 0] >= start - self._t0) & (a[:, 0] <= end - self._t0)]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def slope_mb_per_min(samples: np.ndarray, column: int = 1) -> float:
    """Least-squares slope of (seconds, MB, ...) samples' MB ``column``, in MB per minute (NaN for
    fewer than 3)."""
    if len(samples) < 3:
        return float("nan")
    return float(np.polyfit(samples[:, 0], samples[:, column], 1)[0] * 60.0)
