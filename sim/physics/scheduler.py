"""One pool of physics threads shared by every tab of a server, with fair turns.

Each tab's physics comes as chunk-sized tasks: the chunks of a streamed replay (the first one, the
first motion; the later ones of a gait the user has let go of; those of a gait still being dragged
through) and the rows of an ensemble. ``FairPhysics`` runs them on ``threads`` niced rollout threads
(``sim.physics.threads``: MuJoCo's rollout with the GIL released) in this order:

1. strictly by class (``LANES``): every waiting replay chunk of any tab before any tab's ensemble
   row; a new gait's first motion first of all once its slider value is held (a first motion of a
   value a slider may still be passing through comes after the settled replays' chunks);
2. inside a class, round robin between tabs: the tab served longest ago goes next, so a tab with a
   long queue (an 8-member ensemble) cannot hold up a tab with one row, and no tab starves;
   then physics variations, inverse design's replays (a search of seconds), and last a fit of the
   robot to a measured run (minutes);
3. a task whose ``wanted()`` says no when its turn comes is dropped unrun (its future cancelled):
   superseded work never takes a core. ``Future.cancel`` on a queued task does the same.

A task that is running is not preempted: a replay chunk (~0.02-0.04 s of physics) or an ensemble
row's segment (``SEGMENT_SAMPLES``, ~0.06 s) is the longest a waiting replay chunk waits for a free
thread. ``first_threads`` more threads, at ``first_nice``, serve held first motions alone
(``FIRST_LANES``): with several tabs the pool's threads are always busy with replays, and a first
motion neither waits for one of them to finish its chunk nor runs level with them, since at most
``threads`` tasks run at once: while first motions run, the pool's threads start no new task (a
running one finishes its chunk). The pool counts each class's thread time (``busy_s``: ``bench
load`` reports it).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from concurrent.futures import Future
from dataclasses import dataclass, field
from enum import IntEnum

from snakeloco.sim.physics.results import Dropped
from snakeloco.sim.physics.threads import RowRunner, lower_thread_priority


class Turn(IntEnum):
    """The classes of physics work, in the order they are served."""

    FIRST_MOTION = 0  # a replay's first chunk: the snake starts to move
    SETTLED = 1  # later chunks of a gait the user has let go of
    DRAGGED = 2  # later chunks of a gait a slider is still passing through
    ENSEMBLE = 3  # the perturbed copies that score a finished replay
    VARIATIONS = 4  # the replay on other robots (physics variations)
    CLOSED_LOOP = 5  # the steering loop's probes and replays on those robots
    DESIGN = 6  # inverse design's candidate replays (a search of several seconds)
    FIT = 7  # fitting the robot's physics to a measured run (minutes of replays)


@dataclass
class _Task:
    future: Future
    run: Callable[[], None]
    turn: Turn
    wanted: Callable[[], bool] | None = None
    held_at: float | None = None  # a first motion: when its value counts as held (perf_counter; None: held)

    def is_held(self) -> bool:
        return self.held_at is None or time.perf_counter() >= self.held_at


@dataclass
class _Class:
    """One class's queues: tab -> its tasks in order, tabs in the order they are to be served."""

    queues: OrderedDict = field(default_factory=OrderedDict)

    def pop(self, held_only: bool = False) -> _Task | None:
        """The next tab's first task (``held_only``: the next tab's whose first task ``is_held``)."""
        for tab in list(self.queues):
            if held_only and not self.queues[tab][0].is_held():
                continue
            queue = self.queues.pop(tab)  # served now: to the back of the line if it has more
            task = queue.popleft()
            if queue:
                self.queues[tab] = queue
            return task
        return None


LANES = (
    (Turn.FIRST_MOTION, True),
    (Turn.SETTLED, False),
    (Turn.DRAGGED, False),
    (Turn.FIRST_MOTION, False),
    (Turn.ENSEMBLE, False),
    (Turn.VARIATIONS, False),
    (Turn.CLOSED_LOOP, False),
    (Turn.DESIGN, False),
    (Turn.FIT, False),
)
"""The order ``FairPhysics`` serves in: (class, held values only). A first motion whose slider
value is younger than its tab's hold (before ``held_at``: the slider may be passing through it) comes
after every tab's settled replay chunks, so tabs dragging sliders do not hold up a replay another
tab waits for; with no settled chunk waiting it runs at once, and once held it is first again."""

FIRST_LANES = ((Turn.FIRST_MOTION, True),)
"""What a first-motion thread serves (``FairPhysics(first_threads=...)``): held first motions alone,
so that it is free when one comes (a value a slider passes through is left to the pool)."""


class FairPhysics:
    """``threads`` rollout threads at ``nice`` below their creator, serving tabs' tasks fairly.

    ``runner(tab, turn, wanted)`` gives an object with ``RolloutThreads.rollout``'s signature, so
    ``Simulator.stream`` and ``Simulator.simulate`` run on it unchanged (same results: each row is a
    pool-less rollout on one thread, from its own initial state and warm start).
    """

    def __init__(
        self,
        threads: int,
        nice: int = 0,
        name: str = "physics",
        first_threads: int = 0,
        first_nice: int | None = None,
    ) -> None:
        self.threads = max(1, int(threads))
        self._classes = {turn: _Class() for turn in Turn}
        self._cond = threading.Condition()
        self._closed = False
        self.served: dict[Turn, int] = dict.fromkeys(Turn, 0)
        self.busy_s: dict[Turn, float] = dict.fromkeys(Turn, 0.0)  # thread seconds run, per class
        self.dropped = 0
        self._running = 0  # tasks running now, on any thread
        first_nice = nice if first_nice is None else first_nice
        self._workers = [
            threading.Thread(target=self._loop, args=(int(nice), False), name=f"{name}-{i}", daemon=True)
            for i in range(self.threads)
        ] + [
            threading.Thread(
                target=self._loop, args=(int(first_nice), True), name=f"{name}-first-{i}", daemon=True
            )
            for i in range(max(0, int(first_threads)))
        ]
        for worker in self._workers:
            worker.start()

    def runner(
        self,
        tab: Hashable,
        turn: Turn,
        wanted: Callable[[], bool] | None = None,
        held_at: float | None = None,
    ) -> FairRunner:
        """Where a tab's work of one class goes (``rollout`` as ``RolloutThreads.rollout``)."""
        return FairRunner(self, tab, Turn(turn), wanted, held_at)

    def submit(
        self,
        tab: Hashable,
        turn: Turn,
        run: Callable[[], None],
        wanted: Callable[[], bool] | None = None,
        held_at: float | None = None,
    ) -> Future:
        """Queue ``run()`` for ``tab`` in class ``turn``; its future completes when it has run (or is
        cancelled: dropped as unwanted, or by ``Future.cancel`` while queued). ``held_at``: for a first
        motion, when its slider value counts as held (``time.perf_counter``; ``LANES``)."""
        future: Future = Future()
        with self._cond:
            if self._closed:
                raise RuntimeError("the physics pool was closed (the server is stopping)")
            queues = self._classes[Turn(turn)].queues
            queues.setdefault(tab, deque()).append(_Task(future, run, Turn(turn), wanted, held_at))
            self._cond.notify_all()  # threads serve different lanes: any of them may be the one
        return future

    def pending(self) -> dict[Turn, int]:
        """Tasks waiting per class."""
        with self._cond:
            return {t: sum(map(len, c.queues.values())) for t, c in self._classes.items()}

    def _next(self, first: bool = False) -> _Task | None:
        """The next task to run (``first``: for a first-motion thread, in ``FIRST_LANES``, else in
        ``LANES``), None once closed (caller holds the condition)."""
        lanes = FIRST_LANES if first else LANES
        while True:
            # A pool thread starts a task only in a free slot; a first-motion thread always can.
            free = first or self._running < self.threads
            for turn, held_only in lanes if free else ():
                task = self._classes[turn].pop(held_only)
                if task is not None:
                    self.served[turn] += 1
                    self._running += 1
                    return task
            if self._closed:
                return None
            self._cond.wait(self._until_held() if first else None)

    def _until_held(self) -> float | None:
        """Seconds until the next queued first motion is held (a hold is a time, not an event: a
        first-motion thread wakes for it), None where none waits (caller holds the condition)."""
        times = [q[0].held_at for q in self._classes[Turn.FIRST_MOTION].queues.values() if q[0].held_at]
        return max(0.0, min(times) - time.perf_counter()) if times else None

    def _loop(self, nice: int, first: bool = False) -> None:
        if nice > 0:
            lower_thread_priority(nice)
        while True:
            with self._cond:
                task = self._next(first)
            if task is None:
                return
            if task.wanted is not None and not task.wanted():
                _drop(task.future)
                with self._cond:
                    self.dropped += 1
                    self._ended()
                continue
            if not task.future.set_running_or_notify_cancel():
                with self._cond:
                    self._ended()
                continue  # cancelled while queued
            t0, error = time.perf_counter(), None
            try:
                task.run()
            except BaseException as exc:  # handed to whoever waits on the future
                error = exc
            with self._cond:
                self.busy_s[task.turn] += time.perf_counter() - t0
                self._ended()
            if error is None:
                task.future.set_result(None)
            else:
                task.future.set_exception(error)

    def _ended(self) -> None:
        """A task's slot is free (caller holds the condition): wake a pool thread that waits for one."""
        self._running -= 1
        if self._running == self.threads - 1:
            self._cond.notify_all()

    def close(self) -> None:
        """Cancel what is queued, let running tasks finish, stop the threads."""
        with self._cond:
            self._closed = True
            for cls in self._classes.values():
                for queue in cls.queues.values():
                    for task in queue:
                        _drop(task.future)
                cls.queues.clear()
            self._cond.notify_all()
        for worker in self._workers:
            if worker is not threading.current_thread():
                worker.join()


def _drop(future: Future) -> None:
    """Cancel a queued task's future and wake whoever waits on it (``concurrent.futures.wait``'s
    waiters learn of a cancellation only from ``set_running_or_notify_cancel``)."""
    future.cancel()
    future.set_running_or_notify_cancel()


class FairRunner(RowRunner):
    """One tab's work of one class on a ``FairPhysics`` (``RolloutThreads.rollout``'s signature)."""

    def __init__(
        self,
        pool: FairPhysics,
        tab: Hashable,
        turn: Turn,
        wanted: Callable[[], bool] | None,
        held_at: float | None = None,
    ):
        self.pool, self.tab, self.turn, self.wanted, self.held_at = pool, tab, turn, wanted, held_at

    def _submit(self, call: Callable[[], None]) -> Future:
        return self.pool.submit(self.tab, self.turn, call, self.wanted, self.held_at)


SEGMENT_SAMPLES = 125
"""Record samples (6.25 s) of a batch row per task on the pool (~0.06 s of physics for a compass
gait): how long a new gait's first motion can wait for a thread behind an ensemble (docs/load.md,
"SEGMENT_SAMPLES")."""


class OnTurns:
    """A ``Simulator`` whose batches run as one tab's tasks of one class on a ``FairPhysics``: for
    code written against a simulator (``LocalBackend.on``, an ensemble's batches). ``workers`` is
    the pool's thread count; everything else is the simulator's."""

    def __init__(self, simulator, runner: FairRunner, raises: bool = False) -> None:
        self._simulator, self._runner, self._raises = simulator, runner, raises
        self.workers = runner.pool.threads

    def _kept(self, result):
        """``result``, or where its rows were dropped: None, or with ``raises`` the ``Dropped`` exception
        (for code that knows nothing of dropping: a design's backend jobs)."""
        if result is None and self._raises:
            raise Dropped("the tab no longer wants this work (cancelled, superseded or closed)")
        return result

    def simulate(self, commands, wanted=None, samples=None, resume=None, robots=None):
        """``Simulator.simulate`` on the pool's turns (None where a row was dropped as unwanted, or
        ``Dropped`` raised: ``raises``). A
        whole batch (or its first ``samples``) runs in segments of ``SEGMENT_SAMPLES`` per row and
        task (paused and carried on: the same numbers as one rollout), so no task holds a thread
        long. ``robots``: one variation of the simulator's robot per row."""
        if resume is not None:
            return self._kept(
                self._simulator.simulate(
                    commands, wanted, samples, resume, runner=self._runner, robots=robots
                )
            )
        total, result = samples or self._simulator.excitation.n_samples, None
        for end in range(SEGMENT_SAMPLES, total + SEGMENT_SAMPLES, SEGMENT_SAMPLES):
            paused = None if result is None else result.paused
            result = self._simulator.simulate(
                commands, wanted, min(end, total), paused, runner=self._runner, robots=robots
            )
            if result is None:
                return self._kept(None)
        return result

    @property
    def pool(self) -> FairRunner:
        """Where a closed loop's rows go (``sim.control.closed_loop``): this tab's turns."""
        return self._runner

    def replay(self, commands):
        """``Simulator.replay`` on the pool's turns."""
        return self._simulator.replay(commands, runner=self._runner)

    def __getattr__(self, name: str):
        return getattr(self._simulator, name)
