"""A designer server's decodes in a child process of their own, away from the server's GIL.

Why: a decode is 3-4 ms of torch graphs, numpy and Python alone, but in a server with 8 tabs it took
9-12 ms (p95): its every numpy call and Python line waits for the GIL that the server's drawing and
websocket threads hold in bursts. In a child process the same decode took 4.0 / 4.2 ms (p50 / p95)
beside two bursty Python threads where a thread took 8.1 / 10.6 (docs/load.md), and the server's
threads no longer wait for the decode's bytecode either.

``DecodeProcess`` starts the child as ``python -m snakeloco.app.server.decode_process`` (not
multiprocessing's spawn, which re-runs the caller's main script: a script that builds a server at its
top level would build another), at the server's priority and in its scheduling group, talking over
a socket pair; it ignores Ctrl-C (the server's to act on, by closing it) and leaves when asked or when
the socket closes. Until it has loaded the server's checkpoints and said so, and for ever after it
fails, ``decode`` returns None and the caller decodes in its own thread (``app.designer.session.decode_latents``, the function the child runs
too, with the server's torch thread count: the same bits either way). POSIX only (the child inherits
its end of the socket); elsewhere every decode stays in the server.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterable
from multiprocessing.connection import Connection
from pathlib import Path

from snakeloco.app.designer.session import DecodedGait, Latents
from snakeloco.sim.physics.threads import FifoLock

READY = "ready"
_RUNNING: set[int] = set()
JOIN_S = 5.0
"""How long ``close`` waits for the child to leave before it is terminated."""
IN_FLIGHT = 2
"""Requests a child holds at once: the one it decodes and the next, waiting in its socket, so that it
starts the next decode as soon as it has sent a reply rather than once the server's thread has woken,
taken the GIL and read it. With 8 tabs dragging, a decode's round trip took 9.6 / 15.8 ms (p50 / p95)
for 7.0 / 11.0 ms of decoding (docs/load.md): the rest held the one turn while the child idled."""


def _serve(conn, paths: list[str], threads: int) -> None:
    """The child: load the checkpoints at ``paths``, say ready, then decode ``(path, latents)``
    requests until None or the parent goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the terminal's Ctrl-C is the server's: it closes us
    import torch

    from snakeloco.app.designer.session import decode_latents
    from snakeloco.model.api import load_pretrained

    torch.set_num_threads(threads)
    try:
        models = {path: load_pretrained(path) for path in paths}
        for model in models.values():  # its graphs are made on first use: not on a tab's first slider move
            decode_latents(model, Latents(z_b=(0.0,) * model.z_b_dim))
        status = (READY, None)
    except Exception as exc:  # any failure is the parent's to report
        status = (False, f"decode process could not start: {type(exc).__name__}: {exc}")
    try:
        conn.send(status)
    except OSError:
        return  # the parent went away while we started
    if status[0] != READY:
        return
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone
        if request is None:
            return
        path, latents = request
        try:
            reply = (True, decode_latents(models[path], latents))
        except Exception as exc:
            reply = (False, f"{type(exc).__name__}: {exc}")
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


class DecodeProcess:
    """Decodes for the checkpoints at ``paths`` in a child process (see the module's docstring).

    ``decode(path, latents)`` is safe from any thread: requests go to the child in the order they
    come, up to ``IN_FLIGHT`` at once (the callers' turns bound them), and each caller reads its own
    reply, in the same order. It returns None where the child is not (or no longer) there to decode,
    and raises ``RuntimeError`` with the child's message where the decode itself failed there."""

    def __init__(self, paths: Iterable[str | Path], threads: int, on_error=None) -> None:
        self.paths = {str(Path(p).resolve()) for p in paths}
        self._on_error = on_error or (lambda message: None)
        self._lock = threading.Lock()  # sending (and the ready check, and closing)
        self._replies = threading.Condition()  # reading, in the order the requests were sent
        self._ending = threading.Lock()
        self._sent = 0
        self._read = 0
        self._ready = False
        self._failed: str | None = None
        self._process: subprocess.Popen | None = None
        self.served = 0
        """Decodes the child has answered."""
        if os.name != "posix":
            self._failed = f"no decode process on {os.name}"  # not an error: the server decodes
            return
        ours, theirs = socket.socketpair()
        with theirs:
            self._process = subprocess.Popen(
                [sys.executable, "-m", __name__, str(theirs.fileno()), str(threads), *sorted(self.paths)],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},
            )
        self._conn = Connection(ours.detach())
        _RUNNING.add(self._process.pid)

    @property
    def ready(self) -> bool:
        """Whether the child has loaded the checkpoints and decodes (checked without blocking)."""
        if not self._ready and self._failed is None and self._lock.acquire(blocking=False):
            try:
                if self._conn.poll():
                    self._receive_ready()
            except (EOFError, OSError) as exc:
                self._fail(f"decode process ended before it was ready ({type(exc).__name__})")
            finally:
                self._lock.release()
        return self._ready

    def _receive_ready(self) -> None:
        status, message = self._conn.recv()
        if status == READY:
            self._ready = True
        else:
            self._fail(message)

    def _fail(self, message: str) -> None:
        self._failed = message
        self._ready = False
        self._on_error(f"{message}; decoding in the server's threads from now on")

    @property
    def failed(self) -> str | None:
        """Why the child no longer decodes (None while it does or is starting)."""
        return self._failed

    def decode(self, path: str | Path | None, latents: Latents) -> DecodedGait | None:
        """The child's decode of ``latents`` on the checkpoint at ``path``, or None (see the class)."""
        if path is None or not self.ready or str(Path(path).resolve()) not in self.paths:
            return None
        with self._lock:
            if self._failed is not None:
                return None
            try:
                self._conn.send((str(Path(path).resolve()), latents))
            except OSError as exc:
                self._ended(exc)
                return None
            ticket, self._sent = self._sent, self._sent + 1
        with self._replies:
            while self._read != ticket:  # the replies before ours are their senders' to read
                self._replies.wait()
            try:
                if self._failed is not None:
                    return None
                ok, value = self._conn.recv()
                self.served += 1
            except (EOFError, OSError) as exc:
                self._ended(exc)
                return None
            finally:
                self._read += 1
                self._replies.notify_all()
        if not ok:
            raise RuntimeError(f"decode process: {value}")
        return value

    @property
    def in_flight(self) -> int:
        """Requests sent to the child whose replies are not read yet."""
        return self._sent - self._read

    def _ended(self, exc: Exception) -> None:
        """The child's socket failed: say why it ended (once), and decode in the server from now on."""
        with self._ending:
            if self._failed is not None:
                return
            try:  # a killed child's socket closes before it is reaped: give it a moment
                code = self._process.wait(JOIN_S)
            except subprocess.TimeoutExpired:
                code = None  # alive but not answering: it is closed with the server
            self._fail(f"decode process ended (exit code {code}, {type(exc).__name__})")

    @property
    def pid(self) -> int | None:
        """The child's process id (None where none was started)."""
        return None if self._process is None else self._process.pid

    def close(self) -> None:
        """Ask the child to leave; terminate it if it has not within ``JOIN_S``."""
        with self._lock:
            self._failed, self._ready = self._failed or "closed", False
            if self._process is None:
                return
            with self._replies:  # requests in flight give up their replies: none is read any more
                self._replies.wait_for(lambda: self._read == self._sent, JOIN_S)
            try:
                self._conn.send(None)
            except OSError:
                pass  # gone already
            self._conn.close()
            try:
                self._process.wait(JOIN_S)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
            _RUNNING.discard(self._process.pid)


class DecodePool:
    """The decode stage a server's tabs share: ``processes`` child processes (``DecodeProcess``) and
    the turns on them (``turns``: FIFO, ``IN_FLIGHT`` a process; one at a time with none, then every
    decode runs in its tab's thread)."""

    def __init__(self, paths: Iterable[str | Path], threads: int, processes: int, on_error=None) -> None:
        paths = list(paths)
        self.processes = [DecodeProcess(paths, threads, on_error) for _ in range(processes)]
        self.turns = FifoLock(slots=max(1, IN_FLIGHT * processes))
        """Held by a tab while it decodes: granted in the order the tabs asked."""
        self._idle: queue.SimpleQueue[DecodeProcess] = queue.SimpleQueue()
        for _ in range(IN_FLIGHT):  # each process once per request it may hold
            for process in self.processes:
                self._idle.put(process)
        self._in_thread = threading.Lock()

    def decode(self, path: str | Path | None, latents: Latents, fallback) -> DecodedGait:
        """Decode ``latents`` (on the checkpoint at ``path``) in an idle child process, or with
        ``fallback(latents)`` in this thread where none can (starting, failed, a checkpoint it did not
        load), one such at a time: GIL-bound decodes side by side only slow each other. Call it
        holding ``turns``."""
        if self.processes:
            process = self._idle.get()  # holding a turn, one is idle
            try:
                decoded = process.decode(path, latents)
            finally:
                self._idle.put(process)
            if decoded is not None:
                return decoded
        with self._in_thread:
            return fallback(latents)

    def close(self) -> None:
        for process in self.processes:
            process.close()


def decode_pids() -> set[int]:
    """Process ids of this process's running decode processes: the server's own work, for the load
    benchmark's CPU and memory figures (not the browsers it started)."""
    return set(_RUNNING)


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])), sys.argv[3:], int(sys.argv[2]))
