"""Issue 70, point 0: the snake's anisotropic friction off MuJoCo's plane (sim/physics/anisotropy_probe.py)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from snakeloco.sim.physics.anisotropy_probe import GROUNDS, ground_model, realign, replay_end, staged_step
from snakeloco.sim.robot.description import DEFAULT_ROBOT, FLOOR

ALONG, ACROSS = 0.15, 0.6


def _capsule_on(ground: str) -> mujoco.MjModel:
    """One capsule (axis x, free to slide, not to turn) lying on ``ground`` with the robot's pair friction (along, across)."""
    spec = mujoco.MjSpec()
    spec.option.timestep = 0.0025
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICIT
    world = spec.worldbody
    floor = world.add_geom(name=FLOOR, contype=2, conaffinity=2)
    if ground == "plane":
        floor.type, floor.size = mujoco.mjtGeom.mjGEOM_PLANE, [0, 0, 0.1]
    elif ground == "hfield":
        field = spec.add_hfield(name="ground", size=[5, 5, 0.1, 0.1], nrow=17, ncol=17)
        field.userdata = np.zeros(17 * 17)
        floor.type, floor.hfieldname = mujoco.mjtGeom.mjGEOM_HFIELD, "ground"
    else:
        floor.type, floor.size, floor.pos = mujoco.mjtGeom.mjGEOM_BOX, [5, 5, 0.1], [0, 0, -0.1]
    body = world.add_body(name="link", pos=[0, 0, 0.03])
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1]):  # it slides but cannot roll (as a link between joints)
        body.add_joint(type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis)
    body.add_geom(
        name="link",
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        size=[0.03, 0, 0],
        fromto=[-0.1, 0, 0, 0.1, 0, 0],
        mass=1.0,
    )
    spec.add_pair(geomname1=FLOOR, geomname2="link", condim=3, friction=[ALONG, ACROSS, 0.005, 1e-4, 1e-4])
    return spec.compile()


def _slide(ground: str, direction: int, staged: bool) -> float:
    """How far the capsule slides in 1 s under a horizontal push of 0.35 m g along its axis (0) or
    across it (1): between the two frictions, so it slides along and holds across."""
    model = _capsule_on(ground)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    floor = model.geom(FLOOR).id
    for _ in range(100):  # settle
        mujoco.mj_step(model, data)
    start = data.qpos[:2].copy()
    push = np.zeros(6)
    push[direction] = 0.35 * 9.81
    for _ in range(400):
        data.xfrc_applied[1] = push
        if staged:
            staged_step(model, data, floor)
        else:
            mujoco.mj_step(model, data)
    return float(np.linalg.norm(data.qpos[:2] - start))


@pytest.mark.parametrize("ground", GROUNDS)
def test_a_link_pushed_along_slides_and_across_holds_on_every_ground_once_realigned(ground):
    along, across = _slide(ground, 0, staged=True), _slide(ground, 1, staged=True)
    assert along > 0.3 and across < 0.005, (ground, along, across)


def test_without_realigning_a_heightfield_loses_the_anisotropy():
    """The measurement that asks for the re-alignment: on a flat heightfield MuJoCo's own frame puts
    "along" on an arbitrary tangent, and the push across the link slides it as the plane never does."""
    assert _slide("plane", 1, staged=False) < 0.005
    for ground in ("hfield", "box"):  # measured: the two tangents swapped, 0.98 m across and 0 along
        assert _slide(ground, 1, staged=False) > 0.3 and _slide(ground, 0, staged=False) < 0.005


def test_realigning_leaves_the_planes_frames_as_mujoco_sets_them():
    model = ground_model(DEFAULT_ROBOT, "plane")
    data = mujoco.MjData(model)
    data.qpos[2] = DEFAULT_ROBOT.link_radius - 1e-4
    mujoco.mj_forward(model, data)
    before = data.contact.frame[: data.ncon].copy()
    assert realign(model, data, model.geom(FLOOR).id) == data.ncon > 0
    np.testing.assert_allclose(data.contact.frame[: data.ncon], before, atol=1e-12)


@pytest.mark.slow
def test_the_library_undulation_on_a_flat_heightfield_goes_where_it_goes_on_the_plane():
    from snakeloco.sim.gaits.library import PRESETS

    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)[:400]  # 20 s
    plane, _ = replay_end(ground_model(DEFAULT_ROBOT, "plane"), commands, staged=False)
    field, _ = replay_end(ground_model(DEFAULT_ROBOT, "hfield"), commands, staged=True)
    # Measured 10.9% (0.77 m of 7.06 m; 100% without the re-alignment): the heightfield's prisms touch a
    # link where the plane does not. Issue 70 asks for 5%: not met yet (docs/terrain.md).
    assert np.linalg.norm(field - plane) <= 0.15 * np.linalg.norm(plane), (plane, field)
