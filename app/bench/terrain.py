"""``snakeloco bench terrain``: what a world costs (docs/terrain.md), measured side by side in one run.

- A replay of the library undulation on each world against the same replay on the flat plane (the
  plane goes to MuJoCo's own rollout; a world with rough ground or steps re-aligns its contacts,
  ``sim.physics.ground_contact``), natively and, for rough ground, with the numpy step a machine
  without a C compiler falls back to. Best of ``repeats``, flat and world interleaved.
- The designer's first view: a server started on the flat plane and on rough ground, one headless
  client each, from its connection to the tab's first decoded view and first replay.
"""

from __future__ import annotations

import time

from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics import ground_contact
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.world.description import DEFAULT_WORLD, load_world

WORLDS = ("rough", "steps", "pegs", "slope10")


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _replay_costs(repeats: int) -> dict:
    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)
    flat = Simulator(1)
    flat.replay(commands)  # warm: the first call pays for allocations
    out: dict = {}
    for name in WORLDS:
        on = Simulator(1, world=load_world(name))
        on.replay(commands)  # and the first world's, for the native step's build
        flat_s = world_s = float("inf")
        for _ in range(repeats):
            flat_s = min(flat_s, _best(lambda: flat.replay(commands), 1))
            world_s = min(world_s, _best(lambda on=on: on.replay(commands), 1))
        out[name] = {"flat_s": flat_s, "world_s": world_s, "ratio": world_s / flat_s}
    native = ground_contact.native
    try:
        ground_contact.native = lambda: None  # the fallback a machine without a compiler runs
        on = Simulator(1, world=load_world("rough"))
        numpy_s = _best(lambda: on.replay(commands), 1)
    finally:
        ground_contact.native = native
    out["rough_numpy"] = {"world_s": numpy_s, "ratio": numpy_s / out["rough"]["flat_s"]}
    out["native"] = native() is not None
    return out


def _first_view(checkpoint, world) -> dict:
    from snakeloco.app.bench.users.headless import HeadlessClient
    from snakeloco.app.server.lifecycle import DesignerServer

    server = DesignerServer(
        port=0,
        checkpoint=checkpoint,
        ensemble=2,
        verbose=False,
        variations=False,
        closed_loop=False,
        world=world,
    )
    try:
        t0 = time.perf_counter()
        client = HeadlessClient(server.port)
        try:
            while not server.clients:
                if time.perf_counter() - t0 > 120:
                    raise TimeoutError("the designer never registered the client")
                time.sleep(0.01)
            designer = next(iter(server.clients.values()))
            designer.wait_idle(120)
            first = designer.timings[0]
            return {"decoded_s": first.decoded - t0, "replayed_s": first.replayed - t0}
        finally:
            client.close()
    finally:
        server.stop()


def bench_terrain(checkpoint=None, repeats: int = 3, designer: bool = True) -> dict:
    """The figures above as a dict: per world ``flat_s``, ``world_s``, ``ratio``; ``rough_numpy``; and with
    ``designer`` ``first_view`` per ground (``decoded_s``, ``replayed_s`` from the connection)."""
    out = {"replay": _replay_costs(repeats)}
    if designer:
        out["first_view"] = {
            "flat": _first_view(checkpoint, DEFAULT_WORLD),
            "rough": _first_view(checkpoint, load_world("rough")),
        }
    return out
