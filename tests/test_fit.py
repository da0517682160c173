"""Fitting the robot to measured runs (``sim.fit.measured``, ``sim.fit.fit_robot``, ``snakeloco fit-robot``, the
designer's "Your robot" folder): docs/calibration.md."""

from __future__ import annotations

import json

import numpy as np
import pytest

from snakeloco.app.cli.main import main
from snakeloco.app.export.gait_csv import library_gait_csv
from snakeloco.sim.fit.fit_robot import FitConfig, fit_robot
from snakeloco.sim.fit.measured import MeasuredRunError, read_measured_run, write_measured_run
from snakeloco.sim.gaits.library import BASE_GAITS, PRESETS
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT, Robot, load_robot

QUICK = FitConfig(params=("friction_across", "servo_kp"), popsize=6, generations=9, horizons=(20.0, 40.0))
"""A fit small enough for a test: two fields, 40 s runs."""


def measured_text(
    robot: Robot, gait: str, seconds: float = 40.0, seed: int = 0, noise: bool = True, joints: bool = False
) -> str:
    """A synthetic measured run: ``gait`` replayed on ``robot``, sampled at 50 Hz with 1 mm and 0.5 deg
    noise, in a world frame of its own (shifted and turned, as a motion-capture frame is); with
    ``joints`` the servos' joint angles too (0.5 deg noise)."""
    replayed = Simulator(workers=1, robot=robot).replay(PRESETS[gait].gait.commands(DEFAULT_ROBOT))
    body = replayed.body
    rng = np.random.default_rng(seed)
    t = np.arange(0, seconds, 0.02)
    ts = np.arange(len(body)) / 20
    xy = np.stack([np.interp(t, ts, body[:, k]) for k in (1, 2)], axis=1)
    yaw = np.interp(t, ts, body[:, 5])
    angles = np.stack([np.interp(t, ts, a) for a in replayed.joint_angles.T], axis=1) if joints else None
    if noise:
        xy += rng.normal(0, 0.001, xy.shape)
        yaw += rng.normal(0, np.radians(0.5), yaw.shape)
        if joints:
            angles += rng.normal(0, np.radians(0.5), angles.shape)
    turn = 0.7  # the world frame: turned and shifted
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    return write_measured_run(t, xy @ rot.T + [3.0, -1.0], yaw + turn, gait=f"{gait}.csv", joints=angles)


def test_a_measured_run_is_read_in_its_start_frame():
    truth = Simulator(workers=1).replay(PRESETS["roll"].gait.commands(DEFAULT_ROBOT)).body
    run = read_measured_run(measured_text(DEFAULT_ROBOT, "roll", noise=False), "roll run", 8)
    assert run.gait == "roll.csv" and run.joints is None
    ts = np.arange(len(truth)) / 20
    last = [np.interp(39.98, ts, truth[:, k]) for k in (1, 2, 5)]  # the run's last row, at 50 Hz
    np.testing.assert_allclose(run.xy[-1], last[:2], atol=1e-6)
    assert abs(run.yaw[-1] - last[2]) < 1e-6


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("time_s,x,y\n0,0,0\n1,0,0\n", "header must start 'time_s,x,y,yaw'"),
        ("time_s,x,y,yaw\n0,0,0,0\n0.5,0,0,0\n0.4,0,0,0\n", "line 4: time 0.4 s does not come after 0.5 s"),
        ("time_s,x,y,yaw\n0,0,0,0\n0.1,1200,0,0\n", "line 3: the body moves at 1.2e+04 m/s"),
        ("time_s,x,y,yaw\n0,0,0,0\n0.02,0,0,45\n", "yaw must be radians (degrees?)"),
        (
            "time_s,x,y,yaw,joint_1,joint_2\n0,0,0,0,0,0\n1,0,0,0,0,0\n",
            "2 measured joints, but the gait has 8",
        ),
        ("time_s,x,y,yaw\n0,0,0,0\n0.1,zero,0,0\n", "line 3: '0.1,zero,0,0' is not a row of numbers"),
        ("time_s,x,y,yaw\n0,0,0,0\n", "1 data rows"),
    ],
)
def test_a_bad_measured_run_is_refused_with_its_line_and_reason(text, reason):
    with pytest.raises(MeasuredRunError) as exc:
        read_measured_run(text, "run.csv", n_joints=8)
    assert reason in str(exc.value) and str(exc.value).startswith("run.csv")


def test_a_run_shorter_than_a_cycle_or_of_another_gait_is_refused():
    short = read_measured_run(measured_text(DEFAULT_ROBOT, "roll", seconds=1.0), "short.csv")
    with pytest.raises(MeasuredRunError, match=r"short.csv: the run lasts 0.98 s, shorter than one cycle"):
        fit_robot([(PRESETS["roll"].gait.commands(DEFAULT_ROBOT), short)], DEFAULT_ROBOT, QUICK)
    run = read_measured_run(measured_text(DEFAULT_ROBOT, "roll", seconds=5.0), "run.csv")
    with pytest.raises(MeasuredRunError, match="the gait has 6 joints, the robot snakeloco-8 8"):
        fit_robot([(PRESETS["roll"].gait.commands(DEFAULT_ROBOT)[:, :6], run)], DEFAULT_ROBOT, QUICK)


def test_bench_fit_fits_by_default_the_runs_the_library_names():
    """The command line's default (``app.bench.options``, which imports no MuJoCo) is the library's
    fit set, and every gait in it is a library gait."""
    from snakeloco.app.bench.options import BenchFit
    from snakeloco.sim.fit.bench import FIT_GAITS

    assert BenchFit().gaits == FIT_GAITS and set(FIT_GAITS) <= set(PRESETS)


@pytest.mark.slow
def test_a_perturbed_robot_is_recovered_and_noise_alone_stays_within_the_uncertainty():
    truth = Robot(friction_across=0.6 * 1.25, servo_kp=30 * 0.75)
    pairs = [
        (PRESETS[g].gait.commands(DEFAULT_ROBOT), read_measured_run(measured_text(truth, g, seed=i), g))
        for i, g in enumerate(("sidewind", "roll"))
    ]
    sim = Simulator(workers=2)
    report = fit_robot(pairs, DEFAULT_ROBOT, QUICK, sim, advise=False)
    for name in QUICK.params:
        p = report["params"][name]
        want = getattr(truth, name)
        assert abs(p["fitted"] / want - 1) < 0.15, (name, p)
    assert all(a["end_m"] < b["end_m"] for a, b in zip(report["after"], report["before"], strict=True))
    # The nominal robot's own runs, measured with noise: the fit stays at nominal within what it reports.
    nominal = [
        (
            PRESETS[g].gait.commands(DEFAULT_ROBOT),
            read_measured_run(measured_text(DEFAULT_ROBOT, g, seed=7 + i), g),
        )
        for i, g in enumerate(("sidewind", "roll"))
    ]
    report = fit_robot(nominal, DEFAULT_ROBOT, QUICK, sim, advise=False)
    for name, p in report["params"].items():
        assert p["low"] <= getattr(DEFAULT_ROBOT, name) <= p["high"], (name, p)
    sim.close()


def test_measured_joint_angles_enter_the_loss_and_their_error_is_reported():
    """The servos' tracking: on a robot with softer servos the replayed joint angles lag the
    measured ones less than the nominal robot's do; a run without joints is scored on its path alone."""
    from snakeloco.sim.fit.fit_robot import RobotFit

    soft = Robot(servo_kp=30 * 0.6)
    with_joints = read_measured_run(measured_text(soft, "roll", seconds=10.0, joints=True), "run.csv", 8)
    without = read_measured_run(measured_text(soft, "roll", seconds=10.0), "run.csv", 8)
    commands = PRESETS["roll"].gait.commands(DEFAULT_ROBOT)
    cfg = FitConfig(params=("servo_kp",))
    sim = Simulator(workers=2)
    try:
        fit = RobotFit([(commands, with_joints)], DEFAULT_ROBOT, cfg, sim)
        fit.set_horizon(10.0)
        nominal, right = fit.replay([DEFAULT_ROBOT, soft])
        extra = [fit.run_loss(r[0], with_joints) - fit.run_loss(r[0], without) for r in (nominal, right)]
        # kp x0.6: ~1.2 deg RMS of tracking misfit beyond the run's 0.5 deg noise; the right servos
        # track as measured: what is left is the noise, which the loss takes out.
        assert extra[0] > 5 * extra[1] >= 0 and extra[0] > cfg.joint_weight * np.radians(0.8)
        assert fit.noise[id(with_joints)] == pytest.approx(np.radians(0.5), rel=0.05)
        errors = fit.path_errors(soft)
        assert errors[0]["joint_rms_rad"] == pytest.approx(np.radians(0.5), rel=0.1)
        no_joints = FitConfig(params=("servo_kp",), joint_weight=0.0)
        plain = RobotFit([(commands, with_joints)], DEFAULT_ROBOT, no_joints, sim)
        plain.set_horizon(10.0)
        assert plain.run_loss(nominal[0], with_joints) == pytest.approx(fit.run_loss(nominal[0], without))
    finally:
        sim.close()


@pytest.mark.slow
def test_fit_robot_writes_a_robot_description_that_loads_and_replays(tmp_path, capsys):
    gait = tmp_path / "roll.csv"
    gait.write_text(library_gait_csv("roll", robot=DEFAULT_ROBOT))
    run = tmp_path / "run.csv"
    run.write_text(measured_text(Robot(servo_kp=24.0), "roll", seconds=20.0))
    out = tmp_path / "fitted.yaml"
    main(
        [
            *("fit-robot", "--measured", str(run), "--out", str(out), "--params", "servo_kp"),
            *("--generations", "4", "--workers", "2", "--json"),
        ]
    )
    report = json.loads(capsys.readouterr().out.splitlines()[-1])
    fitted = load_robot(out)
    assert fitted.servo_kp == pytest.approx(report["params"]["servo_kp"]["fitted"])
    assert fitted.friction_along == DEFAULT_ROBOT.friction_along  # only what was asked for moves
    assert (tmp_path / "fitted.png").stat().st_size > 10_000
    Simulator(workers=1, robot=fitted).replay(PRESETS["roll"].gait.commands(DEFAULT_ROBOT))  # it replays
    with pytest.raises(SystemExit):
        main(["fit-robot", "--measured", str(run), "--out", str(out), "--params", "colour"])
    assert "--params colour: fit physical fields only" in capsys.readouterr().err


@pytest.mark.slow
def test_the_designer_fits_a_measured_run_and_replays_on_the_fitted_robot(checkpoint):
    from snakeloco.app.bench.users.load_driver import wait_until

    from helpers import connect_headless, quiet_server

    srv = quiet_server(checkpoint)
    client, d = connect_headless(srv)
    try:
        body = Simulator(workers=1, robot=Robot(servo_kp=24.0)).replay(d.decoded.commands).body
        t = np.arange(0, 20, 0.02)
        ts = np.arange(len(body)) / 20
        text = write_measured_run(
            t, np.stack([np.interp(t, ts, body[:, k]) for k in (1, 2)], axis=1), np.interp(t, ts, body[:, 5])
        )
        assert d.fit.import_bytes("bad.csv", b"time_s,x\n") is None
        assert d.fit.import_bytes("run.csv", text.encode()) is not None
        assert d.fit.line is not None and "Measured run" in d.fit.controls.status.content
        # A long fit shows its bar and stops at Cancel (issue 71), the robots offered unchanged.
        d.fit.config = FitConfig(params=("servo_kp",), popsize=4, generations=30, horizons=(20.0,))
        d.fit.request()
        job = d.fit.controls.job
        assert job.bar.visible and job.cancel.visible
        assert wait_until(lambda: job.bar.value > 0 and "generation" in d.fit.controls.status.content, 120)
        for callback in job.cancel._impl.update_cb:  # what a click on Cancel runs
            callback(None)
        assert d.fit.worker.wait_idle(20), "the fit went on after Cancel"
        assert d.fit.controls.status.content.startswith("**Cancelled**") and not job.bar.visible
        assert d.fit.report is None and d.fit.controls.robot.options == ("nominal",)
        d.fit.config = FitConfig(params=("servo_kp",), popsize=4, generations=2, horizons=(20.0,))
        d.fit.request()
        assert d.fit.worker.wait_idle(300)
        assert d.fit.report is not None and "Fitted" in d.fit.controls.status.content
        label = next(o for o in d.fit.controls.robot.options if o.startswith("fitted"))
        version = d.fit.choose(label)
        assert version is not None and d.wait_idle(120)
        assert d.session.robot == d.fit.robots[label] != DEFAULT_ROBOT
        assert "trained on the nominal robot" in d.controls.readout.content
    finally:
        client.close()
        srv.stop()


@pytest.mark.slow
def test_bench_fit_with_joint_angles_reports_every_field_and_the_held_out_gaits(capsys):
    """``bench fit --joints`` on one robot and one generation: the figures are there and consistent
    (it measures the fit; tests above check the fit itself)."""
    main(["bench", "fit", "--robots", "1", "--generations", "1", "--joints", "--workers", "2", "--json"])
    out = capsys.readouterr().out.splitlines()
    result = json.loads(out[-1])
    assert result["joints"] is True and any(
        line.startswith("fitted runs turn, sidewind, undulate, with measured joint angles") for line in out
    )
    (row,) = result["robots"]
    assert set(row["params"]) == {"friction_along", "friction_across", "servo_kp"}
    for name, p in row["params"].items():
        assert p["error_rel"] == pytest.approx(p["fitted"] / row["truth"][name] - 1)
    # Every library gait the fit did not see is held out, and a slow undulation.
    assert set(row["held_out"]) == (set(PRESETS) - {"turn", "sidewind", "undulate"}) | {"slow undulation"}
    assert set(result["held_out_per_gait"]) == set(row["held_out"])
    # The floor: robots 3% off the truth do not replay its ends (a zero would say they were not applied).
    assert all(h["near_rel"] > 0 for h in row["held_out"].values())
    assert result["held_out_near_rel_median"] == pytest.approx(
        np.median([h["near_rel"] for h in row["held_out"].values()])
    )
    assert result["determined"] == sum(p["determined"] for p in row["params"].values())


@pytest.mark.slow
def test_bench_fit_single_runs_table_every_gait_on_every_robot(capsys):
    """``bench fit --single``: each library gait's run fitted alone, a row per robot, with joint
    angles measured when asked (what one run determines, docs/calibration.md)."""
    main(
        [
            "bench",
            "fit",
            "--single",
            "--robots",
            "2",
            "--generations",
            "1",
            "--joints",
            "--workers",
            "2",
            "--json",
        ]
    )
    out = capsys.readouterr().out.splitlines()
    result = json.loads(out[-1])
    assert result["joints"] is True and len(result["truths"]) == 2
    assert set(result["single_runs"]) == set(BASE_GAITS)
    for gait, rows in result["single_runs"].items():
        assert len(rows) == 2
        assert any(line.startswith(f"{gait} alone, per robot: friction_along") for line in out)
        for row, truth in zip(rows, result["truths"], strict=True):
            assert set(row) == set(truth) == {"friction_along", "friction_across", "servo_kp"}
            assert all(p["rel_uncertainty"] > 0 for p in row.values())
