"""``snakeloco serve``: the browser designer's server lifecycle on viser.

``DesignerServer`` loads the checkpoint, starts one shared pool of physics threads and a viser server,
and gives every browser tab a ``DesignerClient`` (``tab.py``). ``serve`` also tunes the process for
serving (``tune_process``) and runs until Ctrl-C or SIGTERM; constructing a ``DesignerServer`` alone
(tests, benchmarks) changes no process-wide setting.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import signal
import socket
import sys
import threading
import traceback
from pathlib import Path

import torch
import viser

from snakeloco.app.designer.tab import (
    FIRST_MOTION_NICE,
    FIRST_MOTION_THREADS_PER_CORE,
    PHYSICS_NICE,
    DesignerClient,
)
from snakeloco.app.export.gait_csv import MAX_BYTES
from snakeloco.app.server.decode_process import DecodePool
from snakeloco.app.server.viser_patches import refuse_large_uploads, share_prop_hints
from snakeloco.model.api import GaitModel, load_pretrained
from snakeloco.model.checkpoint import SHIPPED, CheckpointError, resolve_checkpoint
from snakeloco.sim.physics.scheduler import FairPhysics
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.physics.threads import resolve_workers
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE
from snakeloco.sim.world.description import World

DECODE_THREADS = 1
"""torch intra-op threads of a designer server process: more did not decode faster on 2 cores
(docs/load.md, "DECODE_THREADS")."""
DECODE_PROCESSES = 1
"""Child processes a designer server decodes in (``app.server.decode_process``): a second one made no
decoded view faster for ~250 MB more (docs/load.md, "DECODE_PROCESSES")."""
SWITCH_INTERVAL_S = 0.001
"""Python's GIL switch interval in a designer server (default 0.005 s)."""
_M_MMAP_THRESHOLD = -3  # glibc malloc.h
_M_ARENA_MAX = -8


MMAP_THRESHOLD = 256 << 10
"""Bytes from which a designer server's allocations get mappings of their own
(``return_freed_buffers_to_the_os``): a stream's reused chunk buffers then go back to the OS when
freed (docs/load.md, "MMAP_THRESHOLD")."""


MALLOC_ARENAS = 2
"""glibc malloc arenas of a designer server process (``limit_malloc_arenas``): fewer arenas keep fewer
freed pages (docs/load.md, "MALLOC_ARENAS")."""


def _mallopt(param: int, value: int) -> bool:
    """glibc's ``mallopt``: whether the setting took (False off Linux or off glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(param, int(value)))
    except (OSError, AttributeError):  # not glibc
        return False


def return_freed_buffers_to_the_os(threshold: int = MMAP_THRESHOLD) -> bool:
    """glibc: serve every allocation of ``threshold`` bytes or more with its own mmap, unmapped
    when freed. Returns whether the setting took (False elsewhere).

    By default glibc raises that threshold (up to 32 MB) after the first large free; from then on
    each replay's arrays come from heap arenas, whose pages are kept after the arrays die, and a
    server's RSS creeps up with every tab's replays.
    """
    return _mallopt(_M_MMAP_THRESHOLD, threshold)


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """glibc: at most ``arenas`` malloc arenas for the threads started from now on (``MALLOC_ARENAS``
    says why). Returns whether the setting took (False elsewhere)."""
    return _mallopt(_M_ARENA_MAX, arenas)


def tune_process() -> None:
    """Process-wide settings for serving many tabs: called by ``serve`` (and the benchmarks that
    measure a served designer), never on import or by constructing a server.

    One decode is a small, GIL-bound graph (~5 ms): intra-op threads do not speed it up, and with
    several tabs decoding at once their OpenMP teams only compete for the cores. A thread that waits
    for the GIL forces the holder to let go after the switch interval: with many busy threads (tabs
    drawing, the websocket loop) a decode's every numpy/torch call would otherwise wait up to the
    default 5 ms to get it back.
    """
    torch.set_num_threads(DECODE_THREADS)
    limit_malloc_arenas()
    return_freed_buffers_to_the_os()
    sys.setswitchinterval(SWITCH_INTERVAL_S)


def freeze_started() -> None:
    """Leave every object alive now (the checkpoints, torch, viser, the server itself) out of Python's
    cyclic garbage collection: called by ``serve`` (and the benchmarks that measure a served
    designer) once the server is built.

    Why: a full collection walks every tracked object holding the GIL, so every thread of the server
    stops for it. With ~265,000 objects from the start it took 104-129 ms; one ran as 8 tabs joined,
    and in 10-minute 8-client runs one more in the fourth minute (that minute's decoded view p95
    106-283 ms against 20-34 in the others). With them frozen, 1-9 ms (docs/load.md).
    """
    gc.collect()
    gc.freeze()


def check_bindable(host: str, port: int = 0) -> None:
    """An OSError naming ``host`` (or ``port``) unless a TCP server can bind to it on this machine.

    Why: viser (1.1) binds in a background thread and, on any OSError, tries the next port, forever
    when the host itself is wrong (a typo, another machine's address), while its constructor waits
    for that thread: ``serve --host 999.1.1.1`` hung without a word, and ``serve --port 18123`` on a
    busy port silently served on 18124 (a user's bookmark then opens somebody else's server).
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise OSError(f"--host {host}: not a host name or address ({exc.strerror})") from None
    try:
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise OSError(f"--host {host}: cannot serve on it here ({exc.strerror})") from None
    if port:
        try:
            with socket.socket(family, kind, proto) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a server binds: a
                probe.bind((address[0], port, *address[2:]))  # closed server's lingering port is free
        except OSError as exc:
            raise OSError(
                f"--port {port}: {exc.strerror.lower()} on {host} (another server?); choose another "
                "port, or --port 0 for any free one"
            ) from None


def _refuse_upload(client: viser.ClientHandle, filename: str, size: int) -> None:
    client.add_notification(
        f"Import CSV: {filename[:80]} rejected",
        f"file is {size / 2**20:.1f} MiB; a gait CSV is at most {MAX_BYTES // 2**20} MiB. The current gait stays.",
        color="red",
        auto_close_seconds=15.0,
    )


def load_families(
    checkpoint: str | Path | tuple[str | Path, ...] | None, families: dict[str, str | Path] | None = None
) -> tuple[dict[str, GaitModel], str]:
    """The models a designer offers by family name, and the name of ``checkpoint``'s.

    ``families`` (name -> checkpoint) if given, ``checkpoint`` then naming one of them (default: the
    first); else every shipped checkpoint (``model.checkpoint.SHIPPED``) and ``checkpoint`` itself
    where it is a directory of its own, under its folder's name (a built robot's ``runs/NAME/model``:
    under NAME). Several checkpoints (a tuple, ``serve --checkpoint A --checkpoint B``): each is
    offered, the first is the one returned.
    """
    if families is not None:
        models = {name: load_pretrained(path) for name, path in families.items()}
        default = str(checkpoint) if checkpoint is not None else next(iter(models))
        if default not in models:
            raise CheckpointError(f"checkpoint {checkpoint}: not one of the families {list(models)}")
        return models, default
    models = {name: load_pretrained(path) for name, path in SHIPPED.items()}
    names = []
    for c in (checkpoint if isinstance(checkpoint, tuple) else (checkpoint,)) or (None,):
        wanted = resolve_checkpoint(c)
        shipped = next((n for n, path in SHIPPED.items() if path.resolve() == wanted.resolve()), None)
        if shipped is not None:
            names.append(shipped)
            continue
        label = wanted.parent.name if wanted.name == "model" and wanted.parent.name else wanted.name
        name = label if label not in models else f"{label} (directory)"
        models[name] = load_pretrained(wanted)
        names.append(name)
    return models, names[0]


class DesignerServer:
    """The viser server with one ``DesignerClient`` per connected tab."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        checkpoint: str | Path | tuple[str | Path, ...] | None = None,
        ensemble: int = ENSEMBLE_SIZE,
        workers: int | None = None,
        verbose: bool = True,
        families: dict[str, str | Path] | None = None,
        robot: Robot | None = None,
        variations: bool = True,
        closed_loop: bool = True,
        world: World | None = None,
    ) -> None:
        check_bindable(host, port)
        self.variations, self.closed_loop = variations, closed_loop
        self.models, default = load_families(checkpoint, families)
        self.model = self.models[default]
        """The model a new tab starts with (``checkpoint``'s); ``models``: all its Gait family dropdown offers."""
        self.ensemble = ensemble
        self.workers = workers
        # Every tab's replays and ensembles take fair turns on one pool of physics threads, one a
        # core, below the decoding and drawing threads (``sim.physics.scheduler``: every tab's replay before
        # any tab's ensemble, round robin between tabs, superseded work dropped unrun).
        threads = resolve_workers(workers)
        self.physics = FairPhysics(
            threads,
            PHYSICS_NICE,
            first_threads=FIRST_MOTION_THREADS_PER_CORE * threads,
            first_nice=FIRST_MOTION_NICE,
        )
        self.decoding = DecodePool(
            [m.path for m in self.models.values() if m.path is not None],
            torch.get_num_threads(),
            DECODE_PROCESSES,
            self._error,
        )
        """Every tab's decodes, in turns, in child processes (``app.server.decode_process``)."""
        # The robot, its command rule and checks (rollouts go to physics): every tab replays on it
        # (default: the robot the first checkpoint was trained on; a family of another robot's
        # replays on its own, ``GaitSession.use_model``).
        if robot is not None and robot.n_joints != self.model.robot.n_joints:
            raise CheckpointError(
                f"--robot {robot.name} has {robot.n_joints} joints, the checkpoint's robot "
                f"{self.model.robot.name} {self.model.robot.n_joints}: give a description of that robot"
            )
        self.simulator = Simulator(1, robot=robot or self.model.robot, world=world)
        self.robot = self.simulator.robot
        self.clients: dict[int, DesignerClient] = {}
        self.errors: list[str] = []
        """Every exception a tab's callbacks or workers raised (each also printed); bench load counts them."""
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=host, port=port, label="snakeloco", verbose=verbose)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        refuse_large_uploads(self.server, MAX_BYTES, _refuse_upload)
        share_prop_hints()

    @property
    def port(self) -> int:
        return self.server.get_port()

    def _error(self, message: str) -> None:
        with self._lock:
            self.errors.append(message)
            del self.errors[:-1000]

    def _connect(self, client: viser.ClientHandle) -> None:
        try:
            designer = DesignerClient(
                client,
                self.model,
                self.ensemble,
                self.workers,
                on_error=self._error,
                simulator=self.simulator,
                models=self.models,
                physics=self.physics,
                decoding=self.decoding,
                variations=self.variations,
                closed_loop=self.closed_loop,
            )
        except Exception as exc:  # a tab that could not be set up must not take the server down
            traceback.print_exc()
            self._error(f"client {client.client_id}: setup failed: {type(exc).__name__}: {exc}")
            return
        with self._lock:
            self.clients[client.client_id] = designer

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            designer = self.clients.pop(client.client_id, None)
        if designer is not None:
            designer.close()

    def stop(self) -> None:
        with self._lock:
            designers = list(self.clients.values())
            self.clients.clear()
        for d in designers:
            d.close()
        self.decoding.close()
        self.simulator.close()
        self.physics.close()
        self.server.stop()


def serve(
    host: str = "127.0.0.1",
    port: int = 8080,
    checkpoint: str | Path | tuple[str | Path, ...] | None = None,
    ensemble: int = ENSEMBLE_SIZE,
    robot: Robot | None = None,
    variations: bool = True,
    closed_loop: bool = True,
    world: World | None = None,
) -> None:
    """Run the designer until Ctrl-C or SIGTERM; then stop cleanly (port freed, threads joined);
    ``robot``: the robot every replay runs on (default: the first checkpoint's); ``variations``: replay each
    gait on the default physics variations (the Variations fan); ``closed_loop``: and with its steering
    loop (the closed-loop fan), where the tab's Closed loop box stays ticked; ``world``: the ground every tab
    starts on (default: the flat plane; each tab's World dropdown offers the shipped worlds too)."""
    tune_process()
    app = DesignerServer(
        host,
        port,
        checkpoint,
        ensemble,
        robot=robot,
        variations=variations,
        closed_loop=closed_loop,
        world=world,
    )
    freeze_started()
    stop = threading.Event()

    def _stop(signum, _frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    warning = app.model.robot_warning(app.robot)
    if warning:
        print(f"snakeloco: warning: {warning}", file=sys.stderr)
    print(f"snakeloco designer on http://{host}:{app.port} (no authentication: keep it on a trusted network)")
    try:
        # Not a bare wait(): the kernel hands a process's signal to any of its threads (a rollout's,
        # viser's event loop), and Python runs the handler only when the main thread next runs
        # bytecode, which a lock wait without a timeout never does (measured: 3 of 5 SIGTERMs were
        # never acted on while a tab's ensemble ran).
        while not stop.wait(timeout=0.2):
            pass
    finally:
        app.stop()
