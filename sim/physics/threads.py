"""The threads physics runs on: MuJoCo rollouts on niced Python threads that block (not a native pool
whose caller spins), a lock granted in request order, and thread priorities.

Linux only where it matters (per-thread nice); elsewhere the priorities are left alone.
"""

from __future__ import annotations

import collections
import functools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from snakeloco.sim.physics import ground_contact


def set_thread_nice(value: int | None) -> int | None:
    """Set the calling thread's nice value (Linux: per thread; threads and processes it starts
    inherit it); returns the previous value, or None where that is not possible."""
    if value is None or not hasattr(os, "setpriority"):
        return None
    tid = threading.get_native_id()
    try:
        previous = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, value)
    except OSError:
        return None
    return previous


def lower_thread_priority(increment: int) -> int | None:
    """Raise the calling thread's nice value by ``increment``; returns the previous value or None."""
    if not hasattr(os, "getpriority"):
        return None
    return set_thread_nice(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + increment)


class FifoLock:
    """A lock granted in request order (``threading.Lock`` lets a thread that just released it win
    again): tabs sharing one simulator each get their turn between the others' batches, and tabs
    sharing the server's decode stage theirs between the others' decodes.

    ``slots``: how many may hold it at once (a FIFO semaphore; 1: a lock). A release hands the slot
    to the longest waiter and wakes that one thread alone (a condition's ``notify_all`` woke every
    waiter to check its ticket: 1.4 ms per hand-off at the median, 4.2 at p95, with 8 tabs' decodes
    queued on 2 busy cores)."""

    def __init__(self, slots: int = 1) -> None:
        if slots < 1:
            raise ValueError(f"slots must be at least 1, got {slots}")
        self._lock = threading.Lock()
        self._free = slots
        self._waiting: collections.deque[threading.Lock] = collections.deque()
        self._held = 0

    def __enter__(self) -> None:
        with self._lock:
            if self._free and not self._waiting:
                self._free -= 1
                self._held += 1
                return
            turn = threading.Lock()
            turn.acquire()
            self._waiting.append(turn)
        turn.acquire()  # released by the holder that hands us its slot (counted there)

    def __exit__(self, *exc) -> None:
        with self._lock:
            if self._waiting:
                self._waiting.popleft().release()  # the slot passes straight to the next in line
            else:
                self._free += 1
                self._held -= 1

    def queued(self) -> int:
        """Threads that hold the lock or wait for it."""
        with self._lock:
            return self._held + len(self._waiting)


class RowRunner:
    """Where rollouts run, one record (row) a task: ``rollout`` submits each row's pool-less rollout
    (``rollout_row``) through ``_submit`` and, with ``wait``, blocks until all are in. A row whose
    future is cancelled (never run) leaves its arrays as they were."""

    def _submit(self, call: Callable[[], None]) -> Future:
        raise NotImplementedError

    def rollout(
        self,
        model: mujoco.MjModel | list[mujoco.MjModel],
        initial: np.ndarray,
        ctrl: np.ndarray,
        warm: np.ndarray,
        state: np.ndarray,
        sensordata: np.ndarray,
        data: mujoco.MjData | None = None,
        wait: bool = True,
        warm_out: np.ndarray | None = None,
    ) -> list[Future]:
        """Roll out rows ``initial`` (B, nstate), ``ctrl`` (B, nstep, nu) from ``warm`` (B, nv) into
        ``state`` (B, nstep, nstate) and ``sensordata`` (B, nstep, nsensordata), one row per task;
        ``data``: the MjData to use (one row only: a stream keeps its own); ``warm_out`` (B, nv):
        where to put each row's warm start after its last step; ``model``: one, or one per row (of
        one size signature). Blocks until all are in, unless not ``wait``: then returns the rows'
        futures at once."""
        if data is not None and len(ctrl) != 1:
            raise ValueError("a given MjData serves one row at a time")
        futures = [
            self._submit(
                functools.partial(
                    rollout_row,
                    _THREAD,
                    model[i] if isinstance(model, list) else model,
                    data,
                    None if warm_out is None else warm_out[i],
                    initial_state=initial[i : i + 1],
                    control=ctrl[i : i + 1],
                    initial_warmstart=warm[i : i + 1],
                    state=state[i : i + 1],
                    sensordata=sensordata[i : i + 1],
                )
            )
            for i in range(len(ctrl))
        ]
        if wait:
            wait_futures(futures)
            for f in futures:
                if not f.cancelled():
                    f.result()  # a row's exception, raised here
        return futures


class RolloutThreads(RowRunner):
    """``n`` Python threads, ``nice`` below their creator, that run MuJoCo rollouts one record each.

    Why not ``mujoco.rollout.Rollout(nthread=n)``: its caller waits for the pool by spinning
    (``std::this_thread::yield``) at the caller's own priority, so a server thread waiting for a
    niced ensemble burnt a core at full priority for the whole batch (measured: the waiting thread
    used 0.82 s of CPU in a 0.82 s rollout). Here each thread calls a pool-less rollout, which runs
    on that thread with the GIL released, and the caller blocks on a future without using the CPU.
    The threads take the GIL only to enter and leave a rollout. Rows are independent (each from its
    own initial state and warm start), so the results do not depend on which thread ran them.
    """

    def __init__(self, n: int, nice: int = 0, name: str = "rollout") -> None:
        self.n = max(1, int(n))
        self._executor = ThreadPoolExecutor(
            self.n, thread_name_prefix=name, initializer=self._start_thread, initargs=(int(nice),)
        )
        started = threading.Barrier(self.n + 1)  # all threads now (an executor starts them lazily)
        for _ in range(self.n):
            self._executor.submit(started.wait)
        started.wait()

    @staticmethod
    def _start_thread(nice: int) -> None:
        if nice > 0:  # lowering needs no privilege; the creator's priority is untouched
            lower_thread_priority(nice)

    def _submit(self, call: Callable[[], None]) -> Future:
        return self._executor.submit(call)

    def close(self) -> None:
        """Finish the rollouts in progress and stop the threads."""
        self._executor.shutdown(wait=True, cancel_futures=True)


def resolve_workers(workers: int | None) -> int:
    """Simulation threads to use: ``workers``, or one per core of this machine where it is None."""
    return max(1, int(workers)) if workers is not None else (os.cpu_count() or 1)


def rollout_row(
    local: threading.local,
    model: mujoco.MjModel,
    data: mujoco.MjData | None,
    warm_out: np.ndarray | None,
    **arrays,
) -> None:
    """One row's pool-less rollout on the calling thread (GIL released in MuJoCo): ``local`` keeps
    the thread's rollout object and its own MjData per model where ``data`` is None (rollout sets
    its whole state); ``warm_out``: where to put the solver's warm start after the last step (to
    carry on from)."""
    if not hasattr(local, "runner"):
        local.runner = mj_rollout.Rollout(nthread=0)  # no pool: runs on this thread
        local.data = {}
    if data is None:
        # One MjData per size signature, not per model: a fit or a variation set rolls out many
        # models of one signature (rollout sets the whole state, as mujoco.rollout does with one
        # MjData for a sequence of models), and a dict keyed by model grew with every candidate.
        data = local.data.get(model.signature)
        if data is None:
            data = local.data[model.signature] = mujoco.MjData(model)
    ground_contact.rollout(model, data, runner=local.runner, **arrays)
    if warm_out is not None:
        warm_out[:] = data.qacc_warmstart


_THREAD = threading.local()
"""Each rollout thread's pool-less rollout and its MjData per model size signature (never shared)."""
