"""Issue 70: the snake's anisotropic friction off MuJoCo's plane (sim/physics/ground_contact.py) and the
world description (sim/world)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from snakeloco.sim.physics.anisotropy_probe import GROUNDS, ground_flags, ground_model, replay_end
from snakeloco.sim.physics.ground_contact import realign, staged_step
from snakeloco.sim.robot.description import DEFAULT_ROBOT, FLOOR
from snakeloco.sim.world.sets import TERRAIN_SET

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
    floor = ground_flags(model)
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
    assert realign(data, ground_flags(model)) == data.ncon > 0
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


# --- point 1: the world description ---------------------------------------------------------------


def test_the_default_world_leaves_the_robots_model_as_it_is():
    from snakeloco.sim.world.description import DEFAULT_WORLD

    assert DEFAULT_WORLD.mjcf(DEFAULT_ROBOT) == DEFAULT_ROBOT.mjcf()


def test_each_world_field_changes_the_model_it_names():
    from snakeloco.sim.world.description import Pegs, Rough, Steps, World

    base = World(rough=Rough(extent_m=2.0), steps=Steps(), pegs=Pegs(extent_m=1.0))
    m = base.compile(DEFAULT_ROBOT)
    rough = m.hfield_data.copy()
    for field, value in (("height_m", 0.05), ("wavelength_m", 0.6), ("seed", 3), ("resolution_m", 0.1)):
        other = base.model_copy(update={"rough": base.rough.model_copy(update={field: value})})
        o = other.compile(DEFAULT_ROBOT)
        changed = o.hfield_size[0, 2] != m.hfield_size[0, 2] or o.hfield_data.shape != rough.shape
        assert changed or not np.array_equal(o.hfield_data, rough), field
    step = lambda w, k=3: w.compile(DEFAULT_ROBOT).geom(f"ground_step{k}")  # noqa: E731
    assert step(base).size[2] == pytest.approx(3 * 0.02 / 2)  # the top step's half height
    for field, value in (("height_m", 0.04), ("depth_m", 0.8), ("start_m", 2.0), ("direction_deg", 90.0)):
        other = base.model_copy(update={"steps": base.steps.model_copy(update={field: value})})
        assert not np.allclose(
            np.r_[step(other).size, step(other).pos, step(other).quat],
            np.r_[step(base).size, step(base).pos, step(base).quat],
        ), field
    assert (
        base.model_copy(update={"steps": base.steps.model_copy(update={"count": 5})})
        .compile(DEFAULT_ROBOT)
        .geom("ground_step5")
    )
    pegs = lambda w: sorted(n for n in w.ground_geoms() if "peg" in n)  # noqa: E731
    for field, value in (("spacing_m", 0.3), ("extent_m", 1.5), ("clear_m", 0.2)):
        other = base.model_copy(update={"pegs": base.pegs.model_copy(update={field: value})})
        assert len(pegs(other)) != len(pegs(base)), field
    moved = base.model_copy(update={"pegs": base.pegs.model_copy(update={"seed": 4, "clear_m": 0.0})})
    still = base.model_copy(update={"pegs": base.pegs.model_copy(update={"clear_m": 0.0})})
    assert not np.allclose(moved.pegs.centres(), still.pegs.centres())  # the same grid, jittered anew
    tall = base.model_copy(update={"pegs": base.pegs.model_copy(update={"radius_m": 0.05, "height_m": 0.3})})
    g = tall.compile(DEFAULT_ROBOT).geom("ground_peg1")
    assert tuple(g.size[:2]) == pytest.approx((0.05, 0.15))
    tilted = World(slope_deg=10.0, slope_direction_deg=90.0).compile(DEFAULT_ROBOT)
    assert tilted.opt.gravity == pytest.approx(
        (0.0, -9.81 * np.sin(np.radians(10)), -9.81 * np.cos(np.radians(10)))
    )


def test_every_ground_geom_gets_the_robots_anisotropic_floor_pairs():
    from snakeloco.sim.world.description import load_world

    for name in ("rough", "steps"):
        world = load_world(name)
        model = world.compile(DEFAULT_ROBOT)
        grounds = {model.geom(g).id for g in world.ground_geoms()}
        pairs = [
            (int(a), int(b), tuple(f))
            for a, b, f in zip(model.pair_geom1, model.pair_geom2, model.pair_friction, strict=True)
        ]
        mine = [p for p in pairs if p[0] in grounds]
        assert len(mine) == len(grounds) * DEFAULT_ROBOT.n_links
        assert all(
            f[:2] == pytest.approx((DEFAULT_ROBOT.friction_along, DEFAULT_ROBOT.friction_across))
            for *_, f in mine
        )


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("rough:\n  height_m: -1\n", "rough.height_m: Input should be greater than 0"),
        ("pegs:\n  radius_m: 0.3\n  spacing_m: 0.4\n", "spacing_m 0.4 must exceed the peg diameter"),
        ("stepz:\n  height_m: 0.1\n", "stepz: unknown field"),
        ("- 1\n- 2\n", "a world description is a mapping"),
        ("slope_deg: 45\n", "slope_deg: Input should be less than or equal to 30"),
    ],
)
def test_a_bad_world_file_is_refused_naming_the_field(tmp_path, text, says):
    from snakeloco.sim.world.description import WorldError, load_world

    path = tmp_path / "w.yaml"
    path.write_text(text)
    with pytest.raises(WorldError, match=r"w\.yaml") as info:
        load_world(path)
    assert says in str(info.value)


def test_world_show_and_mjcf_commands(tmp_path, capsys):
    from snakeloco.app.cli.main import main

    main(["world", "show", "pegs"])
    out = capsys.readouterr().out
    assert "pegs" in out and "ground_geoms" in out
    main(["world", "mjcf", "steps", "--out", str(tmp_path / "s.xml")])
    assert "ground_step3" in (tmp_path / "s.xml").read_text()
    with pytest.raises(SystemExit):
        main(["world", "show", str(tmp_path / "missing.yaml")])
    assert "shipped worlds: pegs, rough, slope10, steps" in capsys.readouterr().err


def test_a_robots_own_slope_tilts_a_sloped_world_further():
    """A slope variation (or an old robot file's slope) replayed on a sloped world: the tilts compose."""
    from snakeloco.sim.world.description import World, load_world

    world = load_world("slope10")
    ahead = DEFAULT_ROBOT.model_copy(
        update={"slope_deg": 5.0, "slope_direction_deg": world.slope_direction_deg}
    )
    g = np.array(load_world("slope10").compile(ahead).opt.gravity)
    tilt = np.degrees(np.arccos(-g[2] / np.linalg.norm(g)))
    assert tilt == pytest.approx(15.0, abs=1e-9) and np.linalg.norm(g) == pytest.approx(9.81)
    across = DEFAULT_ROBOT.model_copy(update={"slope_deg": 5.0, "slope_direction_deg": 90.0})
    g = np.array(World(slope_deg=10.0).compile(across).opt.gravity)
    assert g[0] < 0 and g[1] < 0  # downhill -x (the world's) and -y (the robot's)
    np.testing.assert_allclose(
        World(slope_deg=10.0).compile(DEFAULT_ROBOT).opt.gravity, World(slope_deg=10.0).gravity(DEFAULT_ROBOT)
    )


# --- the staged step in the simulator: native, numpy, and the plane untouched ---------------------


def _rough_world(height: float = 0.01):
    from snakeloco.sim.world.description import Rough, World

    return World(name="rough-test", rough=Rough(height_m=height, extent_m=5.0, wavelength_m=0.3, seed=3))


def test_the_native_step_is_mujocos_step_where_nothing_is_realigned():
    """``ground_contact.c`` splits mj_step at the constraints; with no ground flagged it must be mj_step
    to the bit (the same stages in the same order)."""
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.physics import ground_contact

    lib = ground_contact.native()
    if lib is None:
        pytest.skip("no C compiler here: the numpy step is checked instead")
    model = DEFAULT_ROBOT.compile()
    a, b = mujoco.MjData(model), mujoco.MjData(model)
    none = np.zeros(model.ngeom, dtype=np.uint8)
    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)
    for t in range(800):
        a.ctrl[:] = b.ctrl[:] = commands[t // 50] * min(1.0, t / 400)
        mujoco.mj_step(model, a)
        ground_contact.step(model, b, none)
    assert a.ncon > 0
    np.testing.assert_array_equal(a.qpos, b.qpos)
    np.testing.assert_array_equal(a.sensordata, b.sensordata)


def test_the_native_and_numpy_steps_agree_on_rough_ground(monkeypatch):
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.physics import ground_contact
    from snakeloco.sim.physics.simulator import Simulator

    if ground_contact.native() is None:
        pytest.skip("no C compiler here")
    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)[None]
    native = Simulator(world=_rough_world()).simulate(commands, samples=60)
    monkeypatch.setattr(ground_contact, "native", lambda: None)
    numpy = Simulator(world=_rough_world()).simulate(commands, samples=60)
    assert native.failures == numpy.failures == [None]
    np.testing.assert_allclose(native.body, numpy.body, atol=1e-6)


def test_a_simulator_on_a_world_realigns_its_ground_and_leaves_the_plane_to_mujoco():
    from snakeloco.sim.physics import ground_contact
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.world.description import DEFAULT_WORLD, load_world

    assert ground_contact.ground_flags(Simulator(world=DEFAULT_WORLD).model) is None
    assert ground_contact.ground_flags(Simulator(world=load_world("slope10")).model) is None
    assert ground_contact.ground_flags(Simulator(world=load_world("pegs")).model) is None  # pegs: links'
    for name in ("rough", "steps"):
        model = Simulator(world=load_world(name)).model
        flags = ground_contact.ground_flags(model)
        flagged = {model.geom(int(i)).name for i in np.flatnonzero(flags)}
        assert flagged and all(n.startswith("ground_") for n in flagged), flagged


def test_a_low_rough_ground_carries_the_undulation_as_the_plane_does():
    """With the frames re-aligned, 1 mm of roughness changes an 8 s undulation's distance little; without,
    the links' anisotropy is lost and the snake barely moves (the same test fails on the unaligned step)."""
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.physics import ground_contact
    from snakeloco.sim.physics.simulator import Simulator

    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)[None]
    plane = Simulator().simulate(commands, samples=160).body[0, -1, 1:3]
    rough = Simulator(world=_rough_world(0.001)).simulate(commands, samples=160).body[0, -1, 1:3]
    assert np.linalg.norm(plane) > 1.0
    # Measured: 2.59 m on the plane, 2.51 m here (its heading drifts: the end 0.53 m from the plane's),
    # 0.33 m with MuJoCo's own frames.
    assert abs(np.linalg.norm(rough) - np.linalg.norm(plane)) <= 0.15 * np.linalg.norm(plane), (plane, rough)
    assert ground_contact.ground_flags(Simulator(world=_rough_world(0.001)).model) is not None


# --- --world on the commands ----------------------------------------------------------------------


def test_robustness_on_a_world_measures_the_nominal_from_the_flat_grounds_end(tmp_path, capsys):
    import json

    from snakeloco.app.cli.main import main

    gait = tmp_path / "undulate.csv"
    main(["gait", "undulate", "--out", str(gait)])
    one = tmp_path / "one.yaml"
    one.write_text("- name: slippery\n  scale: {friction_along: 0.5, friction_across: 0.5}\n")
    main(["robustness", str(gait), "--world", "steps", "--set", str(one), "--json"])
    out = capsys.readouterr().out
    report = json.loads(out.strip().splitlines()[-1])
    assert "on steps" in out and "on the flat ground" in out
    nominal, flat = report["nominal"], report["flat"]
    assert report["world"] == "steps" and flat["distance_m"] > 25  # measured 32.6 m on the plane
    gap = np.hypot(nominal["forward"] - flat["forward"], nominal["sideways"] - flat["sideways"])
    assert nominal["end_error_m"] == pytest.approx(gap) and gap > 0.1  # the steps change where it ends
    assert nominal["rel"] == pytest.approx(gap / flat["distance_m"], rel=1e-6)
    with pytest.raises(SystemExit):
        main(["robustness", str(gait), "--world", str(tmp_path / "nowhere.yaml")])
    assert "shipped worlds" in capsys.readouterr().err


def test_a_dataset_on_a_world_says_so_and_the_default_worlds_meta_is_unchanged():
    from snakeloco.sim import GenerateConfig
    from snakeloco.sim.world.description import load_world

    assert "world" not in GenerateConfig().to_meta()
    meta = GenerateConfig(world=load_world("rough")).to_meta()
    assert meta["world"]["rough"]["height_m"] == 0.02
    assert GenerateConfig.model_validate(meta).world == load_world("rough")


@pytest.mark.slow
def test_design_on_a_world_verifies_its_candidates_there(tmp_path, checkpoint, capsys):
    import json

    from test_design import QUICK_ARGS

    from snakeloco.app.cli.main import main
    from snakeloco.app.export.gait_csv import read_gait_csv
    from snakeloco.model.design.search import path_end
    from snakeloco.sim.data.dataset import BODY_DOWNSAMPLE
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.world.description import load_world

    out = tmp_path / "design"
    target = ["--forward", "0.5", "--sideways", "0.0", "--checkpoint", str(checkpoint), "--world", "rough"]
    main(["design", *target, *QUICK_ARGS, "--rounds", "1", "--out", str(out), "--json", "--workers", "2"])
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["world"] == "rough"
    rough, flat = Simulator(world=load_world("rough")), Simulator()

    def end(simulator, commands):
        body = simulator.replay(commands).body[::BODY_DOWNSAMPLE]
        return path_end(body.astype(np.float32).astype(np.float64))

    moved = 0.0
    for c in report["candidates"]:
        commands = read_gait_csv((tmp_path / c["csv"]).read_bytes(), robot=DEFAULT_ROBOT).commands
        there = end(rough, commands)
        assert there[0] == pytest.approx(c["simulated"]["forward"], abs=1e-4)
        assert there[1] == pytest.approx(c["simulated"]["sideways"], abs=1e-4)
        moved = max(moved, float(np.hypot(*(end(flat, commands)[:2] - there[:2]))))
    assert moved > 0.01  # the flat ground would have put them elsewhere


# --- the designer on a world ------------------------------------------------------------------------


def test_the_designer_starts_on_serve_worlds_ground_and_a_tab_switches_world(checkpoint):
    from snakeloco.app.designer.ground import ground_mesh
    from snakeloco.sim.world.description import Pegs, World

    from helpers import apply, connect_headless, quiet_server

    own = World(name="my pegs", pegs=Pegs(extent_m=1.5, seed=4))
    srv = quiet_server(checkpoint, world=own)
    try:
        client, d = connect_headless(srv)
        try:
            c = d.controls
            assert c.world.value == "my pegs" and {"flat", "rough", "steps", "pegs", "slope10"} <= set(
                c.world.options
            )
            assert d.session.world == own and d.scene.ground.mesh is not None
            assert d.session.replay_model.ngeom == DEFAULT_ROBOT.compile().ngeom + len(own.pegs.centres())
            flat_end = None
            assert apply(d, c.world, "flat")
            assert d.session.world == World() and d.scene.ground.mesh is None
            flat_end = d.simulated.body[-1, 1:3]
            assert apply(d, c.world, "steps")
            steps = d.session.replay_model
            assert d.scene.ground.mesh is not None and len(ground_mesh(steps).faces) == 3 * 12
            assert d.simulated is not None and not np.allclose(d.simulated.body[-1, 1:3], flat_end)
            # The ground hangs under the start frame: the start's own world point lands on the origin.
            p0, yaw0 = d.scene.start
            frame = d.scene.ground.frame
            w, z = frame.wxyz[0], frame.wxyz[3]
            turn = np.arctan2(2 * w * z, 1 - 2 * z * z)
            assert turn == pytest.approx(-yaw0)
            rotated = [
                np.cos(turn) * p0[0] - np.sin(turn) * p0[1],
                np.sin(turn) * p0[0] + np.cos(turn) * p0[1],
            ]
            np.testing.assert_allclose(np.asarray(frame.position[:2]) + rotated, 0.0, atol=1e-9)
        finally:
            client.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_the_design_panel_verifies_its_candidates_on_the_tabs_world(checkpoint):
    """A tab on rough ground designs there: each verified candidate's end is its replay's on that
    ground, where the flat plane would have put it elsewhere."""
    from snakeloco.model.design.config import DesignConfig
    from snakeloco.model.design.search import path_end
    from snakeloco.sim.data.dataset import BODY_DOWNSAMPLE
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.world.description import load_world

    from helpers import apply, connect_headless, quiet_server

    srv = quiet_server(checkpoint)
    try:
        client, d = connect_headless(srv)
        try:
            assert apply(d, d.controls.world, "rough")
            d.design.config = DesignConfig(
                screen=64, starts=2, generations=10, population=8, candidates=2, rounds=1
            )
            d.controls.design.forward.value, d.controls.design.sideways.value = 0.5, 0.0
            d.design.request()
            assert d.design.worker.wait_idle(300) and d.design.result is not None
            verified = [c for c in d.design.result.candidates if c.simulated is not None]
            assert verified
            rough, flat = Simulator(1, robot=DEFAULT_ROBOT, world=load_world("rough")), Simulator(1)

            def end(simulator, commands):
                body = simulator.replay(commands).body[::BODY_DOWNSAMPLE]
                return path_end(body.astype(np.float32).astype(np.float64))[:2]

            moved = 0.0
            try:
                for c in verified:
                    commands = d.model.commands(c.shape[None])[0]
                    np.testing.assert_allclose(end(rough, commands), c.simulated[:2], atol=1e-4)
                    moved = max(moved, float(np.hypot(*(end(flat, commands) - c.simulated[:2]))))
            finally:
                rough.close()
                flat.close()
            assert moved > 0.01
        finally:
            client.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_the_designers_fan_over_other_ground_replays_the_terrain_set(checkpoint):
    """Fan over "other ground": the Variations fan is the gait on each world of the terrain set, each
    row's end the world's own replay's, measured from the tab's replay; the line says "on other
    ground". Back to "other robots": the physics variations again."""
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.robot.variations import DEFAULT_SET
    from snakeloco.sim.scores.robustness import end_point

    from helpers import apply, connect_headless, quiet_server

    srv = quiet_server(checkpoint, variations=True)
    try:
        client, d = connect_headless(srv)
        try:
            assert d.variations is not None and d.variations[1].get("set") != "terrain"
            assert apply(d, d.controls.fan, "other ground", timeout=180)
            version, report = d.variations
            assert version == d.version and report["set"] == "terrain"
            assert [r["name"] for r in report["variations"]] == [w.name for w in TERRAIN_SET]
            assert "on other ground" in d.readout.variations
            assert len(d.scene.variation_fan) == len(TERRAIN_SET) - len(report["broken"])
            steps = next(i for i, w in enumerate(TERRAIN_SET) if w.steps is not None)
            on = Simulator(1, robot=DEFAULT_ROBOT, world=TERRAIN_SET[steps])
            try:
                end = end_point(on.replay(d.decoded.commands).body)
            finally:
                on.close()
            row = report["variations"][steps]
            assert (row["forward"], row["sideways"]) == pytest.approx(
                (end["forward"], end["sideways"]), abs=1e-9
            )
            assert apply(d, d.controls.fan, "other robots", timeout=180)
            assert [r["name"] for r in d.variations[1]["variations"]] == [v.name for v in DEFAULT_SET]
            assert "on other robots" in d.readout.variations
        finally:
            client.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_bench_terrain_measures_each_world_beside_the_plane(capsys):
    import json

    from snakeloco.app.cli.main import main

    main(["bench", "terrain", "--repeats", "1", "--sections", "replay", "--json"])
    out = capsys.readouterr().out
    r = json.loads(out.strip().splitlines()[-1])
    assert set(r["replay"]) == {"rough", "steps", "pegs", "slope10", "rough_numpy", "native"}
    for name in ("rough", "steps", "pegs", "slope10"):
        f = r["replay"][name]
        assert (
            f["world_s"] > 0 and f["flat_s"] > 0 and f["ratio"] == pytest.approx(f["world_s"] / f["flat_s"])
        )
    assert "replay on rough" in out and "first view" not in out


# --- the terrain set ---------------------------------------------------------------------------------


def test_the_terrain_set_has_each_kind_of_ground_once_and_names_them():
    from snakeloco.sim.world.sets import TERRAIN_SET

    names = [w.name for w in TERRAIN_SET]
    assert len(names) == len(set(names)) == 12
    assert [w.rough.height_m for w in TERRAIN_SET if w.rough] == [0.01, 0.02, 0.03]
    assert [w.steps.height_m for w in TERRAIN_SET if w.steps] == [0.02, 0.04]
    assert sorted((w.slope_deg, w.slope_direction_deg) for w in TERRAIN_SET if w.slope_deg) == [
        (d, a) for d in (5.0, 10.0, 15.0) for a in (0.0, 90.0)
    ]
    assert sum(w.pegs is not None for w in TERRAIN_SET) == 1


def test_terrain_rows_are_measured_from_the_flat_grounds_end():
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.scores.robustness import readout_line
    from snakeloco.sim.scores.terrain import terrain_robustness
    from snakeloco.sim.world.description import load_world

    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)
    worlds = (load_world("steps"), _rough_world(0.02))
    report = terrain_robustness(commands, Simulator(2), worlds)
    flat = Simulator().replay(commands).body[-1]
    assert report["nominal"]["forward"] == pytest.approx(flat[1]) and report["set"] == "terrain"
    for w, row in zip(worlds, report["variations"], strict=True):
        on = Simulator(world=w).replay(commands).body[-1]
        assert row["name"] == w.name and row["forward"] == pytest.approx(on[1])
        assert row["end_error_m"] == pytest.approx(np.hypot(on[1] - flat[1], on[2] - flat[2]))
    assert readout_line(report).startswith("on other ground: ends within")


@pytest.mark.slow
def test_robustness_set_terrain_closed_loop_cli(tmp_path, capsys):
    import json

    from snakeloco.app.cli.main import main

    gait = tmp_path / "undulate.csv"
    main(["gait", "undulate", "--out", str(gait)])
    main(["robustness", str(gait), "--set", "terrain", "--closed-loop", "--json"])
    out = capsys.readouterr().out
    report = json.loads(out.strip().splitlines()[-1])
    assert "12 worlds (terrain set)" in out and "flat ground" in out
    rows = {r["name"]: r for r in report["variations"]}
    assert len(rows) == 12 and report["nominal"]["rel"] < 0.03
    # Measured: the loop holds the path on 1 cm of roughness, a 5 deg slope across and the pegs (<= 0.1%).
    assert rows["rough 1 cm"]["rel"] < 0.03 and rows["pegs"]["rel"] < 0.03


def test_bench_terrain_prints_a_run_without_the_replay_section(capsys):
    """The printer reads only the sections that ran (it once needed the replay figures)."""
    from snakeloco.app.bench import report

    row = {"open": {"arrives": True, "speed": 0.3, "rel": 0.05}}
    report.terrain(
        {"library": {"undulate": {"distance_m": 32.6, "steering": "steers", "worlds": {"pegs": row}}}}
    )
    assert "library undulate (32.6 m; steers): arrives open/closed: pegs y/-" in capsys.readouterr().out
