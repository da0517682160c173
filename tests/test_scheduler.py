"""The server's shared physics pool: fair turns between tabs, strict order between kinds of work,
superseded work dropped unrun, results unchanged."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from snakeloco.sim.physics.scheduler import SEGMENT_SAMPLES, FairPhysics, OnTurns, Turn
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT


def _blocked_pool() -> tuple[FairPhysics, threading.Event]:
    """A one-thread pool whose thread is held until the returned event is set."""
    pool, gate, started = FairPhysics(1), threading.Event(), threading.Event()
    pool.submit("gate", Turn.FIRST_MOTION, lambda: (started.set(), gate.wait(10)))
    assert started.wait(10)
    return pool, gate


def test_replays_go_before_any_ensemble_and_tabs_take_turns_within_a_kind():
    pool, gate = _blocked_pool()
    ran: list[str] = []
    try:
        futures = [
            pool.submit(tab, turn, lambda name=name: ran.append(name))
            for tab, turn, name in [
                ("a", Turn.FIT, "a-fit"),
                ("a", Turn.ENSEMBLE, "a-ens-1"),
                ("a", Turn.ENSEMBLE, "a-ens-2"),
                ("a", Turn.ENSEMBLE, "a-ens-3"),
                ("b", Turn.ENSEMBLE, "b-ens-1"),
                ("c", Turn.DESIGN, "c-design"),
                ("c", Turn.CLOSED_LOOP, "c-closed-loop"),
                ("b", Turn.VARIATIONS, "b-variations"),
                ("b", Turn.DRAGGED, "b-dragged"),
                ("c", Turn.SETTLED, "c-settled"),
                ("a", Turn.FIRST_MOTION, "a-first"),
            ]
        ]
        assert pool.pending() == {
            Turn.FIRST_MOTION: 1,
            Turn.SETTLED: 1,
            Turn.DRAGGED: 1,
            Turn.ENSEMBLE: 4,
            Turn.VARIATIONS: 1,
            Turn.CLOSED_LOOP: 1,
            Turn.DESIGN: 1,
            Turn.FIT: 1,
        }
        gate.set()
        for f in futures:
            f.result(10)
    finally:
        pool.close()
    # strictly by kind; inside the ensembles tab b's one row comes between tab a's, not after them
    assert ran == [
        "a-first",
        "c-settled",
        "b-dragged",
        "a-ens-1",
        "b-ens-1",
        "a-ens-2",
        "a-ens-3",
        "b-variations",
        "c-closed-loop",
        "c-design",
        "a-fit",
    ]


def test_a_first_motion_of_a_value_not_yet_held_waits_for_settled_replays_and_its_thread_time_is_counted():
    """A first motion whose slider value is younger than its hold (the slider may be passing
    through it) goes after every tab's settled and dragged chunks, but before any ensemble; once held
    it is first again. The pool counts each class's thread time."""
    pool, gate = _blocked_pool()
    ran: list[str] = []
    later = time.perf_counter() + 3600.0  # not held while this test runs
    try:
        futures = [
            pool.submit("a", Turn.ENSEMBLE, lambda: ran.append("a-ens")),
            pool.submit("b", Turn.FIRST_MOTION, lambda: ran.append("b-young"), held_at=later),
            pool.submit("c", Turn.DRAGGED, lambda: ran.append("c-dragged")),
            pool.submit("d", Turn.SETTLED, lambda: ran.append("d-settled")),
            pool.submit("e", Turn.FIRST_MOTION, lambda: ran.append("e-held"), held_at=time.perf_counter()),
        ]
        gate.set()
        for f in futures:
            f.result(10)
        first_round, ran[:] = list(ran), []
        gate.clear()
        started = threading.Event()
        pool.submit("gate", Turn.FIRST_MOTION, lambda: (started.set(), gate.wait(10)))
        assert started.wait(10)
        futures = [
            pool.submit("d", Turn.SETTLED, lambda: ran.append("d-settled")),
            pool.submit(
                "b", Turn.FIRST_MOTION, lambda: ran.append("b-held"), held_at=time.perf_counter() + 0.05
            ),
            pool.submit("f", Turn.DESIGN, lambda: time.sleep(0.05)),  # work of a known length
        ]
        time.sleep(0.06)  # held by the time a thread is free
        gate.set()
        for f in futures:
            f.result(10)
        busy = dict(pool.busy_s)
    finally:
        pool.close()
    assert first_round == ["e-held", "d-settled", "c-dragged", "b-young", "a-ens"]
    assert ran == ["b-held", "d-settled"]
    assert 0.05 <= busy[Turn.DESIGN] < 1.0  # each class's thread time, counted where it ran
    assert 0.0 < busy[Turn.ENSEMBLE] < 0.05 and busy[Turn.SETTLED] < 0.05


def test_a_first_motion_thread_runs_held_first_motions_alone_and_at_its_own_priority():
    """With the pool's thread busy, a first motion that becomes held runs at once on the
    first-motion thread (no new submission wakes it: a hold is a time); that thread takes neither a
    value not yet held nor any other work, and runs at its own nice, between the pool's and the
    caller's."""
    pool = FairPhysics(1, nice=10, first_threads=1, first_nice=5)
    gate, started = threading.Event(), threading.Event()
    where: dict[str, tuple[str, int]] = {}

    def note(name: str) -> None:
        where[name] = (
            threading.current_thread().name,
            os.getpriority(os.PRIO_PROCESS, threading.get_native_id()),
        )

    try:
        blocker = pool.submit("a", Turn.SETTLED, lambda: (note("a-settled"), started.set(), gate.wait(10)))
        assert started.wait(10)
        held_at = time.perf_counter() + 0.3
        young = pool.submit("b", Turn.FIRST_MOTION, lambda: note("b-first"), held_at=held_at)
        settled = pool.submit("c", Turn.SETTLED, lambda: note("c-settled"))
        time.sleep(0.1)
        assert not young.done() and not settled.done()  # the first-motion thread left both alone
        young.result(10)  # ran once held, while the pool's thread was still held
        assert time.perf_counter() >= held_at
        assert not settled.done() and not blocker.done()
        gate.set()
        settled.result(10)
    finally:
        gate.set()
        pool.close()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    assert where["b-first"] == ("physics-first-0", min(base + 5, 19))
    assert where["a-settled"][0] == where["c-settled"][0] == "physics-0"
    assert where["c-settled"][1] == min(base + 10, 19)


def test_while_first_motions_run_the_pools_threads_start_no_new_task():
    """At most ``threads`` tasks run at once: a first motion on its own thread takes a core from the
    replays (an idle pool thread waits for it) rather than sharing one with them."""
    pool = FairPhysics(1, first_threads=1)
    gate, started = threading.Event(), threading.Event()
    try:
        first = pool.submit("a", Turn.FIRST_MOTION, lambda: (started.set(), gate.wait(10)))
        assert started.wait(10)
        settled = pool.submit("b", Turn.SETTLED, lambda: None)
        time.sleep(0.1)
        assert not settled.done()  # the pool's thread is idle, but the one slot is the first motion's
        gate.set()
        first.result(10)
        settled.result(10)
    finally:
        gate.set()
        pool.close()


def test_unwanted_and_cancelled_work_never_runs_and_errors_reach_the_caller():
    pool, gate = _blocked_pool()
    ran: list[str] = []
    wanted = {"old": True}
    try:
        old = pool.submit("a", Turn.SETTLED, lambda: ran.append("old"), lambda: wanted["old"])
        withdrawn = pool.submit("b", Turn.SETTLED, lambda: ran.append("withdrawn"))
        new = pool.submit("a", Turn.FIRST_MOTION, lambda: ran.append("new"))
        broken = pool.submit("c", Turn.ENSEMBLE, lambda: 1 / 0)
        wanted["old"] = False  # the tab moved on while the chunk waited
        assert withdrawn.cancel()
        gate.set()
        new.result(10)
        with pytest.raises(ZeroDivisionError):
            broken.result(10)
        assert old.cancelled() and withdrawn.cancelled()
    finally:
        pool.close()
    assert ran == ["new"] and pool.dropped == 1


def test_closing_cancels_queued_work_and_refuses_more():
    pool, gate = _blocked_pool()
    queued = pool.submit("a", Turn.ENSEMBLE, lambda: None)
    gate.set()
    pool.close()
    assert queued.cancelled() or queued.done()
    with pytest.raises(RuntimeError, match="closed"):
        pool.submit("a", Turn.ENSEMBLE, lambda: None)


@pytest.mark.slow
def test_replays_and_batches_on_the_pool_are_bit_identical_to_the_simulators_own():
    from snakeloco.sim.gaits.library import PRESETS

    commands = np.stack([PRESETS[name].gait.commands(DEFAULT_ROBOT) for name in list(PRESETS)[:3]])
    sim = Simulator(workers=2)
    pool = FairPhysics(2)
    try:
        own = sim.simulate(commands)
        pooled = OnTurns(sim, pool.runner("tab", Turn.ENSEMBLE)).simulate(commands)
        np.testing.assert_array_equal(pooled.body, own.body)
        np.testing.assert_array_equal(pooled.joint_angles, own.joint_angles)
        parts = list(sim.stream(commands[0], runner=lambda k: pool.runner("tab", Turn(min(k, 1)))))
        np.testing.assert_array_equal(parts[-1].joint_angles, own.joint_angles[0])
        assert pool.served[Turn.FIRST_MOTION] == 1 and pool.served[Turn.SETTLED] == len(parts) - 1
        # batches run in segments of SEGMENT_SAMPLES per task, the same numbers as one rollout
        per_row = -(-sim.excitation.n_samples // SEGMENT_SAMPLES)
        assert per_row > 1 and pool.served[Turn.ENSEMBLE] == len(commands) * per_row
        # a batch whose rows are no longer wanted is dropped: None, as a superseded batch; a stream
        # whose chunk is dropped when its turn comes ends there (no error)
        assert OnTurns(sim, pool.runner("tab", Turn.ENSEMBLE, lambda: False)).simulate(commands) is None
        assert list(sim.stream(commands[0], runner=pool.runner("tab", Turn.SETTLED, lambda: False))) == []
    finally:
        pool.close()
        sim.close()


@pytest.mark.slow
def test_tabs_decode_in_turns_each_its_newest_value(checkpoint):
    """The decode stage holds ``IN_FLIGHT`` requests a process (the child decodes one while the next
    waits in its socket); beyond that the tabs wait their turns, and a tab that waited decodes only
    the value it ended on."""
    from contextlib import ExitStack

    from snakeloco.app.bench.users.load_driver import wait_until
    from snakeloco.app.server.decode_process import IN_FLIGHT

    from helpers import connect_headless, quiet_server

    srv = quiet_server(checkpoint)
    try:
        tabs = [connect_headless(srv) for _ in range(2)]
        assert all(d.decoding is srv.decoding for _, d in tabs)
        inside, most, decoded = [0], [0], []
        count, real = threading.Lock(), srv.decoding.decode

        def slow(path, latents, fallback):  # the server's decode stage, however it decodes
            with count:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
            time.sleep(0.05)  # long enough for the other tab's decode to overlap, if it could
            with count:
                inside[0] -= 1
            decoded.append(latents.z_b[0])
            return real(path, latents, fallback)

        srv.decoding.decode = slow
        slots = IN_FLIGHT * len(srv.decoding.processes)
        with ExitStack() as held:  # every tab's decode waits for its turn while its slider moves on
            for _ in range(slots):
                held.enter_context(srv.decoding.turns)
            for v in (0.5, 1.0, 1.5):
                for sign, (_, d) in zip((1, -1), tabs, strict=True):
                    before = d.version
                    d.sliders[0].value = sign * v
                    assert wait_until(lambda d=d, before=before: d.version > before, 30)
                if v == 0.5:  # both tabs' decodes of it wait behind the test's turns
                    assert wait_until(lambda: srv.decoding.turns.queued() == slots + 2, 30)
        assert all(d.wait_idle(60) for _, d in tabs)
        # As many decodes at once as the stage holds (here both tabs'), and each tab decoded only the
        # value it ended on: the values it moved through while waiting were dropped, not decoded late.
        assert slots == 2 and most[0] == 2
        assert sorted(decoded) == [-1.5, 1.5]  # the first tab's values are > 0, the second's < 0
        assert [d.decoded.latents.z_b[0] for _, d in tabs] == [1.5, -1.5]
    finally:
        for c, _ in tabs:
            c.close()
        srv.stop()
