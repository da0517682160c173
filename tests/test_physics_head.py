"""The member path head conditioned on the physics (model/heads/physics_head.py): its inputs, its fit, its
files, and the predicted Variations fan the designer draws and the replays check."""

from __future__ import annotations

import math

import numpy as np
import pytest

from snakeloco.model.heads.physics_head import PHYSICS_FEATURES, mirror_features, physics_features
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.robot.variations import DEFAULT_SET
from snakeloco.sim.scores.robustness import prediction_errors, prediction_line, summarise


def test_physics_features_are_zero_on_the_nominal_robot_and_a_mirror_negates_the_slope_to_the_left():
    robots = [DEFAULT_ROBOT, *(v.apply(DEFAULT_ROBOT) for v in DEFAULT_SET)]
    f = physics_features(robots, DEFAULT_ROBOT)
    assert f.shape == (len(robots), len(PHYSICS_FEATURES)) and not f[0].any()
    named = {v.name: row for v, row in zip(DEFAULT_SET, f[1:], strict=True)}
    col = {name: i for i, name in enumerate(PHYSICS_FEATURES)}
    friction = named["floor friction x0.5"]
    assert friction[col["friction_along"]] == friction[col["friction_across"]] == pytest.approx(math.log(0.5))
    assert named["latency 30 ms"][col["latency"]] == pytest.approx(0.03)
    ahead, left = named["5 deg slope uphill ahead"], named["5 deg slope uphill left"]
    assert ahead[col["slope_ahead"]] == pytest.approx(5) and abs(ahead[col["slope_left"]]) < 1e-12
    assert left[col["slope_left"]] == pytest.approx(5) and abs(left[col["slope_ahead"]]) < 1e-9
    # Every variation of the default set is told apart from every other.
    assert len({tuple(np.round(r, 9)) for r in f}) == len(robots)
    m = mirror_features(left)
    assert m[col["slope_left"]] == pytest.approx(-5) and np.array_equal(
        np.delete(m, col["slope_left"]), np.delete(left, col["slope_left"])
    )


def _straight(end: tuple[float, float]) -> np.ndarray:
    body = np.zeros((50, 6))
    body[:, 1], body[:, 2] = np.linspace(0, end[0], 50), np.linspace(0, end[1], 50)
    return body


def test_the_prediction_line_gives_the_median_and_the_worst_gap_over_the_replayed_distance():
    variations = DEFAULT_SET[:3]
    replayed = summarise(
        _straight((4, 0)),
        variations,
        [_straight((2, 0)), _straight((4, 0)), _straight((0.1, 0))],
        [None, None, None],
    )
    # Predicted 0.2 m off on the first (10% of 2 m), exact on the second; the third broke.
    predicted = summarise(
        _straight((4, 0)), variations, [_straight((2, 0.2)), _straight((4, 0)), _straight((1, 0))], [None] * 3
    )
    replayed["variations"][2]["failure"] = "thrown"
    errors = prediction_errors(predicted, replayed)
    assert errors[:2] == pytest.approx([0.1, 0.0]) and np.isnan(errors[2])
    line = prediction_line(predicted, replayed)
    assert line == f"predicted within 5% (median; worst 10%: {variations[0].name})"


@pytest.fixture(scope="module")
def physics_checkpoint(member_checkpoint, tmp_path_factory):
    """The tiny structured checkpoint with a physics head fitted on a few replays; the summary and
    the replays counted on the way."""
    from snakeloco.model.heads.physics_fit import fit_physics_head
    from snakeloco.model.options import PhysicsHeadConfig
    from snakeloco.model.replays import Fit

    out = tmp_path_factory.mktemp("physics")
    cfg = PhysicsHeadConfig(samples=2, sampled=1, eval_samples=1, chunk=2, epochs=3, hidden=16)
    done: list[int] = []
    summary = fit_physics_head(
        Fit(member_checkpoint[0], None, out, workers=2, progress=done.append, log=None), cfg
    )
    return out, cfg, summary, sum(done)


@pytest.mark.slow
def test_a_physics_head_is_fitted_resumed_loaded_and_its_fan_drawn_and_checked_in_the_designer(
    member_checkpoint, physics_checkpoint
):
    from snakeloco.model.api import load_pretrained
    from snakeloco.model.checkpoint import CheckpointError
    from snakeloco.model.heads.physics_fit import NOISE, fit_physics_head, replay_count
    from snakeloco.model.heads.physics_head import PHYSICS_HEAD_WEIGHTS
    from snakeloco.model.replays import Fit

    from helpers import connect_headless, quiet_server

    checkpoint, _ = member_checkpoint
    out, cfg, summary, done = physics_checkpoint
    assert done == replay_count(cfg) == 2 * 2 * (1 + len(DEFAULT_SET) + 1) + 2 + len(DEFAULT_SET)
    names = {"nominal", NOISE, *(v.name for v in DEFAULT_SET)}
    assert set(summary["eval"]["by_variation"]) == names
    assert summary["eval"]["all"]["n"] == len(DEFAULT_SET) - summary["eval"]["broken"]
    # How far each variation moved the scored member, against the command noise's own move.
    table = summary["eval"]["robustness"]
    assert set(table["all"]["median"]) == names - {"nominal"} and table["all"]["n"] == 1
    assert table["all"]["times_floor"][NOISE] == 1.0
    # Again: every chunk is read back, nothing replayed.
    again: list[int] = []
    resumed = fit_physics_head(Fit(checkpoint, None, out, workers=2, progress=again.append, log=None), cfg)
    assert sum(again) == 0
    assert (
        resumed["fit_s"] == summary["fit_s"] and resumed["eval"]["all"] == summary["eval"]["all"]
    )  # not refitted
    model = load_pretrained(out)
    assert model.physics_head is not None and load_pretrained(checkpoint).physics_head is None
    member = model.decode_members(model.sample_z_b(1, 0))[0][0]
    paths = model.members.predict_variation_paths(member, [v.apply(model.robot) for v in DEFAULT_SET])
    assert paths.shape == (len(DEFAULT_SET), 500, 6) and np.isfinite(paths).all()

    # A robot inside the physics it was trained on (a fitted robot, say) is covered; far outside, not.
    from snakeloco.sim.robot.variations import Variation

    slippery = Variation(name="slippery", scale={"friction_along": 0.7, "friction_across": 0.7}).apply(
        model.robot
    )
    icy = Variation(name="icy", scale={"friction_along": 0.05, "friction_across": 0.05}).apply(model.robot)
    assert (
        model.members.covers(model.robot) and model.members.covers(slippery) and not model.members.covers(icy)
    )
    assert "physics head's prediction" in model.robot_warning(slippery)
    assert "physics head" not in model.robot_warning(icy)

    # Served on the covered robot: the model's path is the physics head's for it, the fan its variations'.
    srv = quiet_server(out, robot=slippery, variations=True)
    client, d = connect_headless(srv, timeout=180)  # replay, ensemble and 12 variations on 2 cores
    try:
        assert d.predicted[0] == d.version and d.scene.predicted_fan.visible
        assert d.variations[0] == d.version
        on_it = model.members.predict_variation_paths(d.decoded.member, [slippery])[0]
        assert np.allclose(d.decoded.body_ds, on_it, atol=1e-5)
        assert "physics head" in d.controls.readout.content
        text = d.controls.readout.content.replace("&#x27;", "'")
        assert prediction_line(d.predicted[1], d.variations[1]) in text
    finally:
        client.close()
        srv.stop()

    broken = _copy_beside(out)
    (broken / PHYSICS_HEAD_WEIGHTS).write_bytes(b"not safetensors")
    with pytest.raises(CheckpointError, match=PHYSICS_HEAD_WEIGHTS):
        load_pretrained(broken)


def _copy_beside(src):
    """A copy of a checkpoint folder beside it (to break without touching the shared one)."""
    import shutil

    dst = src.parent / (src.name + "-copy")
    shutil.copytree(src, dst, dirs_exist_ok=True)
    return dst


def test_a_robust_search_pays_for_a_nominal_miss_beyond_most_of_the_tolerance():
    """The fan's cost alone let the search trade the nominal error for robustness (12-38% nominal
    misses on 10 m targets); beyond 70% of the tolerance each metre of nominal miss costs ten."""
    from snakeloco.model.design.config import DesignConfig, Target
    from snakeloco.model.design.targets import GUARD_SHARE, NOMINAL_GUARD, fan_cost

    class Fan:  # the worst predicted miss, as PredictedFan's
        def cost(self, ends, target):
            return np.hypot(ends[..., 0] - target.forward, ends[..., 1] - target.sideways).max(axis=1)

    target, cfg = Target(forward=10.0, sideways=0.0), DesignConfig()
    tol = cfg.tolerance_for(target)  # 1 m
    ends = np.array([[[9.0, 0.0], [11.0, 0.0]], [[10.0, 0.0], [10.0, 3.0]]])  # worst 1 m, 3 m
    inside = fan_cost(Fan(), ends, target, np.array([0.5, 0.5]), cfg)
    assert inside == pytest.approx([1.0, 3.0])  # within 70% of the tolerance: the fan's cost alone
    outside = fan_cost(Fan(), ends, target, np.array([GUARD_SHARE * tol + 0.3, 0.0]), cfg)
    assert outside == pytest.approx([1.0 + NOMINAL_GUARD * 0.3, 3.0])
    # The robust gait that misses the target by 1 m on the nominal robot now loses to the one on it.
    assert outside[0] > outside[1]


@pytest.mark.slow
def test_robust_design_searches_with_the_predicted_fan_and_reports_it_beside_the_replays(physics_checkpoint):
    from snakeloco.model.api import load_pretrained
    from snakeloco.model.design.config import DesignConfig, Target
    from snakeloco.model.design.robust import PredictedFan, robust_design, worst_case
    from snakeloco.model.design.search import design
    from snakeloco.sim.physics.backend import open_backend

    model = load_pretrained(physics_checkpoint[0])
    fan = PredictedFan(model, [v.apply(model.robot) for v in DEFAULT_SET])
    z = model.sample_z_b(3, 1)
    ends = fan.ends(z)
    assert ends.shape == (3, len(DEFAULT_SET), 2)
    target = Target(forward=0.5, sideways=0.2)
    assert fan.cost(ends, target) == pytest.approx(fan.misses(ends, target).max(axis=1))
    # The fan's ends are the physics head's paths' ends, member by member.
    member = model.decode_members(z[:1])[0][0]
    paths = model.members.predict_variation_paths(member, fan.robots)
    assert ends[0] == pytest.approx(paths[:, -1, 1:3] - paths[:, 0, 1:3])
    cfg = DesignConfig(screen=32, starts=2, generations=3, population=6, candidates=1, rounds=1)
    result = robust_design(model, target, cfg, workers=2)
    assert result.extra["searched_with"] == "predicted variations fan"
    for r in result.extra["robust"]:
        assert r["replayed"] == len(DEFAULT_SET) and r["predicted_worst_m"] >= 0
    # The nominal design's answer competed: the robust answer ranks no worse than it by the same key
    # (meets the target on the nominal robot first, then the replayed worst case).
    runner = open_backend(None, 2, robot=model.robot)
    try:
        plain = design(model, target, cfg, runner=runner).candidates[0]
        plain_worst = worst_case([plain], model, target, runner)[0]["worst_m"]
    finally:
        runner.close()
    tol, top = result.tolerance_m, result.candidates[0]
    key = (top.error_m > tol, result.extra["robust"][0]["worst_m"])
    assert key <= (plain.error_m > tol, plain_worst + 1e-9)
    nominal = robust_design(model, target, cfg, workers=2, predicted=False)
    assert nominal.extra["searched_with"] == "nominal path"


@pytest.mark.slow
def test_bench_robust_judges_nominal_and_robust_answers_by_the_same_replayed_worst_case(
    physics_checkpoint, capsys
):
    from snakeloco.app.cli.main import main

    out = physics_checkpoint[0]
    args = ["bench", "robust", "--checkpoint", str(out), "--targets", "1", "--reach", "0.3", "0.6"]
    main([*args, "--candidates", "1", "--rounds", "1", "--workers", "2", "--json"])
    lines = capsys.readouterr().out.splitlines()
    r = __import__("json").loads(lines[-1])
    row = r["rows"][0]
    assert r["searched_with"] == "predicted variations fan" and 0.3 <= row["distance_m"] <= 0.6
    assert (
        row["nominal_worst_rel"] >= row["nominal_error_rel"]
        and row["robust_worst_rel"] >= row["robust_error_rel"]
    )
    assert row["worst_ratio"] == pytest.approx(row["robust_worst_rel"] / row["nominal_worst_rel"])
    # The nominal answer competes in the robust design: where it meets the target (the tolerance is
    # 0.25 m within 2.5 m), the robust answer's replayed worst case is never worse than its.
    if row["nominal_error_rel"] * row["distance_m"] <= 0.25:
        assert row["worst_ratio"] <= 1.0 + 1e-9
    assert any(line.startswith("worst robust / nominal: median") for line in lines)


@pytest.mark.slow
def test_design_on_a_covered_robot_searches_on_the_physics_heads_paths_for_it(
    physics_checkpoint, tmp_path, capsys
):
    from snakeloco.app.cli.main import main
    from snakeloco.model.api import load_pretrained
    from snakeloco.model.heads.physics_head import OnRobot
    from snakeloco.sim.robot.variations import Variation

    out = physics_checkpoint[0]
    model = load_pretrained(out)
    slippery = Variation(name="slippery", scale={"friction_along": 0.7, "friction_across": 0.7}).apply(
        model.robot
    )
    icy = Variation(name="icy", scale={"friction_along": 0.05, "friction_across": 0.05}).apply(model.robot)
    with pytest.raises(ValueError, match="does not cover"):
        OnRobot(model, icy)
    on = OnRobot(model, slippery)
    z = model.sample_z_b(2, 3)
    shape, body = on.decode(z)
    members = model.decode_members(z)[0]
    assert np.allclose(
        body[1], model.members.predict_variation_paths(members[1], [slippery])[0], atol=1e-4
    )  # batch of 2 vs 1
    assert np.array_equal(shape, model.decode(z)[0]) and on.z_b_dim == model.z_b_dim
    (tmp_path / "slippery.yaml").write_text(slippery.to_yaml())
    quick = "--screen 32 --starts 2 --generations 3 --population 6 --candidates 1 --rounds 1".split()
    target = [
        "--forward",
        "0.4",
        "--sideways",
        "0.1",
        "--checkpoint",
        str(out),
        "--robot",
        str(tmp_path / "slippery.yaml"),
    ]
    main(["design", *target, *quick, "--out", str(tmp_path / "d"), "--workers", "2", "--json"])
    report = __import__("json").loads(capsys.readouterr().out.splitlines()[-1])
    assert (
        report["searched_on"] == f"the physics head's paths on {slippery.name}"
        and report["robot"] == slippery.name
    )


def test_a_residual_physics_head_keeps_the_member_heads_path_at_nominal_physics_and_round_trips(tmp_path):
    import torch

    from snakeloco.model.heads.member_path import (
        MemberHeadConfig,
        MemberPathHead,
        ResidualHead,
        fit_member_head,
    )
    from snakeloco.model.heads.physics_head import load_physics_head, save_physics_head

    rng = np.random.default_rng(0)
    support = np.ones((2, 1), bool)
    n_in, n_phys = 4, len(PHYSICS_FEATURES)
    base_cfg = MemberHeadConfig(
        support=support.tolist(), input_mean=[0.0] * n_in, input_std=[1.0] * n_in, hidden=8, layers=1, steps=5
    )
    torch.manual_seed(0)
    base = MemberPathHead(base_cfg).requires_grad_(False).eval()
    before = {k: v.clone() for k, v in base.state_dict().items()}
    x = rng.standard_normal((24, n_in + n_phys))
    x[:6, n_in:] = 0.0  # nominal robots
    y = rng.standard_normal((24, 5, 6))
    head, _ = fit_member_head(
        x[:18],
        y[:18],
        x[18:],
        y[18:],
        support,
        epochs=2,
        hidden=8,
        layers=1,
        physics=PHYSICS_FEATURES,
        base=base,
        log=None,
    )
    assert isinstance(head, ResidualHead) and head.cfg.residual
    assert all(torch.equal(before[k], v) for k, v in base.state_dict().items())  # the member head stays
    t = torch.as_tensor(x, dtype=torch.float32)
    with torch.no_grad():
        at_nominal, on_base = head(t[:6]), base(t[:6, :n_in])
        varied = head(t[6:])
    assert torch.allclose(at_nominal, on_base, atol=1e-6)  # zero physics: exactly the member head's path
    assert not torch.allclose(varied, base(t[6:, :n_in]), atol=1e-6)
    save_physics_head(tmp_path, head)
    again = load_physics_head(tmp_path, base)
    with torch.no_grad():
        assert torch.equal(again(t), head(t))
    from snakeloco.model.checkpoint import CheckpointError

    with pytest.raises(CheckpointError, match="corrects a member head"):
        load_physics_head(tmp_path)


@pytest.mark.slow
def test_the_robust_library_search_ranks_the_physics_heads_members_by_their_replayed_worst_case(
    physics_checkpoint, monkeypatch, capsys
):
    """``gait --search-robust``: every member the head was trained and scored on, its worst case
    read from its replays on the default set; the chosen gait per sector confirmed by replaying it."""
    from snakeloco.model.design import library as robust_library
    from snakeloco.model.heads.physics_fit import PHYSICS_GAITS
    from snakeloco.sim.scores.robustness import robustness

    out, cfg, _, _ = physics_checkpoint
    found = robust_library.candidates(out)
    assert len(found) == 2 * cfg.samples + cfg.eval_samples  # none of the tiny draws broke
    assert {c["draw"] for c in found} == {"train", "eval"}
    one = found[0]  # its worst case at 5 Hz is what the library's 20 Hz replays say, to the last 0.15 s
    again = robustness(one["member"].commands(DEFAULT_ROBOT), DEFAULT_SET, robot=None)
    assert one["worst"] == again["worst"] and one["worst_rel"] == pytest.approx(
        again["worst_rel"], rel=0.05, abs=0.01
    )
    named = robust_library.candidates(out, out / PHYSICS_GAITS)  # the folder named: the same rows
    assert [(c["kind"], c["worst_rel"]) for c in named] == [(c["kind"], c["worst_rel"]) for c in found]
    # The tiny family steers and travels little: let every member stand for the library here.
    monkeypatch.setattr(robust_library, "MIN_TRAVEL", 0.0)
    monkeypatch.setattr(robust_library, "MAX_SPREAD", np.inf)
    monkeypatch.setattr(robust_library, "candidates", lambda *a: [c | {"pure": True} for c in found])
    result = robust_library.search_robust(out, top=1, workers=2, log=None)
    sectors = {(c["kind"], c["sector"]) for c in found}
    assert result["candidates"] == len(found) and len(result["chosen"]) == len(sectors)
    for name, entry in result["chosen"].items():
        best = min(
            (c for c in found if (c["kind"], c["sector"]) == (entry["kind"], entry["sector"])),
            key=lambda c: c["worst_rel"],
        )
        assert name == f"robust-{entry['kind']}-{entry['sector']}"
        assert entry["gait"] == best["member"].wave.model_dump()
        assert entry["worst"]["variation"] in {v.name for v in DEFAULT_SET}
