"""The robot as data (``sim.robot.description``) and its variations (``sim.robot.variations``, ``sim.scores.robustness``):
docs/robot.md, "Your robot", and docs/variations.md."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from snakeloco.app.cli.main import main
from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics.command_rule import CommandRule, expand_commands
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT, MJCF_PATH, Robot, RobotError, load_robot
from snakeloco.sim.robot.variations import DEFAULT_SET, PHYSICAL_FIELDS, Variation, sampled_set
from snakeloco.sim.scores.robustness import change_table, readout_line, robustness


def model_fields(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Every array and number of a compiled model, and its options', by name."""
    out = {}
    for owner, prefix in ((model, ""), (model.opt, "opt.")):
        for name in dir(owner):
            if name.startswith("_"):
                continue
            try:
                value = getattr(owner, name)
            except Exception:  # properties MuJoCo refuses to read back here
                continue
            if isinstance(value, np.ndarray | int | float) and not isinstance(value, bool):
                out[prefix + name] = np.asarray(value)
    return out


def changed_fields(a: mujoco.MjModel, b: mujoco.MjModel) -> set[str]:
    fa, fb = model_fields(a), model_fields(b)
    assert fa.keys() == fb.keys()
    return {k for k in fa if fa[k].shape != fb[k].shape or not np.array_equal(fa[k], fb[k])}


# --- the description -------------------------------------------------------------------------------


def test_default_description_builds_snake_xml_field_by_field():
    built = DEFAULT_ROBOT.compile()
    from_file = mujoco.MjModel.from_xml_path(str(MJCF_PATH))
    assert changed_fields(built, from_file) == set()
    assert DEFAULT_ROBOT.n_joints == 8 and abs(DEFAULT_ROBOT.body_length - 0.95) < 1e-12


def test_default_description_replays_bit_identical_to_snake_xml():
    commands = PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)
    ours = Simulator(workers=1).replay(commands)
    theirs = Simulator(workers=1)
    theirs.model = mujoco.MjModel.from_xml_path(str(MJCF_PATH))
    theirs._data = mujoco.MjData(theirs.model)
    theirs = theirs.replay(commands)
    assert np.array_equal(ours.body, theirs.body) and np.array_equal(ours.joint_angles, theirs.joint_angles)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("n_joints: 2\n", "n_joints"),
        ("link_mass: -0.1\n", "link_mass"),
        ("colour: red\n", "colour"),
        ("joint_pattern: spiral\n", "joint_pattern"),
        ("command_limit: 2.5\n", "robot"),  # outside the 2.3 rad joint range: the whole robot is wrong
        ("timestep: 0.003\n", "robot"),  # does not divide 50 ms
        ("- 1\n- 2\n", "mapping"),
        ("n_joints: [8\n", "not YAML"),
    ],
)
def test_bad_robot_file_is_refused_naming_the_field(tmp_path, capsys, text, field):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(RobotError, match=field):
        load_robot(path)
    with pytest.raises(SystemExit) as exc:
        main(["robot", "show", str(path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("snakeloco: error: ") and str(path) in err and field in err


def test_robot_show_and_mjcf(tmp_path, capsys):
    path = tmp_path / "twelve.yaml"
    path.write_text("name: twelve\nn_joints: 12\nlink_length: 0.07\nlink_radius: 0.02\nlink_mass: 0.12\n")
    main(["robot", "show", str(path), "--json"])
    shown = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert shown["figures"]["joints"] == 12 and shown["figures"]["links"] == 13
    assert shown["figures"]["body_length_m"] == pytest.approx(13 * 0.07 + 0.04)
    assert shown["figures"]["mass_kg"] == pytest.approx(13 * 0.12)
    xml = tmp_path / "twelve.xml"
    main(["robot", "mjcf", str(path), "--out", str(xml)])
    model = mujoco.MjModel.from_xml_path(str(xml))
    assert model.nu == 12 and model.nbody == 14 and model.npair == 13
    # The written MJCF is the description's model: the same physics as compiling it directly.
    np.testing.assert_array_equal(model.body_mass, load_robot(path).compile().body_mass)
    # A description round-trips through YAML.
    again = tmp_path / "again.yaml"
    again.write_text(load_robot(path).to_yaml())
    assert load_robot(again) == load_robot(path)


def test_planar_robot_of_five_joints_yaws_and_moves_forward():
    robot = Robot(name="five", n_joints=5, joint_pattern="planar")
    model = robot.compile()
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    np.testing.assert_allclose(model.jnt_axis[hinges], [[0, 0, 1]] * 5)
    assert robot.body_link == (3, robot.link_length)  # 6 links: the middle joint, between links 3 and 4
    sim = Simulator(workers=1, robot=robot)
    t = np.arange(2000) / 20.0
    # A travelling wave of 0.52 Hz, 1 rad per module: planar undulation.
    commands = 0.8 * np.sin(2 * np.pi * 0.52 * t[:, None] - 1.0 * np.arange(5)[None])
    body = sim.replay(commands).body
    assert np.hypot(body[-1, 1], body[-1, 2]) > 0.5  # it travels
    assert np.abs(body[:, 3]).max() < 0.1  # and never rolls: there is no pitch joint


# --- variations ------------------------------------------------------------------------------------


EXPECTED_FIELDS = {
    "friction_along": {"pair_friction"},
    "friction_across": {"pair_friction"},
    "servo_kp": {"actuator_gainprm", "actuator_biasprm"},
    "servo_kv": {"actuator_biasprm"},
    "servo_force": {"actuator_forcerange"},
    "joint_damping": {"dof_damping"},
    "slope_deg": {"opt.gravity"},
    "latency": set(),  # a command rule, not a model field: tested below
}


@pytest.mark.parametrize("field", sorted(EXPECTED_FIELDS))
def test_each_variation_changes_the_model_field_it_names_and_only_it(field):
    v = (
        Variation(name=field, scale={field: 1.5})
        if field != "slope_deg"
        else Variation(name=field, add={field: 5})
    )
    changed = changed_fields(DEFAULT_ROBOT.compile(), v.apply(DEFAULT_ROBOT).compile())
    assert changed == EXPECTED_FIELDS[field]


def test_mass_variation_changes_masses_and_what_mujoco_derives_from_them():
    varied = Variation(name="heavy", scale={"link_mass": 1.5}).apply(DEFAULT_ROBOT).compile()
    changed = changed_fields(DEFAULT_ROBOT.compile(), varied)
    assert {"body_mass", "body_inertia", "body_subtreemass"} <= changed
    assert all(f.startswith(("body_", "dof_", "actuator_acc0", "light_poscom0")) for f in changed)
    np.testing.assert_allclose(varied.body_mass[1:], 0.3)


def test_latency_delays_the_servo_targets_by_whole_steps():
    commands = np.random.default_rng(0).uniform(-1, 1, (2, 2000, 8))
    cfg = CommandRule()
    plain = expand_commands(commands, 20, cfg)
    late = expand_commands(commands, 20, cfg, delay=12)
    np.testing.assert_array_equal(late[:, 12:], plain[:, :-12])
    np.testing.assert_array_equal(late[:, :12], 0.0)
    # A chunk of the delayed expansion is the same slice of the whole one.
    np.testing.assert_array_equal(expand_commands(commands, 20, cfg, (5, 400), delay=12), late[:, 5:400])
    sim = Simulator(workers=1)
    assert sim.latency_steps(DEFAULT_SET[9].apply(DEFAULT_ROBOT)) == 12  # 30 ms at 2.5 ms


def test_variation_sets_are_valid_physical_changes():
    assert len(DEFAULT_SET) >= 10 and len({v.name for v in DEFAULT_SET}) == len(DEFAULT_SET)
    for v in (*DEFAULT_SET, *sampled_set()):
        assert set(v.fields) <= set(PHYSICAL_FIELDS)
        v.apply(DEFAULT_ROBOT)
    assert sampled_set(4, seed=1) == sampled_set(4, seed=1) != sampled_set(4, seed=2)
    with pytest.raises(ValueError, match="changes nothing"):
        Variation(name="nothing")
    with pytest.raises(RobotError, match="link_mass"):
        Variation(name="massless", add={"link_mass": -1}).apply(DEFAULT_ROBOT)


def test_variations_replay_in_one_batch_as_each_robot_alone():
    commands = PRESETS["roll"].gait.commands(DEFAULT_ROBOT)[None]
    sim = Simulator(workers=2)
    varied = [v.apply(DEFAULT_ROBOT) for v in (DEFAULT_SET[0], DEFAULT_SET[9], DEFAULT_SET[10])]
    batch = sim.simulate(np.repeat(commands, 3, axis=0), robots=varied)
    for i, robot in enumerate(varied):
        alone = Simulator(workers=1, robot=robot).simulate(commands)
        np.testing.assert_array_equal(batch.body[i], alone.body[0])


def test_a_broken_variation_is_reported_not_raised():
    """A servo 10^4 times too stiff for the timestep makes MuJoCo's integration blow up."""
    broken = Variation(name="servo kp x1e4", scale={"servo_kp": 1e4, "servo_force": 1e4})
    report = robustness(
        PRESETS["roll"].gait.commands(DEFAULT_ROBOT), [DEFAULT_SET[1], broken], Simulator(workers=2)
    )
    rows = {r["name"]: r for r in report["variations"]}
    assert rows["servo kp x1e4"]["failure"] and rows["servo kp x1e4"]["end_error_m"] is None
    assert rows["floor friction x2"]["failure"] is None and report["worst"] == "floor friction x2"
    assert report["broken"] == ["servo kp x1e4"] and "broke: servo kp x1e4" in readout_line(report)


def test_change_table_per_kind_against_the_noise_floor():
    """Changes are relative to max(nominal distance, 0.5 m); a broken replay is left out of its
    median and counted; a gait whose nominal replay broke is left out of its kind."""
    ends = {
        "nominal": np.array([[2.0, 0.0], [0.0, 0.1], [np.nan, np.nan], [0.0, 4.0]]),
        "noise": np.array([[2.02, 0.0], [0.0, 0.11], [0.0, 0.0], [0.0, 4.04]]),
        "slope": np.array([[1.0, 0.0], [np.nan, np.nan], [1.0, 1.0], [0.0, 2.0]]),
    }
    table = change_table(["roll", "turn", "roll", "roll"], ends, floor="noise")
    roll, turn = table["roll"], table["turn"]
    assert roll["n"] == 2 and turn["n"] == 1 and table["all"]["n"] == 3
    assert roll["median"]["slope"] == pytest.approx(0.5) and roll["median"]["noise"] == pytest.approx(0.01)
    assert roll["times_floor"]["slope"] == pytest.approx(50.0)
    assert turn["median"]["noise"] == pytest.approx(0.01 / 0.5) and turn["median"]["slope"] is None
    assert turn["broken"]["slope"] == 1.0 and roll["broken"]["slope"] == 0.0


@pytest.mark.slow
def test_robustness_json_matches_its_own_replays(tmp_path, capsys):
    gait = tmp_path / "roll.csv"
    main(["gait", "roll", "--out", str(gait)])
    capsys.readouterr()
    main(["robustness", str(gait), "--json"])
    report = json.loads(capsys.readouterr().out.splitlines()[-1])
    commands = PRESETS["roll"].gait.commands(DEFAULT_ROBOT)
    nominal = Simulator(workers=1).replay(commands).body[-1]
    assert report["nominal"]["forward"] == nominal[1] and report["nominal"]["sideways"] == nominal[2]
    rows = {r["name"]: r for r in report["variations"]}
    assert list(rows) == [v.name for v in DEFAULT_SET]
    for v in (DEFAULT_SET[0], DEFAULT_SET[9], DEFAULT_SET[11]):
        end = Simulator(workers=1, robot=v.apply(DEFAULT_ROBOT)).replay(commands).body[-1]
        assert (rows[v.name]["forward"], rows[v.name]["sideways"]) == (end[1], end[2])
        err = np.hypot(end[1] - nominal[1], end[2] - nominal[2])
        assert rows[v.name]["end_error_m"] == pytest.approx(err, rel=1e-12)
    worst = max(report["variations"], key=lambda r: r["end_error_m"])
    assert report["worst"] == worst["name"] and report["worst_end_error_m"] == worst["end_error_m"]


def test_robustness_refuses_a_bad_gait_file(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,joint_1\n0,0\n")
    with pytest.raises(SystemExit) as exc:
        main(["robustness", str(bad)])
    assert exc.value.code == 2 and "bad.csv: line 1: header must be" in capsys.readouterr().err


@pytest.mark.slow
def test_the_designer_streams_the_variations_fan_and_says_how_far_the_end_moves(checkpoint):

    from helpers import apply, connect_headless, quiet_server

    srv = quiet_server(checkpoint, variations=True)
    client, d = connect_headless(srv)
    try:
        version, report = d.variations
        assert version == d.version and len(report["variations"]) == len(DEFAULT_SET)
        drawn = sum(1 for r in report["variations"] if r["failure"] is None)
        assert drawn and len(d.scene.variation_fan) >= 1
        assert 'data-key="variations"' in d.controls.readout.content
        assert readout_line(report) in d.controls.readout.content.replace("&#x27;", "'")
        # The same numbers as the command line's batch (a variation's replay is its replay anywhere).
        alone = robustness(d.decoded.commands, DEFAULT_SET[:2], Simulator(workers=1))
        for a, b in zip(alone["variations"], report["variations"][:2], strict=True):
            assert a["forward"] == b["forward"] and a["sideways"] == b["sideways"]
        # A new gait drops the old one's variations: its fan is gone until its own come in.
        d.controls.layers["Variations fan"].value = False
        assert apply(d, d.sliders[0], 0.7, 120)
        assert d.variations[0] == d.version and all(not n.visible for n in d.scene.variation_fan)
    finally:
        client.close()
        srv.stop()


@pytest.mark.slow
def test_robust_design_returns_only_candidates_whose_worst_case_it_replayed(checkpoint, tmp_path, capsys):
    from snakeloco.app.export.gait_csv import read_gait_csv

    quick = "--screen 64 --starts 2 --generations 8 --population 8 --candidates 2 --rounds 1".split()
    out = tmp_path / "robust"
    target = ["--forward", "0.5", "--sideways", "0.2", "--checkpoint", str(checkpoint)]
    main(["design", *target, *quick, "--robust", "--out", str(out), "--workers", "2", "--json"])
    report = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert report["robust"] == "worst" and 1 <= len(report["candidates"]) <= 2
    # Ranked by the replayed worst case, those that meet the target on the nominal robot first.
    keys = [(c["error_m"] > report["tolerance_m"], c["robust"]["worst_m"]) for c in report["candidates"]]
    assert keys == sorted(keys)
    for c in report["candidates"][:1]:
        r = c["robust"]
        assert r["replayed"] == len(DEFAULT_SET) and r["worst_m"] >= c["error_m"]
        # The worst case is what the variations' replays of the written gait did.
        commands = read_gait_csv((out / Path(c["csv"]).name).read_bytes(), robot=DEFAULT_ROBOT).commands
        varied = robustness(commands, DEFAULT_SET, Simulator(workers=2))
        ends = [
            np.hypot(v["forward"] - 0.5, v["sideways"] - 0.2)
            for v in varied["variations"]
            if v["forward"] is not None
        ]
        assert max([c["error_m"], *ends]) == pytest.approx(r["worst_m"], abs=2e-3)


def test_the_shipped_example_robots_load_build_and_replay():
    from snakeloco.sim.robot.description import ROBOTS_DIR

    twelve, planar = load_robot(ROBOTS_DIR / "twelve.yaml"), load_robot(ROBOTS_DIR / "planar6.yaml")
    assert twelve.n_joints == 12 and twelve.compile().nu == 12 and twelve.body_length == pytest.approx(0.95)
    assert planar.joint_axes == ("yaw",) * 6
    t = np.arange(2000) / 20.0
    for robot in (twelve, planar):
        k = np.arange(robot.n_joints)
        wave = 0.8 * np.sin(2 * np.pi * 0.52 * t[:, None] - 1.0 * k[None])
        if robot.joint_pattern == "alternate":
            wave[:, 0::2] *= 0.2  # a small pitch wave beside the yaw wave
        body = Simulator(workers=1, robot=robot).replay(wave).body
        assert np.isfinite(body).all() and np.hypot(*body[-1, 1:3]) > 0.3
