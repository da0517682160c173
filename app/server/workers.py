"""``LatestWorker``: one thread that runs the newest of the requests submitted to it (a tab's decode,
replay, ensemble, design and fit jobs each have one)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class LatestWorker:
    """One thread that runs ``fn(version, request, is_current)`` for the newest submitted request.

    Requests submitted while a job runs replace each other; when the job ends only the newest is
    run. ``is_current()`` tells a job whether a newer request has arrived (then it should stop
    drawing). Versions increase with every submit.
    """

    def __init__(
        self,
        fn: Callable[[int, object, Callable[[], bool]], None],
        name: str = "gait-worker",
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        self._fn = fn
        self._on_error = on_error
        self._cv = threading.Condition()
        self._pending: tuple[int, object] | None = None
        self._version = 0
        self._busy = False
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    @property
    def version(self) -> int:
        return self._version

    def submit(self, request: object) -> int:
        with self._cv:
            self._version += 1
            self._pending = (self._version, request)
            self._cv.notify_all()
            return self._version

    def idle(self) -> bool:
        with self._cv:
            return self._pending is None and not self._busy

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until no job is pending or running (for tests and benchmarks)."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._pending is not None or self._busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
            return True

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout=30)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                version, request = self._pending
                self._pending = None
                self._busy = True
            try:
                self._fn(version, request, lambda v=version: v == self._version)
            except Exception as exc:  # a job's failure must never kill the worker
                import traceback

                if self._closed:
                    continue  # closed mid-job (the tab went away): its failure is no one's error
                traceback.print_exc()
                if self._on_error is not None:
                    try:
                        self._on_error(exc)
                    except Exception:
                        traceback.print_exc()
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
