"""Your robot, end to end: every stage reads the robot's joints (family, projection, dataset, model,
CSV, designer), and `snakeloco build` turns a description into a servable model, stage by stage."""

from __future__ import annotations

import json

import numpy as np
import pytest

from snakeloco.app.cli.build import QUICK, Build, BuildError, build_figures, sector
from snakeloco.app.cli.main import main
from snakeloco.app.cli.robot_commands import repeated_line
from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv, write_gait_csv
from snakeloco.sim import GenerateConfig, load_dataset
from snakeloco.sim.data.generate import generate_dataset
from snakeloco.sim.gaits.library import PRESETS, layout
from snakeloco.sim.gaits.members import member_from_draw
from snakeloco.sim.gaits.projection import project
from snakeloco.sim.gaits.structured import STRUCTURED_PRESETS, draw_structured
from snakeloco.sim.robot.description import DEFAULT_ROBOT, ROBOTS_DIR, load_robot

from helpers import SMALL, apply, connect_headless, quiet_server

TWELVE = load_robot(ROBOTS_DIR / "twelve.yaml")
PLANAR = load_robot(ROBOTS_DIR / "planar6.yaml")
LENIENT = STRUCTURED_PRESETS["arcs"].model_copy(
    update={"max_spread": 1e3, "members": 2, "early_seconds": 0.0}
)
"""The arcs family screened leniently (two replays, any spread kept): a record in two replays."""


@pytest.mark.parametrize("robot", [TWELVE, PLANAR], ids=["twelve", "planar6"])
def test_the_family_its_members_and_their_projection_are_the_robots(robot):
    modules, pitch = layout(robot)
    assert len(modules) == robot.n_joints and pitch.sum() == (
        robot.n_joints // 2 if robot.joint_pattern == "alternate" else 0
    )
    for i in range(8):
        shape, drawn = draw_structured(LENIENT, 0, i, 0, robot)
        assert shape.shape == (robot.n_joints, 8, 2)
        member = member_from_draw(drawn)
        np.testing.assert_allclose(member.shape(robot), shape, atol=1e-12)
        assert member.commands(robot).shape == (2000, robot.n_joints)
        back, residual = project(shape, LENIENT, robot=robot)  # a member projects onto itself
        assert residual < 1e-9 and back.kind == member.kind
        if robot.joint_pattern == "planar":
            assert drawn["kind"] == "undulate" and np.abs(shape[pitch]).max(initial=0) == 0
    with pytest.raises(ValueError, match=f"finite \\({robot.n_joints}, 8, 2\\)"):
        project(np.zeros((8, 8, 2)), LENIENT, robot=robot)  # the default robot's shape is not this one's


def test_library_gaits_are_carried_by_the_serpenoid_rule():
    undulate = PRESETS["undulate"].gait
    assert undulate.on_robot(DEFAULT_ROBOT) is undulate  # the robot they were tuned on: unchanged
    twelve = undulate.on_robot(TWELVE)
    assert twelve.nu_yaw == pytest.approx(undulate.nu_yaw * 8 / 12)  # the same waves along the body
    # Each yaw joint bends 2 alpha sin(nu Delta / 2): Delta = 2 modules between yaw joints here and there.
    ratio = np.sin(twelve.nu_yaw) / np.sin(undulate.nu_yaw)
    assert twelve.a_yaw == pytest.approx(undulate.a_yaw * ratio)
    planar = PRESETS["sidewind"].gait.on_robot(PLANAR)
    assert planar.a_pitch == 0.0 and planar.nu_yaw == pytest.approx(0.8 * 8 / 6)
    assert planar.a_yaw == pytest.approx(0.7 * np.sin(planar.nu_yaw / 2) / np.sin(0.8))  # yaw joints 1 apart


def test_gait_csvs_have_the_robots_columns_and_refuse_another_robots_gait():
    commands = PRESETS["roll"].gait.on_robot(TWELVE).commands(TWELVE)
    text = write_gait_csv(commands, {"note": "twelve"}, TWELVE)
    assert ",joint_12\n" in text.split("\n", 2)[1] + "\n"
    np.testing.assert_array_equal(read_gait_csv(text, TWELVE).commands, commands)  # round trip, to the bit
    with pytest.raises(GaitCSVError, match="a gait of 12 joints; robot snakeloco-8 has 8"):
        read_gait_csv(text, robot=DEFAULT_ROBOT)
    eight = write_gait_csv(PRESETS["roll"].gait.commands(DEFAULT_ROBOT), None, DEFAULT_ROBOT)
    with pytest.raises(GaitCSVError, match=r"a gait of 8 joints \(missing .*\); robot twelve has 12"):
        read_gait_csv(eight, TWELVE)


def test_a_dataset_stores_its_robot_and_the_default_one_hashes_as_before():
    default = GenerateConfig(num_samples=4, family="structured")
    assert "robot" not in default.to_meta()  # datasets of the paper's robot keep their meta hash
    twelve = default.model_copy(update={"robot": TWELVE})
    assert twelve.to_meta()["robot"]["n_joints"] == 12
    assert GenerateConfig.model_validate(twelve.to_meta()).robot == TWELVE


@pytest.fixture(scope="module")
def twelve_checkpoint(tmp_path_factory):
    """A tiny member checkpoint of the 12-joint robot (the arcs family screened leniently)."""
    from snakeloco.model import TrainConfig, train
    from snakeloco.model.heads.sampler import SamplerConfig, fit_sampler
    from snakeloco.model.replays import Fit

    work = tmp_path_factory.mktemp("twelve")
    cfg = GenerateConfig(num_samples=4, seed=3, family="structured", structured=LENIENT, robot=TWELVE)
    data = generate_dataset(cfg, work / "data.npz", workers=2)
    train(
        data,
        work / "vae",
        TrainConfig(epochs=2, batch_size=2, val_fraction=0.25),
        SMALL,
        log=None,
        progress=False,
    )
    fit_sampler(
        Fit(work / "vae", data, work / "model", workers=2, log=None),
        SamplerConfig(samples=4, epochs=3, hidden=16),
    )
    return work / "model", data


def test_a_checkpoint_stores_its_robot_and_says_when_replayed_on_another(twelve_checkpoint, capsys):
    from snakeloco.model import load_pretrained

    path, data = twelve_checkpoint
    assert load_dataset(data).commands.shape[-1] == 12
    model = load_pretrained(path)
    assert model.robot == TWELVE and model.config.model.n_joints == 12 and model.projects
    assert model.config.mjcf_sha256 == TWELVE.mjcf_sha256
    z = model.sample_z_b(2, 0)
    _, _, shape, _, _ = model.decode_members(z)
    assert shape.shape == (2, 12, 8, 2) and model.commands(shape).shape == (2, 2000, 12)
    assert model.robot_warning() is None
    assert "trained on robot twelve" in model.robot_warning(DEFAULT_ROBOT)
    with pytest.raises(SystemExit):  # the paper's robot cannot replay a 12-joint gait
        main(
            [
                "design",
                "--checkpoint",
                str(path),
                "--forward",
                "1",
                "--sideways",
                "0",
                "--robot",
                str(ROBOTS_DIR / "planar6.yaml"),
                "--out",
                str(path.parent / "design"),
            ]
        )
    assert "has 6 joints; the checkpoint was trained on twelve of 12" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_design_replays_on_the_checkpoints_robot(twelve_checkpoint, capsys):
    """``bench design`` on a 12-joint checkpoint: its replays run on that robot (they ran on the
    default 8-joint one, and the first verification failed on the command shape)."""
    path, _ = twelve_checkpoint
    args = ["bench", "design", "--checkpoint", str(path), "--targets", "1", "--reach", "0.3", "0.5"]
    main([*args, "--candidates", "1", "--rounds", "1", "--workers", "2", "--json"])
    r = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert r["targets"] == 1 and r["design"]["error_rel_median"] >= 0 and r["checkpoint"] == str(path)


@pytest.mark.slow
def test_the_designer_switches_to_a_family_of_another_robot(member_checkpoint, twelve_checkpoint):

    families = {"structured": member_checkpoint[0], "twelve": twelve_checkpoint[0]}
    srv = quiet_server(families=families)
    client, d = connect_headless(srv)
    try:
        assert d.session.robot.n_joints == 8 and d.scene.kinematics.robot.n_links == 9
        assert apply(d, d.controls.family, "twelve")
        assert d.session.robot == TWELVE and d.session.nominal_robot == TWELVE
        assert d.scene.kinematics.robot.n_links == 13 and len(d.controls.plots["commands"].series) == 13
        assert d.decoded.commands.shape == (2000, 12) and d.simulated is not None
        assert d.simulated.qpos.shape[-1] == TWELVE.compile().nq  # replayed on its own robot
        text = d.files.export_text()
        assert "joint_12" in text and d.model.robot_warning(d.session.robot) is None
        assert (
            d.files.import_bytes(
                "eight.csv",
                write_gait_csv(PRESETS["roll"].gait.commands(DEFAULT_ROBOT), None, DEFAULT_ROBOT).encode(),
            )
            is None
        )
        assert d.fit.robots["nominal"] == TWELVE
        assert apply(d, d.controls.family, "structured")  # and back
        assert d.session.robot == DEFAULT_ROBOT and d.scene.kinematics.robot.n_links == 9
        assert d.decoded.commands.shape == (2000, 8) and len(d.controls.plots["commands"].series) == 9
        assert srv.errors == []
    finally:
        client.close()
        srv.stop()


def test_build_refuses_a_robot_whose_gaits_do_not_travel(tmp_path):
    weak = DEFAULT_ROBOT.model_copy(update={"name": "weak", "servo_force": 0.002})
    build = Build(weak, tmp_path / "weak", QUICK, workers=2, log=lambda _: None)
    generate_dataset(GenerateConfig(num_samples=4, seed=1, robot=weak), build.data, workers=2)
    with pytest.raises(
        BuildError, match="weak cannot move with this family: only 0% of its 4 screened records"
    ):
        build._check_travel()


def test_build_figures_and_sectors():
    assert [sector(h) for h in (0, 44, 46, 134, 136, -136, -134, -46, 180)] == [
        "forward",
        "forward",
        "left",
        "left",
        "backward",
        "backward",
        "right",
        "right",
        "backward",
    ]
    report = {
        "r2_shape": 0.99,
        "r2_body": 0.97,
        "consistency": {
            "zk_zero": {
                "n_gaits": 2,
                "n_broken": 0,
                "xy_r2": 0.95,
                "final_error_rel": 0.04,
                "off_data_fraction": 0.0,
                "gaits": [{"heading_deg": 10.0}, {"heading_deg": -100.0}],
            }
        },
    }
    f = build_figures(report)
    assert f["sectors"] == {"forward": 1, "left": 0, "backward": 0, "right": 1} and f["shape_r2"] == 0.99
    assert f["body_channels_repeated"] is None and repeated_line(f) == ""  # no floor measured
    report |= {"body_channels_repeated": ["forward", "sideways", "yaw"], "r2_body_repeated": 0.98}
    f = build_figures(report | {"r2_body_raw_repeated": 0.99})
    assert f["body_r2_repeated"] == 0.98 and repeated_line(f) == (
        ", over the channels physics repeats (forward, sideways, yaw) 0.990 (from the gait alone 0.980)"
    )


FIVE = DEFAULT_ROBOT.model_copy(update={"name": "five", "n_joints": 5})
"""A 5-joint alternating snake (pitch, yaw, pitch, yaw, pitch) of the default's links and servos."""


@pytest.mark.slow
def test_build_quick_goes_from_a_description_to_a_served_five_joint_designer(tmp_path, capsys):
    """A 5-joint robot through ``build --quick`` to a served decode, a 5-column CSV export and its
    replay; a second run skips every stage, other sizes are refused."""
    from snakeloco.app.server.lifecycle import load_families
    from snakeloco.model import load_pretrained

    robot_file, out = tmp_path / "five.yaml", tmp_path / "runs" / "five"
    robot_file.write_text(FIVE.to_yaml())
    main(["build", "--robot", str(robot_file), "--out", str(out), "--quick", "--workers", "2"])
    printed = capsys.readouterr().out
    assert f"serve it: snakeloco serve --checkpoint {out}" in printed
    state = json.loads((out / "build.json").read_text())
    assert list(state) == ["generate", "train", "calibrate", "evaluate"]
    assert state["generate"]["travel"]["travelling_fraction"] >= 0.25
    f = state["evaluate"]["figures"]
    assert f["positions"] + f["broken"] == QUICK.positions and sum(f["sectors"].values()) == f["positions"]
    model = load_pretrained(out / "model")
    assert model.robot == FIVE and model.projects and model.config.density is not None
    models, first = load_families((str(out),))  # `serve --checkpoint runs/five`: the build's model
    assert first == "five" and models["five"].robot == FIVE

    # Served: the tab decodes and replays on the 5-joint robot; its CSV has 5 joint columns and
    # replays when imported again.
    srv = quiet_server(families={"five": out / "model"})
    client, d = connect_headless(srv)
    try:
        assert d.session.robot == FIVE and d.scene.kinematics.robot.n_links == 6
        assert d.decoded.commands.shape == (2000, 5) and d.simulated is not None
        assert d.simulated.qpos.shape[-1] == FIVE.compile().nq
        text = d.files.export_text()
        header = next(line for line in text.splitlines() if not line.startswith("#"))
        assert header.split(",")[1:] == [f"joint_{i}" for i in range(1, 6)]
        exported = d.decoded.commands.copy()
        before = d.version
        assert d.files.import_bytes("five.csv", text.encode()) is not None
        assert d.version > before and d.wait_idle(60)
        assert np.allclose(d.decoded.commands, exported, atol=1e-5) and d.simulated is not None
        assert d.simulated.qpos.shape[-1] == FIVE.compile().nq and srv.errors == []
    finally:
        client.close()
        srv.stop()

    # Run again: every stage is skipped; other sizes in the same folder are refused.
    main(["build", "--robot", str(robot_file), "--out", str(out), "--quick"])
    assert capsys.readouterr().out.count("skipped") == 4
    with pytest.raises(SystemExit):
        main(["build", "--robot", str(robot_file), "--out", str(out), "--records", "64"])
    assert "its generate stage was built with other options (heldout, records)" in capsys.readouterr().err


def test_a_build_folder_names_its_model(tmp_path):
    from snakeloco.model.checkpoint import resolve_checkpoint

    out = tmp_path / "runs" / "mine"
    (out / "model").mkdir(parents=True)
    assert resolve_checkpoint(out) == out  # not a build's folder until its build.json exists
    (out / "build.json").write_text("{}")
    assert resolve_checkpoint(out) == out / "model" and resolve_checkpoint(out / "model") == out / "model"


def test_serve_offers_several_checkpoints_in_the_family_dropdown(twelve_checkpoint, tmp_path):
    from snakeloco.app.cli.main import parse_args
    from snakeloco.app.server.lifecycle import load_families

    path, _ = twelve_checkpoint
    built = tmp_path / "runs" / "twelve"  # a build's folder: its model is offered under the robot's name
    built.mkdir(parents=True)
    (built / "model").symlink_to(path, target_is_directory=True)
    cmd = parse_args(["serve", "--checkpoint", str(built / "model"), "--checkpoint", "paper", "--port", "0"])
    assert cmd.checkpoint == (str(built / "model"), "paper")
    models, first = load_families(tuple(cmd.checkpoint))
    assert first == "twelve" and list(models) == ["structured", "paper", "twelve"]
    assert models["twelve"].robot == TWELVE
