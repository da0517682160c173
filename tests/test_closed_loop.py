"""Closed-loop gaits: steering found per gait, the path follower, its replays, scores and export."""

import json
import math
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from snakeloco.app.cli.main import main
from snakeloco.sim.control import FollowerConfig, PathFollower, Steering
from snakeloco.sim.control.closed_loop import make_follower, nominal_reference, run_closed_loop
from snakeloco.sim.control.find import find_steering
from snakeloco.sim.gaits.library import PRESETS
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.robot.sensing import PoseEstimate, Sensing

UNDULATE = Steering(
    kind="yaw_offset", turn_rate=2.096, limit=0.3, period=1.0753, travel_offset=0.0015, speed=0.326
)
"""The library undulation's steering as ``find_steering`` measured it (yaw offset, 18 deg/s at 0.15 rad)."""


@pytest.fixture(scope="module")
def sim():
    s = Simulator(workers=2)
    yield s
    s.close()


@pytest.fixture(scope="module")
def undulation(sim):
    commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)
    return commands, nominal_reference(commands, sim, UNDULATE.period)


def test_the_follower_package_imports_no_mujoco_torch_or_viser():
    code = (
        "import sys; from snakeloco.sim.control import PathFollower; "
        "print(sorted(m for m in ('mujoco', 'torch', 'viser') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr


def test_unsteered_closed_loop_replay_is_the_open_loop_replay_to_the_bit(sim):
    """With no steering input the chunked closed-loop rollout is the open-loop one, latency included."""
    commands = PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)[:400]  # a short period keeps it quick: 20 s
    robot = sim.robot.model_copy(update={"latency": 0.03})
    f = make_follower(commands, np.zeros((2, 2)), Steering(period=1.0), sim, "on_time")
    (run,) = run_closed_loop(sim, [f], [robot])
    one = Simulator(workers=1)  # no rollout threads: the rows run on the calling thread, the same numbers
    try:
        (alone,) = run_closed_loop(one, [f], [robot])
    finally:
        one.close()
    np.testing.assert_array_equal(alone.poses, run.poses)
    from snakeloco.sim.physics.command_rule import expand_commands

    ctrl = expand_commands(commands[None], sim.substeps, sim.config, delay=sim.latency_steps(robot))
    _, sens = sim.rollout(ctrl, models=[sim.variation_model(robot)])
    world = sim.poses(sens[0, sim.substeps - 1 :: sim.substeps])[:-1]  # before each control step
    o = sim.poses(sim.initial_sensors())
    c, s = math.cos(o[2]), math.sin(o[2])
    x, y = (
        c * (world[:, 0] - o[0]) + s * (world[:, 1] - o[1]),
        -s * (world[:, 0] - o[0]) + c * (world[:, 1] - o[1]),
    )
    assert np.array_equal(run.poses[1:, 0], x) and np.array_equal(run.poses[1:, 1], y)


def test_the_follower_steers_a_gait_back_to_its_path(sim, undulation):
    """Started 1 m off its path and 30 deg off its heading (the path moved and turned instead of the
    snake), the loop brings the undulation back within 0.1 m and ends within 3% of the path's end."""
    commands, reference = undulation
    turn = math.radians(30.0)
    c, s = math.cos(turn), math.sin(turn)
    start = reference[0]
    moved = start + (reference - start) @ np.array([[c, s], [-s, c]]) + np.array([0.0, 1.0])
    f = make_follower(commands, moved, UNDULATE, sim, "arrive")
    (run,) = run_closed_loop(sim, [f])
    assert run.failure is None and run.arrived
    e = np.abs(run.cross_track)
    assert np.nanmax(e[: len(e) // 4]) > 0.5  # it did start off the path
    settled = int(np.flatnonzero(e >= 0.1)[-1])  # back within 0.1 m for good from here
    assert settled < len(e) / 3
    distance = np.linalg.norm(moved[-1] - moved[0])
    assert np.linalg.norm(run.end - moved[-1]) / distance < 0.03
    assert 0 < run.saturated < 0.5  # it steered, hard at first


def test_path_follower_in_a_plain_mujoco_loop_reproduces_the_simulators_closed_loop(
    sim, undulation, tmp_path
):
    """The exported folder's follower, fed the pose from a plain mj_step loop, ends where the
    simulator's closed-loop replay ends: to the bit."""
    commands, reference = undulation
    short = reference[:600]  # arrive after ~30 s
    follower = make_follower(commands, short, UNDULATE, sim, "arrive")
    (run,) = run_closed_loop(sim, [follower])
    follower.save(tmp_path / "ctl")
    robot_side = PathFollower.load(tmp_path / "ctl")
    m = sim.model
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    prev, n, poses = np.zeros(robot_side.n_joints), 0, []
    while not robot_side.done:
        x, y, yaw = sim.poses(d.sensordata)
        poses.append((x, y, yaw))
        q = robot_side.step(n / robot_side.rate, x, y, yaw)
        for j in range(sim.substeps):
            d.ctrl[:] = prev + (q - prev) * (j / sim.substeps)
            mujoco.mj_step(m, d)
        prev, n = q, n + 1
    assert robot_side.arrived and n == len(run.times)
    assert np.array_equal(robot_side.averaged, run.end)


def test_a_gait_without_a_steering_input_is_played_open_loop_and_says_so(sim, tmp_path, capsys):
    steering = find_steering(PRESETS["roll"].gait.commands(DEFAULT_ROBOT), sim)
    assert not steering.steers and "one way only" in steering.why
    assert steering.line().startswith("no steering input: ")
    f = make_follower(
        PRESETS["roll"].gait.commands(DEFAULT_ROBOT)[:200], np.zeros((2, 2)), steering, sim, "on_time"
    )
    (run,) = run_closed_loop(sim, [f])
    assert run.limit == 0 and not run.steering.any() and run.saturated == 0.0


def test_closed_loop_robustness_cli_and_a_bad_variation_file(tmp_path, capsys):
    gait = tmp_path / "sidewind.csv"
    main(["gait", "sidewind", "--out", str(gait)])
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "- name: slippery\n  scale: {friction_along: 0.5}\n- name: typo\n  scale: {friction_alng: 0.5}\n"
    )
    with pytest.raises(SystemExit) as exc:
        main(["robustness", str(gait), "--closed-loop", "--set", str(bad)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "variation 2 ('typo')" in err and "friction_alng" in err
    steep = tmp_path / "steep.yaml"
    steep.write_text("- name: steep\n  add: {slope_deg: 45}\n")
    with pytest.raises(SystemExit):
        main(["robustness", str(gait), "--closed-loop", "--set", str(steep)])
    assert "slope_deg" in capsys.readouterr().err
    good = tmp_path / "good.yaml"
    good.write_text(
        "- name: slippery\n  scale: {friction_along: 0.5, friction_across: 0.5}\n"
        "- name: 5 deg slope\n  add: {slope_deg: 5}\n  set: {slope_direction_deg: 90}\n"
    )
    main(["robustness", str(gait), "--closed-loop", "--set", str(good), "--json"])
    out = capsys.readouterr().out
    report = json.loads(out.strip().splitlines()[-1])
    assert "steers by conical" in out and "arrival s" in out
    assert report["steering"]["kind"] == "conical" and len(report["variations"]) == 2
    for row in report["variations"]:
        assert row["arrived"] and row["rel"] < 0.03, row
        assert {"end_error_m", "arrival_s", "max_cross_track_m", "saturated"} <= set(row)


def test_export_controller_writes_a_folder_the_follower_loads(tmp_path, capsys):
    gait = tmp_path / "undulate.csv"
    main(["gait", "undulate", "--out", str(gait)])
    out = tmp_path / "ctl"
    main(["export", str(gait), "--format", "controller", "--out", str(out)])
    assert {"controller.json", "commands.csv", "reference.csv", "gait.csv"} <= {p.name for p in out.iterdir()}
    f = PathFollower.load(out)
    assert f.rate == 20.0 and f.n_joints == 8 and f.steering.kind == "yaw_offset"
    assert f.reference.shape[1] == 2 and np.linalg.norm(f.reference[-1] - f.reference[0]) > 30
    assert "steers by yaw offset" in capsys.readouterr().out
    import yaml

    path = yaml.safe_load((out / "path.yaml").read_text())  # nav_msgs/Path, the follower's parameters above
    assert len(path["poses"]) > 100 and '# steering: {"kind":"yaw_offset"' in (out / "path.yaml").read_text()
    last = path["poses"][-1]["pose"]["position"]
    np.testing.assert_allclose([last["x"], last["y"]], f.reference[::2][-1], atol=1e-9)
    with pytest.raises(SystemExit):  # --closed-loop is the ros2 format's
        main(["export", str(gait), "--format", "csv", "--closed-loop", "--out", str(tmp_path / "x.csv")])
    assert "--closed-loop is for --format ros2" in capsys.readouterr().err
    (out / "commands.csv").write_text("nonsense")
    with pytest.raises(ValueError, match="not a controller directory"):
        PathFollower.load(out)


def test_pose_estimate_holds_at_its_rate_arrives_late_and_drifts():
    est = PoseEstimate(Sensing(pose_rate=10, pose_latency=0.05, heading_drift_deg_per_min=6.0), rate=20.0)
    given = [est(n, np.array([n, 0.0, 0.0])) for n in range(6)]
    xs = [g[0] for g in given]
    assert xs == [0, 0, 1, 1, 3, 3]  # refreshed every 2 steps, one step late
    assert given[4][2] == pytest.approx(math.radians(6.0) * 4 / 20 / 60)
    noisy = PoseEstimate(Sensing(pose_noise_m=0.02), rate=20.0, seed=3)
    spread = np.std([noisy(n, np.zeros(3))[0] for n in range(400)])
    assert 0.015 < spread < 0.025


def test_follower_config_refuses_bad_values():
    with pytest.raises(ValueError, match="look_ahead"):
        FollowerConfig(look_ahead=-1)


@pytest.mark.slow
def test_the_designer_plays_a_steerable_gait_closed_loop_and_says_what_it_did(checkpoint):
    """With Closed loop ticked, a replayed gait (the library's undulation as the baseline) gets its
    steering input and a closed-loop fan of 13 runs (nominal and 12 variations), its line and the
    steering plot; a gait no input steers (rolling) says so and draws no fan; unticking clears it."""
    from snakeloco.app.designer.scene import LOOP_COLOR

    from helpers import apply, connect_headless, quiet_server

    srv = quiet_server(checkpoint, closed_loop=True)
    client, d = connect_headless(srv)
    try:
        assert apply(d, d.controls.baseline, "undulate", 120)
        assert d.loop.done.wait(240), d.controls.loop.status.content
        status = d.controls.loop.status.content
        assert "steers by yaw offset" in status and "closed loop on other robots" in status, status
        assert len(d.loop.report["variations"]) == 12 and d.loop.report["nominal"]["arrived"]
        (fan,) = d.scene.loop_fan
        assert tuple(fan.colors.reshape(-1, 3)[0]) == LOOP_COLOR
        t, u = d.controls.loop.plot.data
        assert len(t) == len(u) > 100 and np.nanmax(np.abs(u)) > 0  # it steered
        assert (
            '# steering: {"kind":"yaw_offset"' in d.files.export_text()
        )  # kept with the gait it was found for
        assert apply(d, d.controls.baseline, "roll", 120)
        assert d.loop.done.wait(240)
        assert "no steering input" in d.controls.loop.status.content and not d.scene.loop_fan
        assert apply(d, d.controls.baseline, "undulate", 120)
        # A running closed loop shows its bar, and Cancel stops it (issue 71); this gait then plays open loop.
        job = d.controls.loop.job
        assert job.bar.visible and job.cancel.visible and not d.loop.done.is_set()
        for callback in job.cancel._impl.update_cb:  # what a click on Cancel runs
            callback(None)
        assert d.loop.done.is_set() and d.loop.worker.wait_idle(20), "the closed loop went on after Cancel"
        assert d.controls.loop.status.content.startswith("**Cancelled**") and not job.bar.visible
        d.controls.loop.enabled.value = False
        d.loop._toggled()
        assert not d.scene.loop_fan and "off" in d.controls.loop.status.content
    finally:
        client.close()
        srv.stop()


@pytest.mark.slow
def test_closed_loop_table_per_kind_counts_the_gaits_without_an_input():
    """``evaluate --closed-loop``'s table: per kind, the share with a steering input and the steered
    gaits' closed-loop errors; a kind no gait of which steers says so with None."""
    from snakeloco.app.cli.evaluate_report import closed_loop_lines
    from snakeloco.sim.robot.description import DEFAULT_ROBOT
    from snakeloco.sim.robot.variations import DEFAULT_SET
    from snakeloco.sim.scores.closed_loop import closed_loop_table

    commands = np.stack([PRESETS[n].gait.commands(DEFAULT_ROBOT) for n in ("sidewind", "roll")])
    table = closed_loop_table(
        commands, ["sidewind", "roll"], DEFAULT_ROBOT, 2, [DEFAULT_SET[0], DEFAULT_SET[5]]
    )
    assert table["all"]["n"] == 2 and table["all"]["steered"] == 0.5
    assert table["sidewind"]["steered"] == 1.0 and table["sidewind"]["closed_worst"] < 0.03
    assert table["roll"]["steered"] == 0.0 and table["roll"]["closed_median"] is None
    assert "    roll: 1 gaits, 0% steered; no gait steered" in closed_loop_lines(table)
