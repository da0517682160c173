"""How a gait fares on other ground: its replays over the terrain set (``sim.world.sets``).

Each world's row is the gait replayed there on the nominal robot, open loop or with its steering loop,
measured from where the gait ends on the flat ground (open loop: the flat replay's end; closed loop:
the end of the path it follows, its nominal path on the flat ground), as the physics variations are
measured from the nominal replay (``sim.scores.robustness``, ``sim.scores.closed_loop``). Worlds differ
in their models' sizes, so each runs on a simulator of its own, the worlds spread over ``workers``
threads (MuJoCo and the ground step release the GIL).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.scores.closed_loop import closed_loop_robustness
from snakeloco.sim.scores.robustness import flat_simulator, on_world, summarise
from snakeloco.sim.world.description import World
from snakeloco.sim.world.sets import TERRAIN_SET


@dataclass(frozen=True)
class WorldRow:
    """A world as a row of the variation tables (their ``name`` and ``params``)."""

    world: World

    @property
    def name(self) -> str:
        return self.world.name

    def params(self) -> dict:
        return self.world.model_dump(mode="json", exclude_defaults=True, exclude={"name"})


def _on_each(worlds: Sequence[World], simulator, run) -> list:
    """``run(world_simulator)`` for each world, on ``simulator.workers`` threads, in order."""
    from snakeloco.sim.physics.simulator import Simulator

    def one(world: World):
        on = Simulator(1, simulator.excitation, simulator.config, robot=simulator.robot, world=world)
        try:
            return run(on)
        finally:
            on.close()

    with ThreadPoolExecutor(max(1, simulator.workers)) as pool:
        return list(pool.map(one, worlds))


def _flat(simulator):
    return flat_simulator(simulator) if on_world(simulator) else simulator


def terrain_robustness(commands: np.ndarray, simulator, worlds: Sequence[World] = TERRAIN_SET) -> dict:
    """Open loop: ``summarise``'s report with the flat ground's replay as the nominal row and one row per
    world (``end_error_m`` / ``rel`` from the flat end; a world that breaks the replay is named)."""
    commands = np.asarray(commands, np.float64)
    flat = _flat(simulator)
    try:
        nominal = flat.replay(commands).body
    finally:
        if flat is not simulator:
            flat.close()

    def replay(on):
        result = on.simulate(commands[None])
        return result.body[0], result.failures[0]

    rows = _on_each(worlds, simulator, replay)
    report = summarise(nominal, [WorldRow(w) for w in worlds], [b for b, _ in rows], [f for _, f in rows])
    return report | {"set": "terrain", "on": "the flat ground"}


def terrain_closed_loop(
    commands: np.ndarray, simulator, steering, worlds: Sequence[World] = TERRAIN_SET, end: str = "arrive"
) -> dict:
    """Closed loop: ``closed_loop_robustness``'s report, its nominal row the loop on the flat ground and
    one row per world, every run following the gait's nominal path on the flat ground."""
    from snakeloco.sim.control.closed_loop import nominal_reference

    commands = np.asarray(commands, np.float64)
    flat = _flat(simulator)
    try:
        reference = nominal_reference(commands, flat, steering.period)
        report = closed_loop_robustness(commands, (), flat, steering, reference=reference, end=end)
    finally:
        if flat is not simulator:
            flat.close()

    def follow(on):
        try:
            return closed_loop_robustness(commands, (), on, steering, reference=reference, end=end)["nominal"]
        except SimulationError as exc:  # the world broke the run: a row that says so
            return {"forward": None, "sideways": None, "end_error_m": None, "rel": None, "failure": str(exc)}

    rows = [{"name": w.name, "params": WorldRow(w).params(), **r} for w, r in zip(worlds, _on_each(worlds, simulator, follow), strict=True)]  # fmt: skip
    scored = [r for r in rows if r["failure"] is None]
    worst = max(scored, key=lambda r: r["end_error_m"], default=None)
    report.pop("world", None)
    return report | {
        "set": "terrain",
        "variations": rows,
        "worst_end_error_m": None if worst is None else worst["end_error_m"],
        "worst_rel": None if worst is None else worst["rel"],
        "worst": None if worst is None else worst["name"],
        "broken": [r["name"] for r in rows if r["failure"] is not None],
        "late": [r["name"] for r in scored if end == "arrive" and not r.get("arrived", True)],
        "runs": [],
    }
