"""Where simulation runs: on this machine's cores (``local``) or as Ray tasks on a cluster (``ray``).

Generation, evaluation and calibration cut their work into chunks of records (tens of replays, seconds
to a minute of physics each: Ray's own guidance is against tasks of a few milliseconds, and a task
costs about 200 us) and hand them to a backend's ``map``: ``fn(simulator, job)`` for every job, results
yielded as they finish, with their job's index. Records are independent and deterministic, so the
backend never changes a result, only where and when it is computed.

The Ray backend starts a Ray instance on this machine (``address`` None, shut down again at the end)
or joins a running cluster (``auto``, ``HOST:PORT``); each task runs one single-threaded ``Simulator``
per worker process, kept between tasks; at most ``2 x`` the cluster's CPUs tasks are in flight, so
the driver's memory stays bounded whatever the number of chunks; a task whose worker dies is retried
by Ray (``max_retries``). Ray is an optional dependency (``pip install 'snakeloco[scale]'``).
"""

from __future__ import annotations

import functools
import os
import socket
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.data.dataset import BODY_DOWNSAMPLE
from snakeloco.sim.gaits.excitation import RECORD, ExcitationConfig
from snakeloco.sim.physics.command_rule import CommandRule
from snakeloco.sim.robot.description import Robot, resolve_robot
from snakeloco.sim.world.description import DEFAULT_WORLD, World

RAY_MISSING = "--backend ray needs Ray: pip install 'snakeloco[scale]' (or pip install 'ray>=2.9')"
CONNECT_TIMEOUT_S = 10.0
"""How long joining a cluster at HOST:PORT waits for its address to answer before giving up."""
JOIN_TIMEOUT_S = 30.0
"""How long joining a cluster (``ray.init``) may take once its address answers."""
TASK_RETRIES = 3
"""Times Ray reruns a task whose worker process died (an exception raised by the task is not retried:
simulation is deterministic, it would raise again)."""


class BackendConfig(BaseModel):
    """Where simulation runs (``--backend``, ``--ray-address``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    backend: Literal["local", "ray"] = Field(
        "local", description="local: this machine's cores; ray: Ray tasks, on this machine or a cluster."
    )
    ray_address: str | None = Field(
        None,
        description="With --backend ray: a running cluster to join (auto, or HOST:PORT of its head); "
        "default: start a Ray instance on this machine for this run.",
    )


class BackendError(RuntimeError):
    """The backend cannot run the work (Ray missing, a cluster unreachable, a task lost for good)."""


Job = Any
Fn = Callable[[Any, Job], Any]  # fn(simulator, job) -> result; a module-level function (pickled by name)


def simulate_bodies(simulator, commands: np.ndarray) -> tuple[np.ndarray, list[str | None]]:
    """A job of evaluation and calibration: replay commands (B, T, n_joints); the body series at the
    model's rate (B, 500, 6) float32 and each replay's break reason (None: ran cleanly)."""
    result = simulator.simulate(commands)
    return result.body[:, ::BODY_DOWNSAMPLE].astype(np.float32), result.failures


class LocalBackend:
    """Jobs one after another on a ``Simulator`` with ``workers`` threads, in order."""

    name = "local"

    def __init__(
        self,
        workers: int | None,
        excitation: ExcitationConfig,
        sim: CommandRule,
        robot: Robot | None = None,
        world: World | None = None,
    ) -> None:
        from snakeloco.sim.physics.simulator import Simulator
        from snakeloco.sim.physics.threads import resolve_workers

        self.workers = resolve_workers(workers)
        self.simulator = Simulator(self.workers, excitation, sim, robot=robot, world=world)
        self._owned = True

    @classmethod
    def on(cls, simulator) -> LocalBackend:
        """A backend on an existing ``Simulator`` (a designer tab's); closing it leaves that running."""
        backend = cls.__new__(cls)
        backend.workers, backend.simulator, backend._owned = simulator.workers, simulator, False
        return backend

    @property
    def replays_per_job(self) -> int:
        """Replays a job should hold: enough to keep every thread busy."""
        return 4 * self.workers

    def map(self, fn: Fn, jobs: Iterable[Job]) -> Iterator[tuple[int, Any]]:
        for i, job in enumerate(jobs):
            yield i, fn(self.simulator, job)

    def close(self) -> None:
        if self._owned:
            self.simulator.close()


@functools.cache
def _worker_simulator(excitation_json: str, sim_json: str, robot_json: str, world_json: str):
    """One single-threaded simulator per Ray worker process, robot and world, made on its first task and
    kept."""
    from snakeloco.sim.physics.simulator import Simulator

    return Simulator(
        1,
        ExcitationConfig.model_validate_json(excitation_json),
        CommandRule.model_validate_json(sim_json),
        robot=Robot.model_validate_json(robot_json),
        world=World.model_validate_json(world_json),
    )


def _run_task(fn: Fn, excitation_json: str, sim_json: str, robot_json: str, world_json: str, job: Job) -> Any:
    """The body of every Ray task: ``fn`` on this worker's simulator."""
    return fn(_worker_simulator(excitation_json, sim_json, robot_json, world_json), job)


def _check_reachable(address: str) -> None:
    """Fail fast, in one line, where HOST:PORT does not answer (Ray itself would retry for minutes)."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise BackendError(f"--ray-address {address!r}: expected auto or HOST:PORT of a Ray head node")
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise BackendError(
            f"cannot reach a Ray cluster at {address} ({exc.strerror or exc}, waited up to "
            f"{CONNECT_TIMEOUT_S:.0f} s): start one with `ray start --head` or use --backend local"
        ) from exc


def _join(ray, address: str) -> None:
    """``ray.init(address)``, bounded: Ray retries a port that answers but is no Ray head for minutes."""
    outcome: list = []

    def connect() -> None:
        try:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
            outcome.append(None)
        except BaseException as exc:  # handed to the caller
            outcome.append(exc)

    thread = threading.Thread(target=connect, name="ray-join", daemon=True)
    thread.start()
    thread.join(JOIN_TIMEOUT_S)
    if not outcome:
        raise BackendError(
            f"no Ray cluster answered at {address} within {JOIN_TIMEOUT_S:.0f} s (something listens there, "
            "but not a Ray head node?)"
        )
    if outcome[0] is not None:
        exc = outcome[0]
        raise BackendError(f"cannot join the Ray cluster at {address}: {exc}".splitlines()[0]) from exc


class RayBackend:
    """Jobs as Ray tasks (one CPU each), at most ``2 x`` the cluster's CPUs in flight."""

    name = "ray"
    replays_per_job = 16
    """Replays per task: ~8 s of physics on one core, so task overhead (~200 us) stays below 0.01%."""

    def __init__(
        self,
        address: str | None,
        workers: int | None,
        excitation: ExcitationConfig,
        sim: CommandRule,
        robot: Robot | None = None,
        world: World | None = None,
    ):
        try:
            import ray
        except ImportError as exc:
            raise BackendError(RAY_MISSING) from exc
        self._ray = ray
        self._started = False
        if address not in (None, "auto"):
            _check_reachable(address)
        if ray.is_initialized():  # a caller's own Ray session: use it, leave it running
            pass
        elif address is None:
            ray.init(
                num_cpus=workers or os.cpu_count() or 1,
                include_dashboard=False,
                _node_ip_address="127.0.0.1",  # a single-machine instance talks over loopback only
                log_to_driver=False,
                configure_logging=False,
            )
            self._started = True
        else:
            _join(ray, address)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.max_in_flight = 2 * self.workers
        self._specs = (
            excitation.model_dump_json(),
            sim.model_dump_json(),
            resolve_robot(robot).model_dump_json(),
            (world or DEFAULT_WORLD).model_dump_json(),
        )
        self._task = ray.remote(_run_task).options(
            num_cpus=1, max_retries=TASK_RETRIES, retry_exceptions=False
        )

    def map(self, fn: Fn, jobs: Iterable[Job]) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        pending: dict[Any, int] = {}
        queue = iter(enumerate(jobs))
        more = True
        try:
            while True:
                while more and len(pending) < self.max_in_flight:
                    item = next(queue, None)
                    if item is None:
                        more = False
                        break
                    pending[self._task.remote(fn, *self._specs, item[1])] = item[0]
                if not pending:
                    return
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    index = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as exc:
                        raise BackendError(
                            f"chunk {index} was lost {TASK_RETRIES + 1} times (its Ray worker died each time): "
                            f"{type(exc).__name__}"
                        ) from exc
                    except ray.exceptions.RayTaskError as exc:
                        raise exc.as_instanceof_cause() from None  # the task's own error, as raised
                    yield index, result
        finally:
            for ref in pending:  # an error or Ctrl-C: stop what is still queued or running
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()


def open_backend(
    cfg: BackendConfig | None,
    workers: int | None = None,
    excitation: ExcitationConfig = RECORD,
    sim: CommandRule | None = None,
    robot: Robot | None = None,
    world: World | None = None,
) -> LocalBackend | RayBackend:
    """The backend ``cfg`` names (default local); ``workers``: local threads, or the CPUs of a Ray
    instance started here; ``robot`` on ``world``: what it replays on (default: the paper's robot on
    the plane). Close it
    (``close``) when done."""
    cfg = cfg or BackendConfig()
    sim = sim or CommandRule()
    if cfg.backend == "local":
        if cfg.ray_address is not None:
            raise BackendError("--ray-address is for --backend ray")
        return LocalBackend(workers, excitation, sim, robot, world)
    return RayBackend(cfg.ray_address, workers, excitation, sim, robot, world)
