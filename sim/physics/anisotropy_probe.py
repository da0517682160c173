"""Measurement behind issue 70's first decision: does the snake's anisotropic floor friction survive off
MuJoCo's plane, and what would re-aligning the contact frames cost?

The robot's floor pairs give friction (along, across) on the contact frame's two tangent axes. Only the
capsule-plane collider orients that frame along the capsule (MuJoCo issue #67); on a heightfield or a box
the tangents follow from the normal alone, so "along" lands on an arbitrary direction. This module
replays one gait, open loop, on the same robot over three grounds (the plane, a flat heightfield, a flat
box), each stepped either by ``mj_step`` or by the staged step of ``sim.physics.ground_contact``, which
rewrites every floor contact's frame along its link before the constraints are built. It reports where
each replay ends and what a replay costs.

``python -m snakeloco.sim.physics.anisotropy_probe [GAIT ...]`` prints the table docs/terrain.md shows.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics import ground_contact
from snakeloco.sim.physics.command_rule import CommandRule, expand_commands
from snakeloco.sim.robot.description import BODY_SITE, DEFAULT_ROBOT, FLOOR, Robot

GROUNDS = ("plane", "hfield", "box")
HFIELD_HALF_M = 40.0
"""Half the side of the flat heightfield and the box (m): wider than any gait's 100 s path."""


def ground_model(robot: Robot, ground: str) -> mujoco.MjModel:
    """``robot`` on ``ground``: its plane, or a flat heightfield or box whose top is the plane z = 0,
    with the robot's own anisotropic floor pairs."""
    spec = robot.build_spec()
    if ground == "plane":
        return spec.compile()
    floor = spec.geom(FLOOR)
    if ground == "hfield":
        field = spec.add_hfield(
            name="ground", size=[HFIELD_HALF_M, HFIELD_HALF_M, 0.1, 0.1], nrow=65, ncol=65
        )
        field.userdata = np.zeros(65 * 65)  # flat: its top is z = 0
        floor.type = mujoco.mjtGeom.mjGEOM_HFIELD
        floor.hfieldname = "ground"
        floor.pos = [0, 0, 0]
    else:
        floor.type = mujoco.mjtGeom.mjGEOM_BOX
        floor.size = [HFIELD_HALF_M, HFIELD_HALF_M, 0.1]
        floor.pos = [0, 0, -0.1]
    return spec.compile()


def ground_flags(model: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) uint8: 1 on the plane and on a world's ground geoms (``sim.world``: ``ground_*``, pegs
    aside): the contacts the probe re-aligns (the plane's too, to show it changes nothing)."""
    flags = np.zeros(model.ngeom, dtype=np.uint8)
    for i in range(model.ngeom):
        name = model.geom(i).name
        flags[i] = name == FLOOR or (name.startswith("ground_") and "peg" not in name)
    return flags


def replay_end(model: mujoco.MjModel, commands: np.ndarray, staged: bool) -> tuple[np.ndarray, float]:
    """Where the body site ends (x, y m) after ``commands`` (T, J), and the seconds the replay took."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    substeps = round(1.0 / (20.0 * model.opt.timestep))
    targets = expand_commands(commands[None], substeps, CommandRule())[0]
    site = model.site(BODY_SITE).id
    flags = ground_flags(model)
    start = data.site_xpos[site][:2].copy()
    t0 = time.perf_counter()
    for u in targets:
        data.ctrl[:] = u
        if staged:
            ground_contact.step(model, data, flags)
        else:
            mujoco.mj_step(model, data)
    return data.site_xpos[site][:2] - start, time.perf_counter() - t0


def on_worlds(
    gaits: list[str], worlds: list[str], seconds: float, robot: Robot = DEFAULT_ROBOT
) -> list[dict]:
    """Each gait on the plane and on each shipped world (``sim/worlds``), re-aligned off the plane:
    where it ends, how far from the plane's end, and the seconds a replay took."""
    from snakeloco.sim.world.description import load_world

    rows = []
    for gait in gaits:
        commands = PRESETS[gait].gait.commands(robot)[: round(seconds * 20)]
        flat, _ = replay_end(ground_model(robot, "plane"), commands, staged=False)
        for name in worlds:
            world = load_world(name)
            end, took = replay_end(world.compile(robot), commands, staged=not world.flat)
            rows.append(
                {
                    "gait": gait,
                    "world": name,
                    "end_m": [round(float(v), 3) for v in end],
                    "distance_m": round(float(np.linalg.norm(end)), 3),
                    "plane_distance_m": round(float(np.linalg.norm(flat)), 3),
                    "off_plane_rel": round(float(np.linalg.norm(end - flat) / np.linalg.norm(flat)), 4),
                    "seconds": round(took, 2),
                }
            )
            print(rows[-1], flush=True)
    return rows


def probe(gaits: list[str], seconds: float, robot: Robot = DEFAULT_ROBOT) -> list[dict]:
    rows = []
    for gait in gaits:
        commands = PRESETS[gait].gait.commands(robot)[: round(seconds * 20)]
        reference = None
        for ground in GROUNDS:
            model = ground_model(robot, ground)
            for staged in (False, True):
                end, took = replay_end(model, commands, staged)
                if reference is None:
                    reference = end
                miss = float(np.linalg.norm(end - reference))
                rows.append(
                    {
                        "gait": gait,
                        "ground": ground,
                        "step": "staged" if staged else "mj_step",
                        "end_m": [round(float(v), 3) for v in end],
                        "distance_m": round(float(np.linalg.norm(end)), 3),
                        "off_plane_rel": round(miss / max(float(np.linalg.norm(reference)), 1e-9), 4),
                        "seconds": round(took, 2),
                    }
                )
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("gaits", nargs="*", default=["undulate", "sidewind"])
    parser.add_argument("--seconds", type=float, default=100.0, help="replay length (s)")
    parser.add_argument("--worlds", nargs="*", help="shipped worlds (or YAML files) to replay on instead")
    args = parser.parse_args()
    if args.worlds:
        on_worlds(args.gaits, args.worlds, args.seconds)
    else:
        probe(args.gaits, args.seconds)


if __name__ == "__main__":
    main()
