"""The designer's parts that need no server: the gait CSV and its catalogue of bad files, the latest-
request worker, the panel's text, the metre grid, freed buffers going back to the OS."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from snakeloco.app.designer.panel import spread_text
from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv, write_gait_csv
from snakeloco.app.server.workers import LatestWorker
from snakeloco.sim.robot.description import DEFAULT_ROBOT


def bad_gait_files() -> dict[str, tuple[bytes, str]]:
    """Every bad gait file of the robustness catalogue: name -> (bytes, part of the message)."""
    rng = np.random.default_rng(0)
    text = write_gait_csv(rng.uniform(-2.2, 2.2, (2000, 8)), {"z_B": "[0.1]"}, DEFAULT_ROBOT)
    header = "time_s," + ",".join(f"joint_{k}" for k in range(1, 9))
    cell = text.splitlines()[5].split(",")[3]
    return {
        "empty": (b"", "empty"),
        "header only": ((header + "\n").encode(), "header only"),
        "wrong column": (text.replace("joint_8", "joint_9").encode(), "unexpected ['joint_9']"),
        "missing column": (
            "\n".join(
                ",".join(line.split(",")[:-1]) for line in text.splitlines() if not line.startswith("#")
            ).encode(),
            "missing ['joint_8']",
        ),
        "non-numeric": (text.replace(cell, "abc", 1).encode(), "column joint_3: 'abc' is not a number"),
        "NaN": (text.replace(cell, "nan", 1).encode(), "column joint_3: nan is not a finite number"),
        "Inf": (text.replace(cell, "inf", 1).encode(), "column joint_3: inf is not a finite number"),
        "short row": (text.replace("," + cell, "", 1).encode(), "expected 9 values, got 8"),
        "out of range": (text.replace(cell, "2.5", 1).encode(), "outside the +/-2.2 rad"),
        "wrong time step": (text.replace("\n0.05,", "\n0.07,", 1).encode(), "step by 0.05"),
        "wrong row count": ("\n".join(text.splitlines()[:-1]).encode(), "expected 2000 data rows"),
        "binary": (bytes(range(256)) * 4, "binary"),
        "non-UTF-8": ("time_s,caf\u00e9\n".encode("latin-1"), "not UTF-8"),
        "semicolons": (text.replace(",", ";").encode(), "separated by commas"),
        "oversized": (b"0" * (3 * 2**20), "at most 2 MiB"),
    }


def test_gait_csv_refuses_every_bad_file_of_the_catalogue():
    for name, (data, message) in bad_gait_files().items():
        with pytest.raises(GaitCSVError, match=re.escape(message)):
            read_gait_csv(data, robot=DEFAULT_ROBOT)
        assert name


def test_latest_worker_runs_only_the_newest_request():
    gate, started = threading.Event(), threading.Event()
    ran = []

    def job(version, request, is_current):
        if request == 0:
            started.set()
            gate.wait(10)
        ran.append((request, is_current()))

    worker = LatestWorker(job)
    worker.submit(0)
    assert started.wait(10)  # request 0 is running: the next ones queue behind it
    for r in range(1, 20):
        worker.submit(r)
    gate.set()
    assert worker.wait_idle(10)
    worker.close()
    assert ran == [(0, False), (19, True)]


def test_latest_worker_reports_failures_but_not_those_of_a_job_closed_under_it():
    errors: list[BaseException] = []
    started = threading.Event()

    def job(version, request, is_current):
        if request == "slow":  # a replay still running when its tab goes away
            started.set()
            time.sleep(0.3)
        raise RuntimeError(f"{request} failed")

    worker = LatestWorker(job, on_error=errors.append)
    worker.submit("open")
    assert worker.wait_idle(10) and [str(e) for e in errors] == ["open failed"]
    worker.submit("slow")
    assert started.wait(10)
    worker.close()  # closes while the job runs; the job then fails
    assert [str(e) for e in errors] == ["open failed"]


def test_gait_csv_round_trip():
    rng = np.random.default_rng(0)
    u = rng.uniform(-2.2, 2.2, (2000, 8))
    text = write_gait_csv(u, {"z_B": "[0.1]"}, DEFAULT_ROBOT)
    np.testing.assert_array_equal(read_gait_csv(text.encode(), robot=DEFAULT_ROBOT).commands, u)
    np.testing.assert_array_equal(
        read_gait_csv(text.replace("\n", "\r\n").encode(), robot=DEFAULT_ROBOT).commands, u
    )


_FREED_MEMORY = """
import sys
import numpy as np, psutil
from snakeloco.app.server.lifecycle import return_freed_buffers_to_the_os
if sys.argv[1] == "on":
    assert return_freed_buffers_to_the_os()
rss = lambda: psutil.Process().memory_info().rss / 2**20
big = np.ones((16 << 20) // 8); del big  # one large free: glibc raises its mmap threshold to 16 MB
before = rss()
replays, kept = [], []
for _ in range(30):  # replay-sized arrays with a long-lived array after each (a tab's state)
    replays.append(np.ones((8 << 20) // 8))
    kept.append(np.ones(20_000))
del replays
print(round(rss() - before))
"""


def _off_and_on(script: str, setting: str) -> dict[str, str] | None:
    """What ``script`` prints in fresh processes without ("off") and with ("on") the glibc setting
    ``app.server.<setting>``; None off glibc, where the setting says it did not take."""
    import platform
    import subprocess
    import sys

    if not (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"):
        from snakeloco.app.server import lifecycle as server

        assert getattr(server, setting)() is False
        return None
    printed = {}
    for mode in ("off", "on"):
        out = subprocess.run(
            [sys.executable, "-c", script, mode], capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 0, out.stderr
        printed[mode] = out.stdout.strip()
    return printed


def test_large_freed_buffers_go_back_to_the_os_on_glibc():
    """30 freed 8 MB arrays with live ones between them: by default glibc keeps the 240 MB of heap
    pages (measured 244 MB); with the setting each was its own mapping and went back (4 MB)."""
    pytest.importorskip("psutil")
    printed = _off_and_on(_FREED_MEMORY, "return_freed_buffers_to_the_os")
    if printed is not None:
        kept = {mode: float(mb) for mode, mb in printed.items()}
        assert kept["off"] > 150 and kept["on"] < 40, kept


_ARENAS = """
import ctypes, re, sys, threading
from snakeloco.app.server.lifecycle import limit_malloc_arenas
if sys.argv[1] == "on":
    assert limit_malloc_arenas(2)
libc = ctypes.CDLL("libc.so.6")
go, done = threading.Barrier(9), threading.Barrier(9)
def work():
    go.wait()
    kept = [ctypes.create_string_buffer(4096) for _ in range(64)]  # malloc'd on this thread
    done.wait()
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads:
    t.start()
go.wait()
done.wait()
for t in threads:
    t.join()
libc.open_memstream.restype = ctypes.c_void_p
libc.open_memstream.argtypes = [ctypes.POINTER(ctypes.c_char_p), ctypes.POINTER(ctypes.c_size_t)]
libc.malloc_info.argtypes, libc.fclose.argtypes = [ctypes.c_int, ctypes.c_void_p], [ctypes.c_void_p]
buf, size = ctypes.c_char_p(), ctypes.c_size_t()
f = libc.open_memstream(ctypes.byref(buf), ctypes.byref(size))
libc.malloc_info(0, f)
libc.fclose(f)
print(len(re.findall(r'<heap nr=', ctypes.string_at(buf, size.value).decode())))
"""


def test_malloc_arenas_are_limited_on_glibc():
    """Eight threads allocating at once: glibc gives each an arena of its own (9 with the main
    thread's; up to 8 a core), each keeping freed pages; limited, they share 2."""
    printed = _off_and_on(_ARENAS, "limit_malloc_arenas")
    if printed is not None:
        heaps = {mode: int(n) for mode, n in printed.items()}
        assert heaps["on"] == 2 and heaps["off"] > 2, heaps


def test_panel_spread_is_relative_only_where_the_mean_is_a_scale():
    assert spread_text(1.0, 0.023) == "±1 (2.3%)"
    assert spread_text(0.0091, 0.273) == "±0.0091 (27.3%)"
    # A net roll going both ways: std above the mean's size, so no percentage.
    assert spread_text(15.0, 7.894) == "±15"
    assert spread_text(2.0, 1.0) == "±2"


def test_the_metre_grid_is_thin_quads_on_the_ground_one_per_line():
    from snakeloco.app.designer.view import (
        GRID_HALF_M,
        GRID_LIFT_M,
        RINGS_M,
        grid_lines,
        ground_quads,
        ring_strips,
    )

    lines = grid_lines(1, skip=5)
    assert len(lines) == 2 * (2 * GRID_HALF_M + 1 - (2 * GRID_HALF_M // 5 + 1))  # 5 m lines left out
    vertices, faces = ground_quads(lines, 0.02)
    assert vertices.shape == (4 * len(lines), 3) and faces.shape == (2 * len(lines), 3)
    assert np.all(vertices[:, 2] == np.float32(GRID_LIFT_M))
    quad = vertices[:4, :2].astype(np.float64)  # the line x = -40: 2 cm wide, 80 m long
    assert np.ptp(quad[:, 0]) == pytest.approx(0.02, abs=1e-5) and np.ptp(quad[:, 1]) == pytest.approx(80.0)
    # Faces face up (counter-clockwise seen from above), so the default front side is drawn.
    a, b, c = (vertices[faces[:, i], :2].astype(np.float64) for i in range(3))
    cross = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    assert np.all(cross > 0)
    vertices, faces = ring_strips(0.1, n=64)  # inner and outer edges 0.1 m apart around each radius
    radii = np.linalg.norm(vertices[:, :2], axis=1).reshape(len(RINGS_M), 2, 65)
    assert np.allclose(radii.mean(axis=1), np.array(RINGS_M)[:, None], atol=1e-5)
    assert np.allclose(radii[:, 1] - radii[:, 0], 0.1, atol=1e-5)
    a, b, c = (vertices[faces[:, i], :2].astype(np.float64) for i in range(3))
    assert np.all((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0] > 0)  # facing up


def test_set_arrays_sends_one_update_and_nothing_once_the_connection_has_closed():
    from types import SimpleNamespace as NS

    from snakeloco.app.server.viser_patches import set_arrays

    buffer, sent = NS(done=False), []
    api = NS(_queue_scene_message=sent.append, _websock_interface=NS(get_message_buffer=lambda: buffer))
    props = NS(points=np.zeros((2, 3), np.float32), colors=np.zeros((2, 3), np.uint8))
    handle = NS(_impl=NS(api=api, props=props, name="/cloud", removed=False))
    set_arrays(handle, points=np.ones((2, 3)), colors=np.full((2, 3), 9))
    assert len(sent) == 1 and set(sent[0].updates) == {"points", "colors"}  # one message for both
    buffer.done = True  # the page left
    set_arrays(handle, points=np.full((2, 3), 2.0))
    assert len(sent) == 1 and props.points[0, 0] == 2.0  # kept, not sent


def test_framing_sends_a_camera_move_only_where_the_view_would_move():
    """A drag's next path frames within ``FRAME_STILL`` of the last: no camera message for it; a path
    that outgrows the view moves the camera; a user's own camera is left alone unless forced."""
    import contextlib
    from types import SimpleNamespace

    from snakeloco.app.designer.view import FRAME_STILL, Framer

    moves = []

    class Camera(SimpleNamespace):
        def __setattr__(self, name, value):
            if name in ("position", "look_at") and "fov" in self.__dict__:
                moves.append(name)
            super().__setattr__(name, np.asarray(value, np.float64))

    camera = Camera(position=(-2.5, -3.5, 2.5), look_at=(0.0, 0.0, 0.0))
    camera.__dict__.update(fov=np.radians(50), aspect=1.5, image_height=600, image_width=900)
    client = SimpleNamespace(camera=camera, atomic=contextlib.nullcontext)
    framer = Framer(client)
    path = np.stack([np.linspace(0, 10, 50), np.zeros(50), np.zeros(50)], -1)
    assert framer.frame(path) and moves == ["position", "look_at"]
    distance = float(np.linalg.norm(camera.position - camera.look_at))
    nudged = path * (1 + 0.5 * FRAME_STILL * distance / 10)  # the far end 0.5 % of the distance on
    assert not framer.frame(nudged) and len(moves) == 2
    assert framer.frame(path * 1.2) and len(moves) == 4  # 2 m further: the camera follows
    camera.position = camera.position + 1.0  # the user moved it
    assert not framer.frame(path) and framer.frame(path, force=True)


def test_a_started_server_leaves_its_objects_out_of_the_garbage_collection():
    """``freeze_started`` (called by ``serve`` once the server is built): a full collection then walks
    only what came since, not the ~265,000 objects of the checkpoints, torch and viser (in a process of
    its own: freezing is process-wide)."""
    import subprocess
    import sys

    code = (
        "import gc, time\n"
        "from snakeloco.app.server.lifecycle import freeze_started\n"
        "kept = [{'i': i} for i in range(50000)]\n"
        "freeze_started()\n"
        "new = [{'i': i} for i in range(100)]\n"
        "assert gc.get_freeze_count() >= 50000, gc.get_freeze_count()\n"
        "assert len(gc.get_objects()) < 20000, len(gc.get_objects())\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_a_tab_keeps_its_newest_timings_indexed_and_counts_every_value():
    """A tab's request timings are bounded, and so is their index by version (it kept up to 4000 a
    tab beside 2000 timings: 8 tabs of a 10-minute run still grew in its sixth minute)."""
    from collections import deque
    from types import SimpleNamespace

    from snakeloco.app.designer.tab import TIMINGS_KEPT, DesignerClient

    tab = SimpleNamespace(timings=deque(maxlen=TIMINGS_KEPT), timing_by_version={}, values_received=0)
    for version in range(1, 3 * TIMINGS_KEPT + 1):
        DesignerClient._record(tab, version)
    newest = list(range(2 * TIMINGS_KEPT + 1, 3 * TIMINGS_KEPT + 1))
    assert tab.values_received == 3 * TIMINGS_KEPT
    assert [t.version for t in tab.timings] == newest
    assert sorted(tab.timing_by_version) == newest
    assert all(tab.timing_by_version[t.version] is t for t in tab.timings)
    assert not hasattr(tab.timings[0], "__dict__")  # slots


def test_the_path_plots_draw_each_bucket_as_its_extremes_in_the_order_they_came():
    """Yaw's ~0.5 Hz wiggle at 5 Hz: every 2nd sample lost its peaks unevenly; the envelope keeps
    each cycle's highest and lowest sample in as many points, and a monotone path's samples exactly."""
    from snakeloco.app.designer.gui import PATH_PLOT_BUCKET, PATH_PLOT_TIMES, path_plot_values
    from snakeloco.sim import BODY_TIMES

    assert len(PATH_PLOT_TIMES) == 2 * len(BODY_TIMES) // PATH_PLOT_BUCKET and np.all(
        np.diff(PATH_PLOT_TIMES) > 0
    )
    yaw = 0.3 * np.sin(2 * np.pi * 0.52 * BODY_TIMES) + 0.01 * BODY_TIMES
    drawn = path_plot_values(yaw)
    assert drawn.dtype == np.float32 and drawn.shape == PATH_PLOT_TIMES.shape
    cycle = 1 / 0.52
    for k in range(int(BODY_TIMES[-1] / cycle)):
        at = (BODY_TIMES >= k * cycle) & (BODY_TIMES < (k + 1) * cycle)
        near = (PATH_PLOT_TIMES >= k * cycle - 0.6) & (PATH_PLOT_TIMES < (k + 1) * cycle + 0.6)
        assert drawn[near].max() >= np.float32(yaw[at].max()) and drawn[near].min() <= np.float32(
            yaw[at].min()
        )
    every_2nd = yaw[::2]  # what was drawn before, in the same bytes: some cycles' peaks lost
    lost = [
        yaw[at].max() - every_2nd[at[::2]].max()
        for k in range(50)
        if (at := (BODY_TIMES // cycle == k)).any()
    ]
    assert max(lost) > 0.03
    # Each bucket: its lowest and highest, the earlier first.
    b = yaw.reshape(-1, PATH_PLOT_BUCKET)
    pairs = drawn.reshape(-1, 2)
    np.testing.assert_array_equal(
        np.sort(pairs, axis=1), np.stack([b.min(1), b.max(1)], 1).astype(np.float32)
    )
    rising = b.argmin(1) < b.argmax(1)
    assert np.all((pairs[:, 0] < pairs[:, 1]) == rising)
    # A monotone path keeps its samples at the bucket's first and last time.
    forward = 0.1 * BODY_TIMES + 0.02 * np.sin(BODY_TIMES)
    np.testing.assert_array_equal(
        path_plot_values(forward), np.interp(PATH_PLOT_TIMES, BODY_TIMES, forward).astype(np.float32)
    )


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads a thread's wake-ups from Linux /proc")
def test_a_paused_animation_sleeps_until_played_and_closes_at_once():
    """A paused tab's animation thread does not wake 20 times a second to find itself paused; playing
    it again (the button, or ``playing`` set) wakes it; closing wakes a paused one too."""
    from types import SimpleNamespace

    from snakeloco.app.bench.users.load_driver import wait_until
    from snakeloco.app.designer.playback import FRAME_HZ, PAUSED_WAIT_S, Playback

    def runs(thread: threading.Thread) -> int:
        """How many times the thread has been put on a core (Linux schedstat): its wake-ups."""
        with open(f"/proc/self/task/{thread.native_id}/schedstat") as f:
            return int(f.read().split()[2])

    draws = []
    controls = SimpleNamespace(
        play_button=SimpleNamespace(label="Pause"),
        speed=SimpleNamespace(value=1.0),
        scrubber=SimpleNamespace(value=0.0),
    )
    closed = threading.Event()
    playback = Playback(controls, draws.append, lambda: True, closed, name="animate-test")
    try:
        assert wait_until(lambda: len(draws) >= 3, 5.0)  # playing: a pose every 1 / FRAME_HZ s
        playback.toggle()
        assert controls.play_button.label == "Play" and not playback.playing
        time.sleep(2 / FRAME_HZ)  # a frame that was waiting may still finish
        n_draws, n_runs = len(draws), runs(playback._thread)
        time.sleep(0.6)  # 12 frames' time, under PAUSED_WAIT_S: asleep, not waking to poll
        assert len(draws) == n_draws and runs(playback._thread) == n_runs
        playback.playing = True  # as a hidden tab shown again sets it
        assert wait_until(lambda: len(draws) > n_draws, 0.5 * PAUSED_WAIT_S)
        playback.toggle()
    finally:
        closed.set()
        t0 = time.perf_counter()
        playback.join()
        assert not playback._thread.is_alive() and time.perf_counter() - t0 < 0.5 * PAUSED_WAIT_S
