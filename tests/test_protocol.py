"""`bench load`'s protocol clients against a served designer: they join as a page does, drag, read the
decoded view and the replay off the wire, and report a stale stream; a client that stops reading
does not hold up the others."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from snakeloco.app.bench.users.load_browser import wait_until
from snakeloco.app.bench.users.load_protocol import server_problems
from snakeloco.app.bench.users.protocol import DONE_STATES, ProtocolClient, stream_problems
from snakeloco.app.bench.users.wire import parse_readout
from snakeloco.app.designer.readout import Readout, readout_html

from helpers import apply, connect_headless, quiet_server


def _settled(c: ProtocolClient) -> bool:
    values, state = c.readout
    return state in DONE_STATES and values is not None and np.allclose(values, c.values, atol=5e-5)


def test_the_readout_says_which_sliders_and_state_it_is_for():
    colors = dict.fromkeys(("model", "mujoco", "ensemble", "ring"), (0, 0, 0))
    html = readout_html(Readout(None, None, "streaming", sliders=(0.25, -1.5)), colors)
    assert parse_readout(html) == ((0.25, -1.5), "streaming")
    assert parse_readout(readout_html(Readout(None, None, "done"), colors)) == (None, "done")  # a file's gait


def test_a_protocol_client_joins_drags_and_reads_the_decoded_view_and_replay(checkpoint):
    srv = quiet_server(checkpoint)

    async def run() -> dict:
        c = ProtocolClient(f"http://127.0.0.1:{srv.port}", seed=1)
        await c.join()
        for _ in range(2):
            await c.drag(dwell=0.2)
        assert await c.wait_for(lambda: _settled(c), 120), c.readout
        return c.summary()

    try:
        s = asyncio.run(run())
        d = next(iter(srv.clients.values()))
        # The page's preparations reached the server: playback paused, light rendering on.
        assert d.controls.light.value is True and not d.playback.playing
        assert [float(v.value) for v in d.sliders] == pytest.approx(s["final_values"])
        assert s["drags"] == 2 and len(s["decoded_ms"]) >= 1 and len(s["replay_ms"]) >= 1
        assert all(0 < ms < 120e3 for ms in s["decoded_ms"] + s["replay_ms"])
        # The decoded view is timed from the first send of the drag's final value, so it is caught
        # before the first motion (not taken from a later readout when it came before the last sends).
        timed = [(d, f) for d, f, _ in s["stages_ms"] if np.isfinite(d) and np.isfinite(f)]
        assert timed and all(d <= f for d, f in timed) and any(d < f for d, f in timed), timed
        assert s["bytes"] > 0 and s["frames"] > 0
        assert stream_problems(s) == []
        assert server_problems(d, s) == []
        # A stream whose last readout belongs to other sliders is stale, and so is a generated path
        # that is not the decode of the final sliders.
        moved = s | {"final_values": [v + 0.5 for v in s["final_values"]]}
        assert "the last readout is for sliders" in stream_problems(moved)[0]
        bad_path = s | {"generated": (np.asarray(s["generated"]) + 0.1).tolist()}
        assert "not the decode of its final sliders" in server_problems(d, bad_path)[0]
        unfinished = s | {"readout_state": "streaming"}
        assert "not done or failed" in stream_problems(unfinished)[0]
    finally:
        srv.stop()


def test_each_view_is_sent_once_drawn_not_at_the_end_of_a_window(checkpoint):
    """viser holds a client's messages up to 1/60 s for more to come unless flushed: the decoded
    view, the replay's first motion and the finished replay each flush once drawn."""
    srv = quiet_server(checkpoint)
    client, d = connect_headless(srv)
    try:
        flushed, flush = [], d.client.flush
        d.client.flush = lambda: flushed.append(d.readout.state) or flush()
        assert apply(d, d.sliders[0], 1.0, 60)
        # In order (the ensemble's draw flushes too: repeats are one).
        assert [s for i, s in enumerate(flushed) if i == 0 or s != flushed[i - 1]] == [
            "simulating",
            "streaming",
            "done",
        ], flushed
    finally:
        client.close()
        srv.stop()


@pytest.mark.slow
def test_a_client_that_stops_reading_does_not_stall_the_others_and_is_closed(checkpoint):
    """The server's send to a client that stops reading waits on that client's socket alone; its
    pings go unanswered and the websocket library closes it (websockets' 20 s ping interval and
    20 s timeout)."""
    srv = quiet_server(checkpoint)

    async def run() -> tuple[ProtocolClient, float]:
        stuck, live = (ProtocolClient(f"http://127.0.0.1:{srv.port}", seed=s) for s in (1, 2))
        await asyncio.gather(stuck.join(), live.join())
        stuck.reading = False
        for _ in range(4):  # the stuck tab is sent its own drags' views too: its buffers fill
            await asyncio.gather(stuck.drag(dwell=0.0), live.drag(dwell=0.5))
        assert await live.wait_for(lambda: _settled(live), 120), live.readout
        t0 = time.monotonic()
        closed = await asyncio.to_thread(wait_until, lambda: len(srv.clients) == 1, 90)
        assert closed, "the server kept a client that reads nothing for 90 s"
        return live, time.monotonic() - t0

    try:
        live, _ = asyncio.run(run())
        s = live.summary()
        assert len(s["decoded_ms"]) == 4 and len(s["replay_ms"]) >= 1
        assert max(s["decoded_ms"]) < 30e3  # served at its own pace, not the stuck client's
        assert stream_problems(s) == []
    finally:
        srv.stop()


@pytest.mark.slow
def test_a_tab_whose_page_has_left_draws_nothing_more(checkpoint):
    """Between a page's connection closing and viser's disconnect callback closing its tab, the
    tab's threads (the animation, a replay's chunks) may still draw: they see the connection closed
    and stop, where each draw would be dropped and viser would warn of it."""
    import warnings

    from snakeloco.app.server.viser_patches import connection_closed

    srv = quiet_server(checkpoint)
    try:
        c, d = connect_headless(srv)
        assert d.simulated is not None
        close, d.close = d.close, lambda: None  # the server's disconnect callback: held back
        version = d.version
        assert d.is_current(version) and not connection_closed(d.client)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            c.close()
            assert wait_until(lambda: connection_closed(d.client), 30)
            assert not d.is_current(version)  # a replay's chunk or ensemble draws nothing more
            for frame in (7, 11):  # the animation's draws, at poses the snake is not in
                d.draw_snake(frame)
            time.sleep(0.3)  # the animation thread's own frames meanwhile
        assert [str(w.message) for w in caught] == []
        close()
    finally:
        srv.stop()


def test_bunched_arrivals_tell_clients_in_step_from_independent_ones():
    from types import SimpleNamespace as NS

    from snakeloco.app.bench.users.load_protocol import bunched_arrivals

    def tabs(offsets_s):  # each tab sends every 50 ms for 10 s from its own offset
        return [NS(timings=[NS(submitted=o + 0.05 * k) for k in range(200)]) for o in offsets_s]

    in_step, independent = bunched_arrivals(tabs([0.0, 0.0001, 0.0002, 0.0003]))
    assert in_step == pytest.approx(0.75, abs=0.01)  # 3 of each 4 values within 1 ms of the one before
    assert independent == pytest.approx(1 - np.exp(-80 * 1e-3), rel=0.01)  # 80 values a second
    out_of_step, _ = bunched_arrivals(tabs([0.0, 0.0125, 0.025, 0.0375]))
    assert out_of_step == 0.0
    assert np.isnan(bunched_arrivals([])[0])


def test_clients_of_one_gaits_seed_drag_through_the_same_gaits_at_times_of_their_own(monkeypatch):
    """``bench load`` compares the same work alone and among others: every client drags the same
    sliders to the same values in the same steps, but starts and rests when its own seed says."""
    import asyncio

    slept: dict[int, list[float]] = {}

    def client(seed: int) -> ProtocolClient:
        c = ProtocolClient("http://127.0.0.1:1", seed=seed, gaits_seed=42)
        c.gui = {
            f"u{i}": {
                "type": "GuiSliderMessage",
                "props": {"label": f"z_B {i}", "min": -3.0, "max": 3.0, "step": 0.01},
            }
            for i in (1, 2, 3)
        }
        c.values = [0.0, 0.0, 0.0]
        c.sent = []

        async def send(uuid, value):
            c.sent.append((uuid, value))

        c.send = send
        return c

    clock = [0.0]

    async def sleep(s):
        slept[id(asyncio.current_task())].append(s)
        clock[0] += s

    async def run(c: ProtocolClient) -> None:
        slept[id(asyncio.current_task())] = c.slept = []
        for _ in range(5):
            await c.drag(3.0)

    monkeypatch.setattr("snakeloco.app.bench.users.protocol.asyncio.sleep", sleep)
    monkeypatch.setattr("snakeloco.app.bench.users.protocol.time.perf_counter", lambda: clock[0])
    a, b = client(1), client(2)
    for c in (a, b):
        asyncio.run(run(c))
    assert a.sent == b.sent and len(a.sent) > 5 * 10  # the same sliders, values and steps
    assert [d.values for d in a.drags] == [d.values for d in b.drags]
    rests = lambda c: [s for s in c.slept if abs(s - 0.05) > 1e-9]  # noqa: E731 (the sends are alike)
    assert len(rests(a)) == 5 and rests(a) != rests(b)


def test_a_drag_keeps_to_its_own_50_ms_grid_after_a_stall(monkeypatch):
    """The clients share one event loop: a stall delays whatever sends fall in it, but each drag's
    later sends come back to its own grid rather than staying in step with the other delayed ones."""
    import asyncio

    clock = [100.0]
    sent: list[float] = []
    c = ProtocolClient("http://127.0.0.1:1", seed=0)
    c.gui = {
        "u1": {"type": "GuiSliderMessage", "props": {"label": "z_B 1", "min": -3.0, "max": 3.0, "step": 0.01}}
    }
    c.values = [0.0]

    async def send(uuid, value):
        sent.append(clock[0])
        if len(sent) == 3:
            clock[0] += 0.03  # the loop stalls 30 ms after the third send

    async def sleep(s):
        clock[0] += s

    c.send = send
    monkeypatch.setattr("snakeloco.app.bench.users.protocol.asyncio.sleep", sleep)
    monkeypatch.setattr("snakeloco.app.bench.users.protocol.time.perf_counter", lambda: clock[0])
    asyncio.run(c.drag(0.0))
    grid = 100.0 + 0.05 * np.arange(len(sent))
    assert len(sent) >= 11 and np.allclose(sent, grid, atol=1e-9)  # the stall ends before the fourth is due
    assert max(c.send_late_s) < 1e-9

    clock[0], sent[:] = 100.0, []
    c.send_late_s = []

    async def slow_send(uuid, value):
        sent.append(clock[0])
        if len(sent) == 3:
            clock[0] += 0.07  # past the fourth send's time: that one goes out late ...

    c.send = slow_send
    asyncio.run(c.drag(0.0))
    assert sent[3] == pytest.approx(100.17) and c.send_late_s[2] == pytest.approx(0.02)
    assert np.allclose(sent[4:], 100.0 + 0.05 * np.arange(4, len(sent)), atol=1e-9)  # ... the rest on time
