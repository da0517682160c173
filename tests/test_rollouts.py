"""Rollouts: batches, pauses, thread pools and their priorities, callers in line, streamed replays; each
the same numbers as one plain rollout."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import snakeloco.sim.physics.ground_contact as sim_physics  # where rollouts reach mujoco.rollout
from snakeloco.sim import CommandRule, SimulationError
from snakeloco.sim.physics.simulator import Simulator, replay
from snakeloco.sim.robot.description import DEFAULT_ROBOT


def test_large_batches_roll_out_in_chunks_with_the_same_results(tiny_dataset):
    # A rollout keeps every physics step (~16 MB a record): batches run max_batch at a time.
    commands = tiny_dataset.commands[:3].astype(np.float64)
    whole = Simulator(workers=2, max_batch=3).simulate(commands)
    chunked = Simulator(workers=2, max_batch=2).simulate(commands)
    assert Simulator(workers=3).max_batch == 6
    for name in ("joint_angles", "body", "qpos"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))
    assert chunked.failures == whole.failures == [None] * 3


def test_a_paused_batch_carries_on_to_the_numbers_of_one_uninterrupted_rollout(tiny_dataset):
    """The structured screen pauses its first replays at 20 s and carries on with the survivors only:
    the records it keeps must be exactly the ones a single rollout gives (state and warm start carried)."""
    commands = tiny_dataset.commands[:3].astype(np.float64)
    for workers in (1, 2):  # the calling thread's rollout and the thread pool's
        sim = Simulator(workers=workers, max_batch=2)  # two batches: the pause is per row
        whole = sim.simulate(commands)
        assert whole.paused is None
        early = sim.simulate(commands, samples=400)
        assert early.paused.samples == 400 and early.body.shape == (3, 400, 6)
        np.testing.assert_array_equal(early.body, whole.body[:, :400])
        middle = sim.simulate(commands[[0, 2]], samples=1000, resume=early.paused.rows([0, 2]))
        rest = sim.simulate(commands[[2]], resume=middle.paused.rows([1]))
        for name in ("joint_angles", "body", "qpos"):
            np.testing.assert_array_equal(getattr(middle, name), getattr(whole, name)[[0, 2], :1000])
            np.testing.assert_array_equal(getattr(rest, name), getattr(whole, name)[[2]], err_msg=name)
        assert rest.paused is None and rest.failures == [None]
        with pytest.raises(ValueError, match="samples must be 401"):
            sim.simulate(commands, samples=300, resume=early.paused)
        with pytest.raises(ValueError, match="resuming 3 paused"):
            sim.simulate(commands[:2], resume=early.paused)
        sim.close()


def test_replay_matches_generation_exactly(tiny_dataset):
    i = 2
    result = replay(tiny_dataset.commands[i])
    np.testing.assert_array_equal(result.joint_angles.astype(np.float32), tiny_dataset.joint_angles[i])
    np.testing.assert_array_equal(result.body.astype(np.float32), tiny_dataset.body[i])
    assert result.joint_angles.shape == (2000, 8) and result.body.shape == (2000, 6)
    np.testing.assert_allclose(result.times[:2], [0.0, 0.05])


def test_low_priority_pool_gives_the_same_physics_and_leaves_the_caller_alone(tiny_dataset):
    niced = Simulator(workers=1, nice=5)
    me = threading.get_native_id()
    before = os.getpriority(os.PRIO_PROCESS, me)
    try:
        if Path("/proc/self/task").is_dir():
            assert before + 5 in _thread_nices()  # the pool's native thread
        cpu, wall = time.thread_time(), time.perf_counter()
        first = niced.simulate(tiny_dataset.commands[:1].astype(np.float64))
        cpu, wall = time.thread_time() - cpu, time.perf_counter() - wall
        # The caller blocks while the niced thread works (mujoco's own pool made it spin at the
        # caller's priority, a whole core for the whole batch).
        assert cpu < 0.2 * wall, (cpu, wall)
        second = niced.simulate(tiny_dataset.commands[1:2].astype(np.float64))
        assert os.getpriority(os.PRIO_PROCESS, me) == before  # the caller's priority is untouched
        # Exactly the generator's physics, from a pool thread.
        np.testing.assert_array_equal(first.body[0].astype(np.float32), tiny_dataset.body[0])
        np.testing.assert_array_equal(second.body[0].astype(np.float32), tiny_dataset.body[1])
        np.testing.assert_array_equal(first.joint_angles[0].astype(np.float32), tiny_dataset.joint_angles[0])
    finally:
        niced.close()
    with pytest.raises(SimulationError, match="simulator was closed"):
        niced.simulate(tiny_dataset.commands[:1].astype(np.float64))


def test_callers_sharing_a_simulator_roll_out_in_the_order_they_came():
    from snakeloco.sim.physics.threads import FifoLock

    lock, order, threads = FifoLock(), [], []
    with lock:
        for i in range(5):
            t = threading.Thread(target=lambda i=i: lock.__enter__() or order.append(i) or lock.__exit__())
            t.start()
            deadline = time.monotonic() + 10
            while lock.queued() < i + 2 and time.monotonic() < deadline:  # thread i waits in line
                time.sleep(0.001)
            threads.append(t)
    for t in threads:
        t.join(10)
    assert order == [0, 1, 2, 3, 4]
    assert lock.queued() == 0


def test_a_lock_of_two_slots_has_two_holders_and_a_line_in_order():
    from snakeloco.app.bench.users.load_driver import wait_until
    from snakeloco.sim.physics.threads import FifoLock

    lock, order, inside, most = FifoLock(slots=2), [], [0], [0]
    count, leave = threading.Lock(), [threading.Event() for _ in range(5)]

    def hold(i):
        with lock:
            with count:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
                order.append(i)
            leave[i].wait(10)
            with count:
                inside[0] -= 1

    threads = [threading.Thread(target=hold, args=(i,)) for i in range(5)]
    for i, t in enumerate(threads):
        t.start()
        assert wait_until(lambda i=i: lock.queued() == i + 1, 10)  # thread i holds it or waits in line
    assert order == [0, 1]  # two hold it, three wait
    for i, entered in ((1, [0, 1, 2]), (0, [0, 1, 2, 3]), (3, [0, 1, 2, 3, 4])):
        leave[i].set()  # one slot freed: the longest waiter alone gets it
        assert wait_until(lambda entered=entered: len(order) == len(entered), 10)
        assert order == entered and inside[0] == 2
    for e in leave:
        e.set()
    for t in threads:
        t.join(10)
    assert most[0] == 2 and lock.queued() == 0
    with pytest.raises(ValueError, match="slots"):
        FifoLock(slots=0)


def test_a_batch_left_while_it_waits_for_its_turn_is_not_simulated(tiny_dataset):
    simulator = Simulator(workers=1)  # rolls out on the caller's thread: every rollout is counted
    commands = tiny_dataset.commands[:1].astype(np.float64)
    calls, rollout = [], sim_physics.mj_rollout.rollout
    sim_physics.mj_rollout.rollout = lambda *a, **k: calls.append(1) or rollout(*a, **k)
    still_wanted, results = [True], []
    try:
        with simulator._lock:  # another caller's batch is rolling out
            t = threading.Thread(
                target=lambda: results.append(simulator.simulate(commands, lambda: still_wanted[0]))
            )
            t.start()
            deadline = time.monotonic() + 10
            while simulator._lock.queued() < 2 and time.monotonic() < deadline:  # it waits in line
                time.sleep(0.001)
            still_wanted[0] = False  # its gait is left meanwhile
        t.join(30)
        assert results == [None] and calls == []
        kept = simulator.simulate(commands, lambda: True)
        np.testing.assert_array_equal(kept.body[0].astype(np.float32), tiny_dataset.body[0])
        assert calls == [1]
    finally:
        sim_physics.mj_rollout.rollout = rollout


def test_a_streamed_replay_is_the_replay_chunk_by_chunk_and_stops_where_it_is_left(monkeypatch):
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.physics import threads
    from snakeloco.sim.physics.results import STREAM_FIRST
    from snakeloco.sim.physics.threads import RolloutThreads

    simulator = Simulator(workers=1)
    commands = PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)
    whole = simulator.replay(commands)
    parts = list(simulator.stream(commands, chunk_samples=300, first_samples=100))
    assert [p.samples for p in parts] == [100, 400, 700, 1000, 1300, 1600, 1900, 2000]
    assert [p.done for p in parts] == [False] * 7 + [True] and all(p.failure is None for p in parts)
    for p in parts:  # every part is a prefix of the un-chunked replay, to the bit
        np.testing.assert_array_equal(p.joint_angles, whole.joint_angles[: p.samples])
        np.testing.assert_array_equal(p.body, whole.body[: p.samples])
        np.testing.assert_array_equal(p.qpos, whole.qpos[: p.samples])
    # A consumer that leaves after the first part (a superseded replay) costs one chunk of physics.
    calls = []
    rollout = sim_physics.mj_rollout.rollout
    sim_physics.mj_rollout.rollout = lambda *a, **k: calls.append(1) or rollout(*a, **k)
    try:
        stream = simulator.stream(commands, chunk_samples=300)
        next(stream)
        stream.close()
    finally:
        sim_physics.mj_rollout.rollout = rollout
    assert len(calls) == 1
    # On a runner, a stream no longer wanted ends while its chunk is still in flight.
    runner, parts = RolloutThreads(1, name="replay"), []
    try:
        for part in simulator.stream(commands, chunk_samples=500, runner=runner, wanted=lambda: not parts):
            parts.append(part)
        assert [p.samples for p in parts] == [STREAM_FIRST]
        every = list(
            simulator.stream(commands, chunk_samples=500, runner=lambda k: runner, wanted=lambda: True)
        )
        np.testing.assert_array_equal(every[-1].body, whole.body)  # a runner per chunk: the same replay
        # A chunk still queued behind the runner's other work (the chunk a left replay left running)
        # never runs once its stream is left: superseded gaits do not pile up physics in the queue.
        busy, ran = threading.Event(), []
        one = threads.rollout_row
        monkeypatch.setattr(threads, "rollout_row", lambda *a, **k: ran.append(1) or one(*a, **k))
        runner._executor.submit(busy.wait, 30)
        left = iter([True, False])
        assert list(simulator.stream(commands, runner=runner, wanted=lambda: next(left, False))) == []
        busy.set()
        runner._executor.submit(lambda: None).result(timeout=30)  # the runner has done all it will
        assert ran == []
    finally:
        runner.close()
    # A gait that breaks the physics ends its stream with the reason, as replay raises it.
    strict = Simulator(workers=1, config=CommandRule(max_com_height=0.03))
    last = list(strict.stream(commands, chunk_samples=300))[-1]
    assert last.failure is not None and "thrown" in last.failure and not last.done
    with pytest.raises(SimulationError) as broken:  # the same words, time included
        strict.replay(commands)
    assert str(broken.value) == last.failure
    with pytest.raises(ValueError, match="NaN"):
        next(simulator.stream(np.full((2000, 8), np.nan)))


def test_a_streamed_replay_holds_one_chunk_of_steps_not_the_whole_record():
    """A stream keeps the record's samples and one chunk's physics steps (~0.7 MB): the whole
    record's steps (41,200 x 51 float64, ~17 MB) stayed resident in every tab's replay as it ran."""
    import tracemalloc

    from snakeloco.sim.gaits.library import PRESETS

    simulator = Simulator(workers=1)
    commands = PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)
    whole_steps = simulator.n_steps * 51 * 8
    tracemalloc.start()
    try:
        parts = sum(1 for _ in simulator.stream(commands))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert parts > 30
    assert peak < whole_steps / 4, f"peak {peak / 1e6:.1f} MB while streaming"


def _thread_nices() -> list[int]:
    """Nice values of this process's threads (Linux /proc)."""
    nices = []
    for stat in Path("/proc/self/task").glob("*/stat"):
        fields = stat.read_text().rsplit(")", 1)[1].split()
        nices.append(int(fields[16]))  # field 19 of proc(5), counted after the command name
    return nices
