"""``snakeloco bench terrain``: what a world costs (docs/terrain.md), measured side by side in one run.

- A replay of the library undulation on each world against the same replay on the flat plane (the
  plane goes to MuJoCo's own rollout; a world with rough ground or steps re-aligns its contacts,
  ``sim.physics.ground_contact``), natively and, for rough ground, with the numpy step a machine
  without a C compiler falls back to. Best of ``repeats``, flat and world interleaved.
- The designer's first view: a server started on the flat plane and on rough ground, one headless
  client each, from its connection to the tab's first decoded view and first replay.
- What crosses what (``library``, ``sampler``): each gait of the library, and ``gaits`` draws of the
  structured checkpoint's slider density that travel at least 2 m, over the terrain set
  (``sim.world.sets``), open loop and with its steering loop: per world whether it arrives (open
  loop: ends within ``ARRIVES_REL`` of where it ends on the flat ground; closed loop: reaches its
  path's end by the cap), its speed and its end error over the distance. Sampler rows go gait by gait
  to ``out`` (a rerun with it skips the gaits done).
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import numpy as np

from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics import ground_contact
from snakeloco.sim.physics.bench import best_time
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.world.description import DEFAULT_WORLD, load_world

WORLDS = ("rough", "steps", "pegs", "slope10")
ARRIVES_REL = 0.10
"""Open loop, a gait "arrives" on a world where it ends within 10% of its distance from its flat end."""
MIN_DISTANCE_M = 2.0
"""Sampler draws that travel less in their 100 s record are not scored (as ``bench loop``)."""


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
            flat_s = min(flat_s, best_time(lambda: flat.replay(commands), 1))
            world_s = min(world_s, best_time(lambda on=on: on.replay(commands), 1))
        out[name] = {"flat_s": flat_s, "world_s": world_s, "ratio": world_s / flat_s}
    native = ground_contact.native
    try:
        ground_contact.native = lambda: None  # the fallback a machine without a compiler runs
        on = Simulator(1, world=load_world("rough"))
        numpy_s = best_time(lambda: on.replay(commands), 1)
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


def crosses(commands, simulator) -> dict:
    """One gait over the terrain set: per world ``open`` (arrives, speed m/s, rel) and, where the gait
    steers, ``closed`` (arrives, speed over its path, rel); with its steering line and flat distance."""
    from snakeloco.sim.control.find import find_steering
    from snakeloco.sim.scores.terrain import terrain_closed_loop, terrain_robustness

    record_s = simulator.excitation.n_samples / simulator.excitation.sample_rate
    opened = terrain_robustness(commands, simulator)
    steering = find_steering(commands, simulator)
    closed = terrain_closed_loop(commands, simulator, steering) if steering.steers else None
    worlds = {}
    for i, o in enumerate(opened["variations"]):
        row = {
            "open": {
                "arrives": o["failure"] is None and o["rel"] <= ARRIVES_REL,
                "speed": None if o["failure"] else o["distance_m"] / record_s,
                "rel": o["rel"],
            }
        }
        if closed is not None:
            c = closed["variations"][i]
            row["closed"] = {
                "arrives": bool(c.get("arrived")),
                "speed": closed["distance_m"] / c["arrival_s"] if c.get("arrival_s") else None,
                "rel": c["rel"],
            }
        worlds[o["name"]] = row
    return {"distance_m": opened["nominal"]["distance_m"], "steering": steering.line(), "worlds": worlds}


def _library(simulator, log) -> dict:
    out = {}
    for name, preset in PRESETS.items():
        out[name] = crosses(preset.gait.commands(simulator.robot), simulator)
        log(f"library {name}: {out[name]['steering']}")
    return out


def _sampler(simulator, checkpoint, gaits: int, seed: int, out_path, log) -> dict:
    import json

    from snakeloco.app.bench.loop import travelling_draws
    from snakeloco.model import load_pretrained

    model = load_pretrained(checkpoint or "structured")
    rows = json.loads(out_path.read_text())["rows"] if out_path is not None and out_path.exists() else []
    members, commands, _, travels = travelling_draws(model, simulator, gaits, seed, MIN_DISTANCE_M)
    seen = {r["draw"] for r in rows}
    for index in travels:
        if index in seen:
            continue
        t0 = time.perf_counter()
        row = {"draw": index, "kind": members[index].kind, **crosses(commands[index], simulator)}
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
        log(
            f"sampler {len(rows)}/{len(travels)}: draw {index} {row['kind']} {row['distance_m']:.1f} m, {row['steering']}"
        )
        if out_path is not None:
            out_path.write_text(json.dumps({"rows": rows}))
    return {"gaits": len(rows), "per_world": per_world(rows), "rows": rows}


def per_world(rows: list[dict]) -> dict:
    """Over gaits' ``crosses`` rows: per world the share that arrives open and closed loop, and the
    closed loop's median end error over the distance (the gaits that steer)."""
    out = {}
    for name in rows[0]["worlds"] if rows else ():
        opened = [r["worlds"][name]["open"] for r in rows]
        closed = [r["worlds"][name]["closed"] for r in rows if "closed" in r["worlds"][name]]
        rels = [c["rel"] for c in closed if c["rel"] is not None]
        out[name] = {
            "open_arrives": sum(o["arrives"] for o in opened),
            "closed_arrives": sum(c["arrives"] for c in closed),
            "steered": len(closed),
            "closed_rel_median": float(np.median(rels)) if rels else None,
        }
    return out


def bench_terrain(
    checkpoint=None,
    repeats: int = 3,
    sections: tuple[str, ...] = ("replay", "designer"),
    gaits: int = 64,
    seed: int = 0,
    workers: int | None = None,
    out: Path | None = None,
) -> dict:
    """The figures above as a dict: ``replay`` per world (``flat_s``, ``world_s``, ``ratio``, and
    ``rough_numpy``); ``first_view`` per ground (``decoded_s``, ``replayed_s`` from the connection);
    ``library`` per gait and ``sampler`` (``crosses`` rows and ``per_world``)."""
    result: dict = {}
    if "replay" in sections:
        result["replay"] = _replay_costs(repeats)
    if "designer" in sections:
        result["first_view"] = {
            "flat": _first_view(checkpoint, DEFAULT_WORLD),
            "rough": _first_view(checkpoint, load_world("rough")),
        }
    if "library" in sections or "sampler" in sections:
        simulator = Simulator(workers)
        log = functools.partial(print, file=sys.stderr, flush=True)
        try:
            if "library" in sections:
                result["library"] = _library(simulator, log)
                result["library_per_world"] = per_world(list(result["library"].values()))
            if "sampler" in sections:
                result["sampler"] = _sampler(simulator, checkpoint, gaits, seed, out, log)
        finally:
            simulator.close()
    return result
