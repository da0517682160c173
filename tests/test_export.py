"""``snakeloco export``: ROS 2, resampled CSV, Dynamixel ticks, gait-equation parameters and the html
replay, each read back (docs/export.md)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from snakeloco.app.cli.main import main
from snakeloco.app.export import formats as export
from snakeloco.app.export.gait_csv import MEMBER_KEY, library_gait_csv, write_gait_csv
from snakeloco.sim.gaits.library import PRESETS, GaitEquation
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.physics.command_rule import CommandRule, expand_commands
from snakeloco.sim.robot.description import DEFAULT_ROBOT, Robot

from helpers import BROWSER, quiet_server, random_commands

SIDEWIND = PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)


@pytest.fixture
def sidewind_csv(tmp_path):
    path = tmp_path / "sidewind.csv"
    path.write_text(library_gait_csv("sidewind", robot=DEFAULT_ROBOT))
    return path


def test_20hz_without_lead_in_is_the_gait_itself_and_knots_are_exact():
    traj = export.trajectory(SIDEWIND, DEFAULT_ROBOT, rate=20, lead_in=False)
    np.testing.assert_array_equal(traj.positions, SIDEWIND)
    at100 = export.trajectory(SIDEWIND, DEFAULT_ROBOT, rate=100)
    assert at100.lead_in_s == 3.0 and len(at100.times) == 100 * 103
    np.testing.assert_array_equal(at100.positions[300::5], SIDEWIND)  # every 5th sample is a knot
    np.testing.assert_array_equal(at100.positions[0], 0.0)  # from the straight rest pose
    # Between knots: on the straight line, with its slope as the velocity.
    mid = at100.positions[301]
    np.testing.assert_allclose(mid, SIDEWIND[0] + 0.2 * (SIDEWIND[1] - SIDEWIND[0]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(at100.velocities[301], (SIDEWIND[1] - SIDEWIND[0]) * 20, atol=1e-12)
    two = export.trajectory(SIDEWIND, DEFAULT_ROBOT, rate=20, periods=2, lead_in=False)
    np.testing.assert_array_equal(two.positions, np.concatenate([SIDEWIND, SIDEWIND]))


def test_ros2_positions_equal_the_resampled_commands(sidewind_csv, tmp_path):
    out = tmp_path / "sidewind.yaml"
    main(["export", str(sidewind_csv), "--format", "ros2", "--rate", "50", "--out", str(out)])
    times, positions, names = export.read_ros2(out.read_text())
    traj = export.trajectory(SIDEWIND, DEFAULT_ROBOT, rate=50)
    assert names == [f"joint{k}" for k in range(1, 9)]
    np.testing.assert_allclose(times, traj.times, rtol=0, atol=1e-9)
    np.testing.assert_allclose(positions, traj.positions, rtol=0, atol=1e-9)
    assert np.all(np.diff(times) > 0)


def test_csv_export_reads_back_in_either_unit(sidewind_csv, tmp_path):
    for units in ("rad", "deg"):
        out = tmp_path / f"sidewind_{units}.csv"
        main(
            [
                "export",
                str(sidewind_csv),
                "--format",
                "csv",
                "--units",
                units,
                "--velocities",
                "--out",
                str(out),
            ]
        )
        _, positions, got_units = export.read_csv(out.read_text())
        assert got_units == units and "vel_8" in out.read_text().split("time_s", 1)[1].splitlines()[0]
        np.testing.assert_allclose(
            positions, export.trajectory(SIDEWIND, DEFAULT_ROBOT, 100).positions, atol=1e-12
        )


def test_dynamixel_ticks_back_to_radians_within_one_tick(sidewind_csv, tmp_path):
    robot_file = tmp_path / "robot.yaml"
    offsets = [0.1, -0.2, 0.0, 0.05, 0.0, 0.0, -0.1, 0.3]
    robot_file.write_text(f"servo_ids: [11, 12, 13, 14, 15, 16, 17, 18]\nhome_offsets: {offsets}\n")
    out = tmp_path / "sidewind.dxl.csv"
    main(
        ["export", str(sidewind_csv), "--format", "dynamixel", "--robot", str(robot_file), "--out", str(out)]
    )
    _, ticks, ids = export.read_dynamixel(out.read_text())
    assert ids == list(range(11, 19)) and ticks.dtype.kind == "i" and 0 <= ticks.min() and ticks.max() < 4096
    robot = Robot(servo_ids=tuple(ids), home_offsets=tuple(offsets))
    back = export.from_ticks(ticks, robot)
    want = export.trajectory(SIDEWIND, robot, 100).positions
    assert np.abs(back - want).max() <= 0.5 * 2 * math.pi / 4096 + 1e-12  # rounding: half a tick
    assert ticks[0, 1] == round(2048 - 0.2 * 4096 / (2 * math.pi))  # the home offset, at the rest pose


def test_gait_equation_resynthesises_the_csv_to_the_bit(sidewind_csv, tmp_path):
    out = tmp_path / "sidewind.gait.yaml"
    main(["export", str(sidewind_csv), "--format", "gait-equation", "--out", str(out)])
    np.testing.assert_array_equal(export.read_gait_equation(out.read_text(), robot=DEFAULT_ROBOT), SIDEWIND)
    # A structured-family member, from the '# member:' line Export CSV writes.
    member = Member(
        kind="undulate",
        wave=GaitEquation(a_yaw=0.6, nu_yaw=0.7, frequency=0.52),
        steering_amplitude=0.2,
        steering_phase=0.4,
    )
    member_csv = tmp_path / "member.csv"
    member_csv.write_text(
        write_gait_csv(
            member.commands(DEFAULT_ROBOT), {MEMBER_KEY: json.dumps(member.params())}, DEFAULT_ROBOT
        )
    )
    main(["export", str(member_csv), "--format", "gait-equation", "--out", str(out)])
    np.testing.assert_array_equal(
        export.read_gait_equation(out.read_text(), robot=DEFAULT_ROBOT), member.commands(DEFAULT_ROBOT)
    )


def test_gait_equation_refuses_a_gait_that_has_no_parameters(tmp_path, capsys):
    path = tmp_path / "random.csv"
    path.write_text(write_gait_csv(random_commands(1)[0] * 0.5, None, DEFAULT_ROBOT))
    with pytest.raises(SystemExit):
        main(["export", str(path), "--format", "gait-equation", "--out", str(tmp_path / "x.yaml")])
    assert "not a member of the structured family nor a library gait" in capsys.readouterr().err
    edited = tmp_path / "edited.csv"
    edited.write_text(library_gait_csv("roll", robot=DEFAULT_ROBOT).replace("\n0.0,0.2", "\n0.0,0.3", 1))
    with pytest.raises(SystemExit):
        main(["export", str(edited), "--format", "gait-equation", "--out", str(tmp_path / "x.yaml")])
    assert "not its parameters'" in capsys.readouterr().err


def test_a_command_beyond_the_range_or_speed_is_refused_with_joint_and_time(sidewind_csv, tmp_path, capsys):
    narrow = tmp_path / "narrow.yaml"
    narrow.write_text("joint_range: 0.6\ncommand_limit: 0.5\n")
    argv = [
        "export",
        str(sidewind_csv),
        "--format",
        "ros2",
        "--robot",
        str(narrow),
        "--out",
        str(tmp_path / "a"),
    ]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert (
        exc.value.code == 2
        and re.search(r"joint_[2468] at t = [\d.]+ s: [+-][\d.]+ rad", err)
        and "beyond the robot's command limit +/-0.5 rad" in err
    )
    assert not (tmp_path / "a").exists()
    main([*argv, "--clip"])
    said = capsys.readouterr().out
    assert "clipped joint_2:" in said and "joint_1:" not in said  # pitch joints stay inside 0.4 rad
    _, positions, _ = export.read_ros2((tmp_path / "a").read_text())
    assert np.abs(positions).max() <= 0.5
    slow = Robot(joint_speed_limit=2.0)
    with pytest.raises(
        export.ExportError, match=r"joint_2 at t = [\d.]+ s: [\d.]+ rad/s is beyond .* 2.0 rad/s"
    ):
        export.trajectory(SIDEWIND, slow)
    limited = export.trajectory(SIDEWIND, slow, clip=True)
    assert np.abs(np.diff(limited.positions, axis=0)).max() * 20 <= 2.0 + 1e-9 and limited.clipped


def test_100hz_commands_replay_where_the_20hz_ones_do():
    """The 100 Hz export, interpolated between its own samples at the physics step (as a servo stack
    that interpolates would), ends within 1 cm of the 20 Hz replay."""
    from snakeloco.sim.physics.simulator import Simulator

    sim = Simulator(workers=1)
    ctrl20 = expand_commands(SIDEWIND[None], sim.substeps, CommandRule())[0]
    traj = export.trajectory(SIDEWIND, DEFAULT_ROBOT, rate=100)
    t_step = np.arange(len(ctrl20)) * sim.model.opt.timestep
    times = np.append(traj.times, traj.times[-1] + 0.01)  # the curve closes on the record's first sample
    samples = np.vstack([traj.positions, SIDEWIND[:1]])
    ctrl100 = np.stack([np.interp(t_step, times, samples[:, k]) for k in range(8)], axis=1)
    _, sens = sim.rollout(np.stack([ctrl20, ctrl100]))
    pos = sim.columns.pos
    assert np.linalg.norm(sens[0, -1, pos] - sens[1, -1, pos]) < 0.01
    assert np.linalg.norm(sens[0, -1, pos[:2]] - sens[0, 0, pos[:2]]) > 10  # it went somewhere


def browser_test(test):
    """``helpers.BROWSER``'s marks on one test."""
    for mark in BROWSER:
        test = mark(test)
    return test


@browser_test
def test_html_export_opens_from_disk_with_no_server(sidewind_csv, tmp_path):
    from playwright.sync_api import sync_playwright

    from snakeloco.app.bench.users.load_driver import CHROMIUM, CHROMIUM_ARGS

    out = tmp_path / "share"
    main(["export", str(sidewind_csv), "--format", "html", "--out", str(out)])
    page_file = out / "index.html"
    assert 0.5e6 < page_file.stat().st_size < 5e6
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 950})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(page_file.as_uri())
            page.wait_for_selector("canvas", timeout=60_000)
            page.wait_for_timeout(3000)
            first = page.screenshot()
            page.wait_for_timeout(6000)
            second = page.screenshot()
        finally:
            browser.close()
    assert not errors
    assert first != second  # the replay plays: the snake moved


@pytest.mark.slow
def test_the_designer_exports_for_the_robot_and_shares_its_replay(checkpoint, tmp_path):
    from snakeloco.app.export.formats import ROBOT_FORMATS

    from helpers import connect_headless

    srv = quiet_server(checkpoint, ensemble=3)
    client, d = connect_headless(srv)
    try:
        notes = []
        d.client.add_notification = lambda title, body, **kw: notes.append((title, body))
        gait = d.files.export_text()
        name, data = d.files.export_for_robot("ROS 2 trajectory (100 Hz)")
        assert name.endswith(".yaml")
        _, positions, _ = export.read_ros2(data.decode())
        want = export.trajectory(export.read_gait_csv(gait, robot=DEFAULT_ROBOT).commands, DEFAULT_ROBOT, 100)
        np.testing.assert_allclose(positions, want.positions, atol=1e-9)
        _, data = d.files.export_for_robot("CSV 100 Hz + velocities")
        assert "vel_1" in data.decode()
        # The tiny paper-family checkpoint's gaits are no family member: refused, with the reason.
        assert d.files.export_for_robot("Gait equation (YAML)") is None
        assert notes and "not a member of the structured family" in notes[-1][1]
        assert set(ROBOT_FORMATS) == set(d.controls.robot_format.options)
        name, page = d.files.share()
        assert name.endswith(".html") and b"__VISER_EMBED_DATA__" in page and len(page) > 5e5
    finally:
        client.close()
        srv.stop()
