"""One designer's gait pipeline, free of any UI: latents -> decode -> commands -> replay -> figures.

``GaitSession`` is what each browser tab owns; the viser layer (``tab.py``) only draws its
results. ``LatestWorker`` runs a session's jobs on one thread, coalescing bursts of requests so
that only the newest is computed (latest wins).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from snakeloco.model.api import GaitModel
from snakeloco.sim import BODY_DOWNSAMPLE, BODY_RATE, SimulationError, joint_shape
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.physics.results import StreamedReplay
from snakeloco.sim.physics.scheduler import FairPhysics, OnTurns, Turn
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.physics.threads import resolve_workers
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE, compare, perturbed_commands
from snakeloco.sim.world.description import World

ZkMode = Literal["zero", "sampled"]


@dataclass(frozen=True)
class Latents:
    """What a designer set: z_B, how z_1..8 are chosen, and the seed/temperature of a sampled draw.

    ``component`` and ``axes``: where the sliders sit when they move within a component of the
    checkpoint's density (``model.heads.density``): that component and the slider values (standard
    deviations along its principal axes) that give ``z_b``; None where the sliders are z_B itself."""

    z_b: tuple[float, ...]
    zk_mode: ZkMode = "zero"
    seed: int = 0
    temperature: float = 1.0
    component: int | None = None
    axes: tuple[float, ...] | None = None

    @property
    def sliders(self) -> tuple[float, ...]:
        """The slider values these latents were read from: ``axes``, or z_B itself."""
        return self.axes if self.axes is not None else self.z_b


@dataclass
class DecodedGait:
    """The model's view of a gait: shape (n_joints, L, 2) rad, body_ds (500, 6), commands (2000, 8) rad."""

    latents: Latents | None
    shape: np.ndarray
    body_ds: np.ndarray
    commands: np.ndarray
    decode_ms: float = 0.0
    source: str = "model"  # or "import: <name>"
    stats: dict[str, float] | None = None  # the model's predicted body statistics (model.stats);
    # None from a decode of an exact member: predicted when scored (``GaitSession.decoded_stats``)
    member: Member | None = None  # the exact family member replayed (checkpoints that project)
    residual: float | None = None  # the projection's relative residual
    off_data: bool = False  # z_B lies where the checkpoint's density says records are not
    no_model: str = ""  # why a loaded gait (a file, a library gait) has no model path, in words


@dataclass
class SimulatedGait:
    """Physics' view: the replay, its ensemble, the re-measured shape and the consistency figures."""

    joint_angles: np.ndarray  # (2000, 8) rad
    body: np.ndarray  # (2000, 6)
    qpos: np.ndarray  # (2000, nq)
    shape: np.ndarray  # (n_joints, L, 2) re-measured from joint_angles
    ensemble_body: np.ndarray  # (K, 2000, 6); member 0 is the replay itself
    figures: dict[str, float] = field(default_factory=dict)
    replay_ms: float = 0.0
    ensemble_ms: float = 0.0
    error: str | None = None


@dataclass(slots=True)
class Timing:
    """When each stage of one request finished (perf_counter seconds), for ``bench app``. Slots: a
    tab keeps its last ``TIMINGS_KEPT`` (``app.designer.tab``), and each would otherwise carry a ``__dict__``."""

    version: int
    submitted: float
    started: float = float("nan")  # the decode worker picked the request up
    decoded: float = float("nan")
    first_chunk: float = float("nan")  # the replay's first chunk was simulated (its draw begins)
    first_motion: float = float("nan")  # the first streamed chunk of the replay was drawn
    replayed: float = float("nan")
    ensembled: float = float("nan")
    decode_ms: float = float("nan")
    replay_ms: float = float("nan")
    ensemble_ms: float = float("nan")
    failed: str | None = None


def decode_latents(model: GaitModel, latents: Latents) -> DecodedGait:
    """Decode latents to a joint shape, a body path and resynthesised commands (on a checkpoint that
    projects, exactly the nearest family member's); what a tab's decode stage runs, in the server or
    in its decode process (``app.server.decode_process``)."""
    t0 = time.perf_counter()
    z_b = np.asarray(latents.z_b, dtype=np.float64)[None]
    z_j = None  # z_k = 0: decode's own zeros
    if latents.zk_mode == "sampled":
        z_j = model.joint_latents(z_b, latents.temperature, seed=latents.seed)
    member, residual, stats = None, None, None
    if model.projects:
        # The statistics are scored only once the ensemble is in (``GaitSession.decoded_stats``):
        # predicting them here was a quarter of the decode every slider move waits for.
        members, residuals, shape, body, _ = model.decode_members(z_b, z_j, with_stats=False)
        member, residual = members[0], float(residuals[0])
        commands = member.commands(model.robot)  # exactly the member: replayed, drawn and exported
    else:
        shape, body, predicted = model.decode_with_stats(z_b, z_j)
        stats = {k: float(v[0]) for k, v in predicted.items()}
        commands = model.commands(shape[0])
    return DecodedGait(
        latents,
        shape[0],
        body[0],
        commands,
        1e3 * (time.perf_counter() - t0),
        stats=stats,
        member=member,
        residual=residual,
        off_data=bool(model.off_data(z_b)[0]),
    )


class GaitSession:
    """Per-client pipeline state. Not thread-safe on its own: drive it from one ``LatestWorker``."""

    def __init__(
        self,
        model: GaitModel,
        ensemble: int = ENSEMBLE_SIZE,
        workers: int | None = None,
        physics_nice: int = 0,
        simulator: Simulator | None = None,
        physics: FairPhysics | None = None,
        tab: Hashable = None,
    ) -> None:
        self.model = model
        self.ensemble = ensemble
        # ``physics``: where replays and ensembles run, in fair turns (``sim.physics.scheduler``): a server's
        # one pool shared by every tab (``tab`` names this one), so the physics of N tabs uses the
        # cores once, not N times over. Else a pool of the session's own (``workers`` threads,
        # ``physics_nice`` below the caller). ``simulator``: the robot, command rule and checks
        # those rollouts use (a server shares one); the caller closes what it passed in.
        self._owned = []
        if simulator is None:
            simulator = Simulator(workers=1)
            self._owned.append(simulator)
        if physics is None:
            physics = FairPhysics(resolve_workers(workers), nice=physics_nice)
            self._owned.append(physics)
        self._simulator, self.physics, self.tab = simulator, physics, tab
        self._nominal = self._server = simulator
        self._robot_simulators: dict[tuple[Robot, World], Simulator] = {}
        self._world = simulator.world  # the ground this tab replays on (its World dropdown)

    @property
    def robot(self) -> Robot:
        """The robot this session replays on (its simulator's description)."""
        return self._simulator.robot

    @property
    def nominal_robot(self) -> Robot:
        """The robot the session started on (the server's)."""
        return self._nominal.robot

    @property
    def world(self) -> World:
        """The ground this session replays on (``sim.world``)."""
        return self._world

    @property
    def replay_model(self):
        """The compiled MuJoCo model this session's replays run on (its robot on its world)."""
        return self._simulator.model

    def set_robot(self, robot: Robot) -> None:
        """Replay from now on on ``robot`` (a fitted robot; the nominal one to go back). Its simulator
        is the session's own, kept while the session lives (a tab offers a few)."""
        self._simulator = self._simulator_of(robot)

    def set_world(self, world: World) -> None:
        """Replay from now on on ``world`` (the robot stays); its simulator is kept as ``set_robot``'s."""
        self._world = world
        self._simulator = self._simulator_of(self._simulator.robot)

    def _simulator_of(self, robot: Robot, world: World | None = None) -> Simulator:
        world = self._world if world is None else world
        if robot == self._nominal.robot and world == self._nominal.world:
            return self._nominal
        simulator = self._robot_simulators.get((robot, world))
        if simulator is None:
            simulator = Simulator(workers=1, robot=robot, world=world)
            self._robot_simulators[robot, world] = simulator
            self._owned.append(simulator)
        return simulator

    def simulator_on(self, world: World, turn: Turn, wanted: Callable[[], bool] | None = None) -> OnTurns:
        """``simulator_for(turn, wanted)`` with this session's robot on ``world`` (kept, as ``set_world``'s):
        the terrain fan's replays."""
        return OnTurns(
            self._simulator_of(self._simulator.robot, world), self.physics.runner(self.tab, turn, wanted)
        )

    def use_model(self, model: GaitModel) -> bool:
        """Design with ``model`` from now on, replaying on the server's robot (``serve --robot``, or
        the first checkpoint's) where it has the model's joints, else on the robot the model was
        trained on, which becomes the session's nominal robot. Returns whether the robot changed."""
        self.model = model
        server_robot = self._server.robot
        same_joints = (server_robot.n_joints, server_robot.joint_pattern) == (
            model.robot.n_joints,
            model.robot.joint_pattern,
        )
        robot = server_robot if same_joints else model.robot
        if robot == self._nominal.robot:
            return False
        if robot == self._server.robot and self._world == self._server.world:
            self._nominal = self._server
        else:
            self._nominal = self._simulator_of(robot)
        self._simulator = self._nominal
        return True

    @property
    def simulator(self) -> OnTurns:
        """The session's ensemble simulator (its batches in this tab's ensemble turns)."""
        return self.simulator_for(Turn.ENSEMBLE)

    def simulator_for(
        self, turn: Turn, wanted: Callable[[], bool] | None = None, raises: bool = False
    ) -> OnTurns:
        """A simulator whose batches run on the physics pool as this tab's ``turn`` (each row dropped
        unrun once ``wanted`` says no; the batch is then None, or with ``raises`` ``Dropped`` raised)."""
        return OnTurns(self._simulator, self.physics.runner(self.tab, turn, wanted), raises)

    def close(self) -> None:
        """Stop the threads this session owns."""
        for owned in self._owned:
            owned.close()

    def decode(self, latents: Latents) -> DecodedGait:
        """Decode latents to a joint shape, a body path and resynthesised commands."""
        return decode_latents(self.model, latents)

    def replay(self, gait: DecodedGait) -> SimulatedGait:
        """Replay the commands whole (a settled replay's turns); raises SimulationError if physics
        breaks."""
        t0 = time.perf_counter()
        return self._simulated(self.simulator_for(Turn.SETTLED).replay(gait.commands), t0)

    def _simulated(self, result, t0: float) -> SimulatedGait:
        """A whole replay (``ReplayResult`` or the last ``StreamedReplay``) begun at ``t0``."""
        return SimulatedGait(
            joint_angles=result.joint_angles,
            body=result.body,
            qpos=result.qpos,
            shape=joint_shape(result.joint_angles, self._simulator.excitation),
            ensemble_body=result.body[None],
            replay_ms=1e3 * (time.perf_counter() - t0),
        )

    def replay_streamed(
        self,
        gait: DecodedGait,
        on_part: Callable[[StreamedReplay], bool],
        settled: Callable[[], bool] | None = None,
        wanted: Callable[[], bool] | None = None,
        held_at: float | None = None,
    ) -> SimulatedGait | None:
        """``replay`` in chunks (``Simulator.stream``): ``on_part`` gets what is simulated so far after
        each chunk and returns whether to go on. Returns the same SimulatedGait as ``replay`` (bit for
        bit), or None where ``on_part`` stopped it; raises SimulationError if physics breaks.

        The chunks run on the physics pool: the first as a first motion, each later one as settled
        where ``settled()`` says the user has let go of this gait, else as dragged through, so the
        replay of a gait some tab has settled on comes before the chunks of gaits other tabs are
        still dragging through (same results whichever turn a chunk runs in). ``held_at``: when the
        value counts as held, its first motion then going before settled replays (``LANES``).
        ``wanted``: asked when a chunk's turn comes and polled while it runs; once False the replay
        ends (None)."""
        t0 = time.perf_counter()
        part = None

        def runner(k: int):
            if k == 0:
                return self.physics.runner(self.tab, Turn.FIRST_MOTION, wanted, held_at)
            settle = settled is None or settled()
            return self.physics.runner(self.tab, Turn.SETTLED if settle else Turn.DRAGGED, wanted)

        for part in self._simulator.stream(gait.commands, runner=runner, wanted=wanted):
            if part.failure is not None:
                raise SimulationError(part.failure)
            if not on_part(part):
                return None
        if part is None or not part.done:
            return None  # left mid-chunk: no longer wanted
        return self._simulated(part, t0)

    def run_ensemble(
        self,
        gait: DecodedGait,
        sim: SimulatedGait,
        seed: int = 0,
        keep_going: Callable[[np.ndarray], bool] | None = None,
        wanted: Callable[[], bool] | None = None,
    ) -> SimulatedGait | None:
        """Replay K-1 perturbed copies over all cores, a batch (one per thread) at a time, and score
        the gait. ``keep_going`` gets the ensemble's clean bodies so far (member 0 the replay) after
        each batch and returns whether to go on: None is returned where it stopped. ``wanted``: asked
        when a batch gets its turn on a shared simulator (False: stop, None). The members are those
        of one batched rollout, bit for bit."""
        t0 = time.perf_counter()
        members = perturbed_commands(gait.commands, self.ensemble, seed=seed)[1:]
        simulator = self.simulator_for(Turn.ENSEMBLE, wanted)
        step = simulator.workers  # a batch a thread
        bodies, failures = [sim.body[None]], []
        for i in range(0, len(members), step):
            result = simulator.simulate(members[i : i + step], wanted)
            if result is None:
                return None
            failures += result.failures
            bodies.append(result.body[[j for j, f in enumerate(result.failures) if f is None]])
            if keep_going is not None and not keep_going(np.concatenate(bodies)):
                return None
        ok = [i for i, f in enumerate(failures) if f is None]
        sim.ensemble_body = np.concatenate(bodies)
        sim.ensemble_ms = 1e3 * (time.perf_counter() - t0)
        decoded = gait.body_ds if gait.source == "model" else None
        ds = sim.ensemble_body[:, ::BODY_DOWNSAMPLE]
        if decoded is not None:
            sim.figures = compare(decoded, ds, BODY_RATE, self.decoded_stats(gait))
        else:
            sim.figures = compare(ds[0], ds, BODY_RATE)  # imported gait: spread only
        sim.figures["ensemble_broken"] = float(len(members) - len(ok))
        return sim

    def decoded_stats(self, gait: DecodedGait) -> dict[str, float] | None:
        """The body statistics the model predicts for a decoded gait: the decode's own, or for an
        exact member (whose decode leaves them out) those of the member's measured shape, as
        ``GaitModel.decode_members`` predicts them."""
        if gait.stats is not None or gait.member is None or not self.model.projects:
            return gait.stats
        predicted = self.model.predict_stats(self.model.members.member_shapes([gait.member]))
        return {k: float(v[0]) for k, v in predicted.items()}

    def encode_replay(self, sim: SimulatedGait) -> np.ndarray:
        """Where a replayed gait sits in z_B (posterior mean), from its measured shape and body."""
        shape, body = sim.shape[None], sim.body
        z_b, _ = self.model.encode(shape, body[None, ::BODY_DOWNSAMPLE])
        return z_b[0]


__all__ = [
    "DecodedGait",
    "GaitSession",
    "Latents",
    "SimulatedGait",
    "SimulationError",
    "Timing",
]
