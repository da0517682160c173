"""Consistency scoring, evaluation, figures and the model benchmark on tiny inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from snakeloco.app.cli.evaluate_report import format_report
from snakeloco.app.cli.main import main
from snakeloco.model.evaluate import ConsistencyConfig, evaluate, physics_floor, repeated_channels
from snakeloco.model.vae.metrics import r2_overall, r2_per_channel
from snakeloco.sim.physics.backend import open_backend
from snakeloco.sim.scores.consistency import (
    compare,
    diversity,
    ensemble_spread,
    path_stats,
    perturbed_commands,
    where_it_went,
)

TWO = ConsistencyConfig(prior_samples=2, ensemble=3)
"""Two z_B per z_k mode, three replays each: the smallest check that has a spread."""


def test_perturbed_commands():
    rng = np.random.default_rng(0)
    u = rng.uniform(-2, 2, (2000, 8))
    ens = perturbed_commands(u, 8, 1e-3, seed=1)
    assert ens.shape == (8, 2000, 8)
    np.testing.assert_array_equal(ens[0], u)
    rel = (ens[1:] - u) / u
    assert rel.std() == pytest.approx(1e-3, rel=0.05)


def test_path_stats_and_compare():
    t = np.arange(500) / 5.0
    body = np.zeros((500, 6))
    body[:, 1] = 0.1 * t  # 0.1 m/s straight ahead
    body[:, 3] = 0.05 * t  # rolling
    s = path_stats(body, 5.0)
    assert s["path_length"] == pytest.approx(0.1 * t[-1])
    assert s["median_speed"] == pytest.approx(0.1)
    assert s["net_roll"] == pytest.approx(0.05 * t[-1])
    ens = np.stack([body, body * 1.01, body * 0.99])
    c = compare(body, ens, 5.0)
    assert c["path_length_err"] == pytest.approx(0.0)
    assert c["xy_r2"] == pytest.approx(1.0)
    assert c["final_inside"] == 1.0
    far = body.copy()
    far[:, 2] = 0.2 * t  # drifts sideways by 20 m: outside the ensemble's spread
    assert compare(far, ens, 5.0)["final_inside"] == 0.0
    spread = ensemble_spread(ens, 5.0)
    assert spread["final_spread"] == pytest.approx(np.sqrt(0.01**2), rel=1e-6)
    # Members 1.01x and 0.99x average to member 0: the floor is zero; skewed, it is their mean's error.
    assert spread["path_length_floor"] == pytest.approx(0.0, abs=1e-12)
    skewed = ensemble_spread(np.stack([body, body * 1.02, body * 1.04]), 5.0)
    assert skewed["path_length_floor"] == pytest.approx(0.03)
    assert skewed["net_roll_floor"] == pytest.approx(0.03)
    # The ensemble's std in the statistic's own units (fig9's bars), and relative to its mean.
    length = float(path_stats(body[None], 5.0)["path_length"][0])
    assert skewed["path_length_std"] == pytest.approx(length * np.std([1.0, 1.02, 1.04]))
    assert skewed["path_length_spread"] == pytest.approx(np.std([1.0, 1.02, 1.04]) / 1.02)
    assert c["path_length_floor"] == spread["path_length_floor"]


def _straight(heading_deg: float, speed: float, roll_rate: float = 0.0) -> np.ndarray:
    """A body series (500, 6) at 5 Hz moving straight at ``speed`` m/s in direction ``heading_deg``."""
    t = np.arange(500) / 5.0
    body = np.zeros((500, 6))
    body[:, 1] = speed * t * np.cos(np.radians(heading_deg))
    body[:, 2] = speed * t * np.sin(np.radians(heading_deg))
    body[:, 3] = roll_rate * t
    return body


def test_where_gaits_went_and_their_diversity():
    w = where_it_went(_straight(120.0, 0.2, roll_rate=0.1), 5.0)
    assert w["direction_deg"] == pytest.approx(120.0)
    assert w["displacement_m"] == pytest.approx(0.2 * 99.8)
    assert w["speed_bl_s"] == pytest.approx(0.2 / 0.95, rel=0.01)  # the body is 0.95 m long
    assert w["rolls"] == 1.0 and w["net_roll"] == pytest.approx(9.98)
    assert where_it_went(_straight(0.0, 0.2, roll_rate=0.05), 5.0)["rolls"] == 0.0  # 5 rad: under a turn
    rows = [where_it_went(_straight(h, v), 5.0) for h, v in [(10, 0.01), (80, 0.2), (-100, 0.03), (170, 0.3)]]
    d = diversity(rows)
    assert d["heading_quadrants"] == {"forward": 1, "left": 1, "backward": 1, "right": 1}
    assert sum(d["heading_hist_30deg"]) == 4
    assert d["share_travel_ge_2m"] == 0.75 and d["share_travel_ge_5m"] == 0.5  # 1 m, 20 m, 3 m, 30 m
    assert d["share_speed_ge_0.15_bl_s"] == 0.5
    assert d["share_rolling"] == 0.0
    assert d["speed_bl_s_quantiles"]["max"] == pytest.approx(0.3 * 99.8 / 99.8 / 0.95, rel=0.01)
    assert diversity([]) == {}
    # compare scores the decoded final position against the replay's distance travelled.
    ens = np.stack([_straight(0, 0.1), _straight(0, 0.1) * 1.01])
    c = compare(_straight(0, 0.09), ens, 5.0)
    assert c["final_error_rel"] == pytest.approx(0.1)
    assert c["direction_deg"] == pytest.approx(0.0)
    # A gait turning in place is scored on its net yaw: 9 rad decoded against 10 simulated.
    turning = _straight(0, 0.001)
    turning[:, 5] = np.linspace(0.0, 10.0, len(turning))
    decoded = turning.copy()
    decoded[:, 5] *= 0.9
    assert compare(decoded, np.stack([turning, turning]), 5.0)["net_yaw_error_rel"] == pytest.approx(0.1)


def test_physics_floor_scores_noisy_replays_of_the_records(tiny_dataset):
    runner = open_backend(None, 2)
    try:
        floor = physics_floor(tiny_dataset.commands.astype(np.float64), tiny_dataset.body_ds, runner, batch=3)
    finally:
        runner.close()
    assert floor["floor_records"] + floor["floor_broken"] == len(tiny_dataset.commands)
    assert set(floor["r2_body_floor_per_channel"]) == {
        "vertical",
        "forward",
        "sideways",
        "roll",
        "pitch",
        "yaw",
    }
    # A replay with 0.1% command noise is close to its record but, on these chaotic multisines, not equal.
    assert 0.0 < floor["r2_body_floor"] < 1.0
    assert all(np.isfinite(v) for v in floor["r2_body_floor_per_channel"].values())


def test_evaluate_end_to_end(checkpoint, tiny_dataset_path):
    report = evaluate(
        checkpoint, tiny_dataset_path, TWO.model_copy(update={"ensemble": 2}), workers=2, floor_records=2
    )
    assert report["floor_records"] + report["floor_broken"] == 2 and "r2_body_floor" in report
    for key in ("r2_shape", "r2_shape_zk_zero", "r2_body", "mmd_zb", "mmd_zb_null95", "inter_intra_ratio"):
        assert np.isfinite(report[key])
    assert set(report["r2_body_per_channel"]) == {"vertical", "forward", "sideways", "roll", "pitch", "yaw"}
    for mode in ("zk_zero", "zk_sampled"):
        c = report["consistency"][mode]
        assert c["n_gaits"] + c["n_broken"] == 2 and c["n_gaits"] >= 1  # the figures below are of gaits
        for k in ("vertical_std_err", "net_roll_floor"):
            lo, hi = c[k + "_ci90"]
            assert lo <= c[k] <= hi
        assert sum(c["diversity"]["heading_quadrants"].values()) == c["n_gaits"]
    text = format_report(report)
    assert (
        "consistency (zk_zero, z_B from the sampler" in text
        and "90% bootstrap interval of the median" in text
    )
    assert "physics' floor (2 records" in text and "where the replays went" in text
    assert (
        f"from z_B alone (z_k = 0, what the sliders draw at a record's z_B) {report['r2_shape_zk_zero']:.3f}"
        in text
    )


def test_median_interval_brackets_the_median_and_narrows_with_more_gaits():
    from snakeloco.model.vae.metrics import median_interval

    rng = np.random.default_rng(3)
    # Bimodal per-gait errors, like z_k = 0 vertical oscillation: most near 5%, a third near 60%.
    small = np.where(rng.random(64) < 0.33, 0.6, 0.05) + 0.01 * rng.standard_normal(64)
    large = np.where(rng.random(4096) < 0.33, 0.6, 0.05) + 0.01 * rng.standard_normal(4096)
    lo_s, hi_s = median_interval(small)
    lo_l, hi_l = median_interval(large)
    assert lo_s <= np.median(small) <= hi_s and lo_l <= np.median(large) <= hi_l
    assert hi_l - lo_l < 0.5 * (hi_s - lo_s)
    assert median_interval(small) == (lo_s, hi_s)  # seeded: the report is reproducible
    assert median_interval(np.full(10, 0.2)) == (0.2, 0.2)
    assert all(np.isnan(median_interval(np.array([np.nan]))))


def test_consistency_drops_broken_members_and_leaves_out_broken_gaits(checkpoint, monkeypatch):
    import dataclasses

    from snakeloco.model import evaluate as ev
    from snakeloco.model.api import load_pretrained
    from snakeloco.sim.physics.simulator import Simulator

    real = Simulator.simulate

    def flaky(self, commands):
        result = real(self, commands)
        failures = list(result.failures)
        failures[1] = "a perturbed member of gait 0 broke"
        failures[3] = "gait 1's own replay broke"
        return dataclasses.replace(result, failures=failures)

    monkeypatch.setattr(Simulator, "simulate", flaky)
    report = ev.consistency(load_pretrained(checkpoint), TWO, workers=2)
    for c in report.values():
        assert (c["n_gaits"], c["n_broken"], c["n_gaits_with_a_broken_member"]) == (1, 1, 2)
        assert c["gaits"][0]["ensemble_broken"] == 1.0
        assert c["broken_replay_fraction"] == pytest.approx(2 / 6)
        assert np.isfinite(c["final_spread"])  # the spread of the two clean members


def _evaluate_cli(data, checkpoint, *args) -> None:
    """``snakeloco evaluate --data DATA --checkpoint CHECKPOINT ARGS...`` in this process."""
    main(["evaluate", "--data", str(data), "--checkpoint", str(checkpoint), *map(str, args)])


@pytest.mark.slow
def test_figures_and_bench_commands(checkpoint, tiny_dataset_path, tmp_path, capsys):
    report = tmp_path / "report.json"
    _evaluate_cli(
        tiny_dataset_path, checkpoint, "--prior-samples", "2", "--ensemble", "2", "--json", "--report", report
    )
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "gaits" not in printed["consistency"]["zk_zero"]  # the summary line stays short
    written = json.loads(report.read_text())
    gaits = written["consistency"]["zk_zero"]["gaits"]
    assert len(gaits) == written["consistency"]["zk_zero"]["n_gaits"]
    assert all(np.isfinite(g["path_length_decoded"]) and g["path_length_simulated"] > 0 for g in gaits)
    assert set(written["stats_median_rel_err"]) == {"path_length", "median_speed", "vertical_std", "net_roll"}
    main(
        [
            "figures",
            "--data",
            str(tiny_dataset_path),
            "--checkpoint",
            str(checkpoint),
            "--out",
            str(tmp_path),
            "--report",
            str(report),
        ]
    )
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert sorted(pngs) == sorted(
        [
            "fig5_fit.png",
            "fig6_prior_sweep.png",
            "fig7_zk_samples.png",
            "fig8_joint_shapes.png",
            "fig9_consistency.png",
            "fig10_diversity.png",
        ]
    )
    assert all((tmp_path / p).read_bytes()[:4] == b"\x89PNG" for p in pngs)
    capsys.readouterr()
    main(["bench", "model", "--json", "--checkpoint", str(checkpoint), "--calls", "20"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 0 < result["decode_p50_ms"] <= result["decode_p95_ms"]


@pytest.mark.slow
def test_consistency_replays_are_written_reused_and_checked(
    checkpoint, tiny_dataset_path, tmp_path, monkeypatch, capsys
):
    from snakeloco.model import evaluate as ev
    from snakeloco.model.api import load_pretrained
    from snakeloco.sim import DatasetError

    model = load_pretrained(checkpoint)
    replays = tmp_path / "replays.npz"
    fresh = ev.consistency(model, TWO, workers=2, replays=replays)
    assert replays.exists()

    def no_simulation(self, commands):
        raise AssertionError("stored replays must be reused, not simulated again")

    from snakeloco.sim.physics.simulator import Simulator

    monkeypatch.setattr(Simulator, "simulate", no_simulation)
    reused = ev.consistency(model, TWO, workers=2, replays=replays)
    for mode in ev.ZK_MODES:
        assert reused[mode]["gaits"] == fresh[mode]["gaits"]
        assert reused[mode]["n_gaits"] + reused[mode]["n_broken"] == 2
    # Another draw, or other decoded gaits (another checkpoint's), is refused by name.
    with pytest.raises(DatasetError, match=r"replays of .*'seed': 0.*asks for .*'seed': 5"):
        ev.consistency(model, TWO.model_copy(update={"seed": 5}), replays=replays)
    other = load_pretrained(checkpoint)
    with torch.no_grad():
        other.net.child_out.bias.add_(0.05)  # every decoded shape moves
    with pytest.raises(DatasetError, match="decoded by another checkpoint"):
        ev.consistency(other, TWO, replays=replays)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(DatasetError, match=r"not a consistency-replays \.npz \(no zip archive"):
        ev.consistency(model, TWO, replays=bad)
    # The command says so and exits 2, without a traceback.
    with pytest.raises(SystemExit) as exc:
        _evaluate_cli(tiny_dataset_path, checkpoint, "--replays", bad)
    assert exc.value.code == 2 and "not a consistency-replays .npz" in capsys.readouterr().err


def test_reconstruction_reports_a_bin_the_data_do_not_excite_as_such(checkpoint, tiny_dataset):
    from snakeloco.app.cli.evaluate_report import format_report
    from snakeloco.model.api import load_pretrained
    from snakeloco.model.evaluate import reconstruction

    model = load_pretrained(checkpoint)
    shape, body = tiny_dataset.shape.astype(np.float64), tiny_dataset.body_ds.astype(np.float64)
    every = reconstruction(model, shape, body)
    assert (
        all(v is not None for v in every["r2_shape_per_freq"].values())
        and len(every["r2_shape_per_joint"]) == 8
    )
    shape[:, :, 1] *= 1e-4  # as a structured gait leaves most bins: ~1e-4 rad of harmonics
    unused = reconstruction(model, shape, body)["r2_shape_per_freq"]
    assert [k for k, v in unused.items() if v is None] == [str(round(float(model.freqs[1]), 3))]
    report = {"checkpoint": "c", "data": "d", "n_samples": 4, **reconstruction(model, shape, body)}
    report |= {"stats_median_rel_err": {}, "mmd_zb": 0.0, "mmd_zb_null95": 0.0, "active_units_zb": 1}
    report |= {"active_units_zj": 1, "inter_intra_ratio": 1.0}
    assert "Hz not excited" in format_report(report)


@pytest.mark.slow
def test_evaluate_reports_each_member_kind_of_the_sampler_gaits(member_checkpoint):
    from snakeloco.app.cli.evaluate_report import consistency_lines
    from snakeloco.model import load_pretrained
    from snakeloco.model.evaluate import ConsistencyConfig, consistency

    m = load_pretrained(member_checkpoint[0])
    report = consistency(m, ConsistencyConfig(prior_samples=3, ensemble=2, seed=4), workers=2)
    for mode in report.values():  # the undulation family: one kind, every draw of it
        kind = mode["per_kind"]["undulate"]
        assert set(mode["per_kind"]) == {"undulate"} and kind["n_drawn"] == 3
        assert kind["n_gaits"] == mode["n_gaits"] and kind["xy_r2"] == pytest.approx(
            np.median([g["xy_r2"] for g in mode["gaits"]])
        )
        assert sum(kind["diversity"]["heading_quadrants"].values()) == kind["n_gaits"]
    assert (
        sum(line.startswith("  kind undulate: 3 gaits (of 3 drawn)") for line in consistency_lines(report))
        == 2
    )


@pytest.mark.slow
def test_evaluate_reports_how_far_each_variation_moves_the_sampler_gaits(member_checkpoint):
    """``evaluate --robustness N``: the first N gaits replayed on the default set, per kind, against
    the ensemble's first noisy copy; each median as ``sim.scores.robustness`` reports the gaits one by one."""
    from snakeloco.app.cli.evaluate_report import consistency_lines
    from snakeloco.model import load_pretrained
    from snakeloco.model.evaluate import ConsistencyConfig, consistency
    from snakeloco.sim.robot.variations import DEFAULT_SET
    from snakeloco.sim.scores.robustness import robustness

    m = load_pretrained(member_checkpoint[0])
    cfg = ConsistencyConfig(prior_samples=3, ensemble=2, seed=4, zk_modes=("zk_zero",))
    table = consistency(m, cfg, workers=2, robustness=2)["zk_zero"]["robustness"]
    floor = "command noise 0.001"
    assert set(table) == {"all", "undulate"} and table["all"]["n"] == 2
    assert list(table["all"]["median"]) == [floor, *(v.name for v in DEFAULT_SET)]
    assert table["all"]["times_floor"][floor] == 1.0
    members = m.decode_members(m.sample_z_b(3, 4))[0][:2]
    one_by_one = [robustness(x.commands(m.robot), DEFAULT_SET[:2], robot=m.robot) for x in members]
    for k, v in enumerate(DEFAULT_SET[:2]):  # the body at 5 Hz ends 0.15 s before the 20 Hz one
        want = np.median([r["variations"][k]["rel"] for r in one_by_one])
        assert table["all"]["median"][v.name] == pytest.approx(want, rel=0.05, abs=0.01)
    lines = consistency_lines({"zk_zero": {**_EMPTY_MODE, "robustness": table}})
    assert any(line.strip().startswith("| floor friction x0.5 |") for line in lines)


_EMPTY_MODE = {"n_gaits": 0, "n_broken": 0, "final_inside_fraction": 0.0}


def test_body_r2_over_the_channels_physics_repeats():
    """A channel whose noisy replays do not repeat the record (a planar snake's roll: contact jitter)
    is left out of the repeated-channel body R², which is the mean of the others' standardised R²
    (``r2_overall`` over them)."""
    rng = np.random.default_rng(0)
    target = rng.normal(size=(40, 50, 6))
    pred = target + 0.1 * rng.normal(size=target.shape)
    pred[..., 3] = rng.normal(size=pred.shape[:2])  # roll: nothing of the record in it
    channels = ("vertical", "forward", "sideways", "roll", "pitch", "yaw")
    per = dict(zip(channels, r2_per_channel(target, pred).tolist(), strict=True))
    floor = dict.fromkeys(channels, 0.9) | {"roll": 0.01, "pitch": 0.49}
    report = {"r2_body_floor_per_channel": floor, "r2_body_raw_per_channel": per, "r2_body_per_channel": per}
    out = repeated_channels(report)
    assert out["body_channels_repeated"] == ["vertical", "forward", "sideways", "yaw"]
    keep = [0, 1, 2, 5]
    assert out["r2_body_raw_repeated"] == pytest.approx(r2_overall(target[..., keep], pred[..., keep]))
    assert out["r2_body_repeated"] > 0.95 > r2_overall(target, pred)
