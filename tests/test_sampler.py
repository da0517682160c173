"""The slider sampler on the data: its density, the checkpoints it ships in, and what the designer,
evaluation and inverse design do with it.

The fast tests run on numbers alone; the slow ones build a tiny structured checkpoint with a
density and a member path head (``calibrate --sampler``) and check the designer's promises on it.
"""

from __future__ import annotations

import numpy as np
import pytest

from snakeloco.app.export.gait_csv import read_gait_csv, read_member
from snakeloco.model.heads.density import LatentDensity, fit_density, name_components
from snakeloco.model.replays import Fit
from snakeloco.sim import GenerateConfig
from snakeloco.sim.data.generate import generate_dataset
from snakeloco.sim.gaits.members import member_from_draw
from snakeloco.sim.gaits.projection import project
from snakeloco.sim.gaits.structured import STRUCTURED_PRESETS, draw_structured
from snakeloco.sim.robot.description import DEFAULT_ROBOT

UNDULATE = STRUCTURED_PRESETS["undulate"]
MIXED = STRUCTURED_PRESETS["mixed"]


def _two_clusters(n: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal([3, 0, 0], [0.3, 0.5, 0.2], (n, 3))
    b = rng.normal([-3, 1, 0], [0.4, 0.2, 0.3], (n, 3))
    return np.concatenate([a, b])


def test_the_density_separates_clusters_samples_deterministically_and_flags_the_gap():
    z = _two_clusters()
    d = fit_density(z, max_components=4, seed=0)
    assert len(d.weights) == 2  # BIC picks the two clusters
    s1, c1 = d.sample(64, seed=5)
    s2, c2 = d.sample(64, seed=5)
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(c1, c2)
    assert not np.array_equal(s1, d.sample(64, seed=6)[0])
    between = np.array([[0.0, 0.5, 0.0]])  # where N(0, I) puts its mass, between the clusters
    assert d.off_data(between)[0]
    assert d.off_data(z).mean() == pytest.approx(0.01, abs=0.01)  # the records themselves are on it
    assert not d.off_data(np.asarray(d.means)).any()
    # a slider position along a component's axes and back
    s = np.array([0.5, -1.0, 2.0])
    for c in range(2):
        np.testing.assert_allclose(d.to_axes(c, d.to_z(c, s)), s, atol=1e-12)
    assert (d.component_of(np.asarray(d.means)) == np.arange(2)).all()
    again = LatentDensity.model_validate_json(d.model_dump_json())
    np.testing.assert_allclose(again.log_density(z[:5]), d.log_density(z[:5]))


def test_components_are_named_by_where_their_gaits_go():
    names = name_components(np.array([[17.0, 1.0, 5.0], [-12.0, 0.5, 0.0], [0.5, 4.0, 120.0], [16.0, 0, 0]]))
    assert names == ["forward, 17 m", "backward, 12 m", "left, turning left, 4 m", "forward, 16 m"]
    # Names that would repeat say what differs: 0.1 m and the heading, then the share of the records.
    assert name_components(np.array([[5.0, 0, 0], [5.2, 0, 2.0]])) == [
        "forward, 5.0 m, heading +0°",
        "forward, 5.2 m, heading +2°",
    ]
    same = np.array([[5.0, 0, 0], [5.0, 0, 0], [0.2, 0.1, 400.0], [0.1, 0.3, 770.0]])
    assert name_components(same, weights=[0.5, 0.2, 0.2, 0.1]) == [
        "forward, 5.0 m, heading +0°, 50% of the records",
        "forward, 5.0 m, heading +0°, 20% of the records",
        "in place, turning left 1.1 turns",
        "in place, turning left 2.1 turns",
    ]
    assert name_components(np.array([[5.0, 0, 0], [5.0, 0, 0]]))[1] == "forward, 5.0 m, heading +0° (2)"
    from snakeloco.model import load_pretrained

    for family in ("structured", "paper"):  # the shipped clusters all read differently
        names = load_pretrained(family).config.density.names
        assert len(set(names)) == len(names) and not any("(2)" in n for n in names)
    # A family of several kinds names each component's kind first (the every family's sampler).
    kinds = name_components(np.array([[0.5, -5.0, 3.0], [0.2, 0.1, 800.0]]), ["roll", "turn"])
    assert kinds == ["rolling: right, 5 m", "turning wave: in place, turning left 2.2 turns"]


def _fit_toy_head(x, body, mean, std, **options):
    """A member path head fitted for 40 quick epochs on toy paths ``body`` (n, t, 6) from inputs
    ``x``, all examples both train and validation; returns (head, fit record, its paths in metres)."""
    import torch

    from snakeloco.model.heads.member_path import fit_member_head

    y = (body - mean) / std
    ones = np.ones((8, 8), bool)
    head, fit = fit_member_head(x, y, x, y, ones, epochs=40, batch_size=32, lr=1e-2, log=None, **options)
    with torch.no_grad():
        pred = head(torch.as_tensor(x, dtype=torch.float32)).numpy() * std + mean
    return head, fit, pred


def test_weighting_xy_by_each_paths_scale_fits_a_small_path_relative_to_its_size():
    """Two kinds of member in one head: straight 10 m paths and 0.5 m circles. Scored in metres the
    head spends its capacity on the long paths; weighted by each path's own scale
    (``calibrate --sampler.xy-floor``) the circle's error relative to its size falls."""
    from snakeloco.model.heads.member_path import path_scales

    rng = np.random.default_rng(0)
    n, t = 256, 50
    s = np.linspace(0, 1, t)
    small = rng.random(n) < 0.5
    a = rng.uniform(0.5, 1.5, n)  # a size parameter per example
    body = np.zeros((n, t, 6))
    body[~small, :, 1] = 10 * a[~small, None] * s
    body[~small, :, 2] = a[~small, None] * s**2
    ang = 2 * np.pi * s
    body[small, :, 1] = 0.25 * a[small, None] * np.sin(ang)
    body[small, :, 2] = 0.25 * a[small, None] * (1 - np.cos(ang))
    x = np.stack([small.astype(float), a], axis=1)
    scale = path_scales(body)
    assert scale[small].max() < 0.6 < 2.5 < scale[~small].min()
    mean, std = body.mean(axis=(0, 1)), body.std(axis=(0, 1)) + 1e-6

    def small_rel_error(weighted: bool) -> float:
        xy_scale = (scale, scale) if weighted else None
        _, _, pred = _fit_toy_head(x, body, mean, std, hidden=8, layers=1, xy_scale=xy_scale, xy_floor=0.1)
        err = np.linalg.norm(pred[small, :, 1:3] - body[small, :, 1:3], axis=-1).mean(-1)
        return float(np.median(err / scale[small]))

    plain, weighted = small_rel_error(False), small_rel_error(True)
    assert weighted < 0.5 * plain, (weighted, plain)


def test_a_heading_head_draws_a_turn_in_place_round_the_circle_its_yaw_sets():
    """Turns in place: the body circles a point while its heading turns 3-9 rad, so where it ends
    swings round the circle as the turn's size grows. A heading head (``HeadPath``: body-frame
    velocities turned by the predicted yaw and summed) follows it; the direct head, fitted the same,
    misses by more. The body-frame velocities integrate back to the path exactly."""
    from snakeloco.model.heads.member_path import body_frame_velocities, fit_member_head

    rng = np.random.default_rng(1)
    n, t = 256, 60
    a = rng.uniform(0.5, 1.5, n)  # the turn's size
    yaw = 6.0 * a[:, None] * np.linspace(0, 1, t)  # 3-9 rad by the end
    body = np.zeros((n, t, 6))
    body[:, :, 5] = yaw
    body[:, :, 1] = 0.3 * np.sin(yaw)  # a point 0.3 m ahead of the centre it turns about
    body[:, :, 2] = 0.3 * (1 - np.cos(yaw))
    u = body_frame_velocities(body)
    c, s = np.cos(yaw[:, :-1]), np.sin(yaw[:, :-1])
    steps = np.stack([c * u[..., 0] - s * u[..., 1], s * u[..., 0] + c * u[..., 1]], axis=-1)
    np.testing.assert_allclose(np.cumsum(steps, axis=1), body[:, 1:, 1:3], atol=1e-12)

    x = a[:, None]
    mean, std = body.mean(axis=(0, 1)), body.std(axis=(0, 1)) + 1e-6
    y = (body - mean) / std

    def end_error(path: str) -> float:
        head, fit, pred = _fit_toy_head(
            x, body, mean, std, hidden=32, layers=2, path=path, body_norm=(mean, std)
        )
        assert fit["path"] == path and head.cfg.path == path
        return float(np.median(np.linalg.norm(pred[:, -1, 1:3] - body[:, -1, 1:3], axis=-1)))

    direct, heading = end_error("direct"), end_error("heading")
    assert heading < 0.5 * direct, (heading, direct)
    with pytest.raises(ValueError, match="body_norm"):
        fit_member_head(x, y, x, y, np.ones((8, 8), bool), epochs=1, path="heading", log=None)


@pytest.mark.slow
def test_a_checkpoint_with_a_sampler_decodes_exact_members_and_the_paths_predicted_for_them(
    member_checkpoint,
):
    from snakeloco.model import load_pretrained

    path, _ = member_checkpoint
    m = load_pretrained(path)
    assert m.projects and m.member_head is not None and m.config.density is not None
    z = m.sample_z_b(5, seed=1)
    np.testing.assert_array_equal(z, m.sample_z_b(5, seed=1))  # deterministic in its seed
    assert not np.array_equal(z, m.sample_z_b(5, seed=2))
    members, residuals, shape, body, stats = m.decode_members(z)
    s2, b2 = m.decode(z)
    np.testing.assert_array_equal(s2, shape)
    np.testing.assert_array_equal(b2, body)
    np.testing.assert_allclose(
        body, m.members.predict_paths(members, z)
    )  # the member's path, not a second decode
    assert m.config.member_head.z_b_dim == m.z_b_dim  # the head reads the slider position too
    with pytest.raises(ValueError, match="reads each member's z_B"):
        m.members.predict_paths(members)
    raw_shape, raw_body = m.decode_raw(z)
    assert not np.allclose(raw_body, body)
    # the shape-only decode (the slider's path on such a checkpoint) is the network's own, to the bit
    np.testing.assert_array_equal(m.decode_shape(z), raw_shape)
    np.testing.assert_array_equal(m.decode_shape(z[:1]), m.decode_raw(z[:1])[0])  # traced
    for member, s in zip(members, shape, strict=True):
        again, _ = m.members.project(s[None])
        np.testing.assert_allclose(
            again[0].shape(DEFAULT_ROBOT), member.shape(DEFAULT_ROBOT), atol=1e-12
        )  # an exact member
        np.testing.assert_allclose(m.commands(s), member.commands(DEFAULT_ROBOT), atol=1e-12)
    assert (residuals > 0).all() and set(stats) == {"path_length", "median_speed", "vertical_std", "net_roll"}
    assert m.off_data(np.full((1, m.z_b_dim), 50.0))[0]
    assert not m.off_data(np.asarray(m.config.density.means)).any()


@pytest.mark.slow
def test_record_members_are_the_members_the_records_drew_and_a_non_member_is_refused(member_checkpoint):
    from snakeloco.model import load_pretrained
    from snakeloco.model.heads.sampler import record_members
    from snakeloco.sim import DatasetError, load_dataset

    family = load_pretrained(member_checkpoint[0]).config.members
    ds = load_dataset(member_checkpoint[1])
    index = np.arange(len(ds))
    logged = [member_from_draw(d).shape(DEFAULT_ROBOT) for d in ds.meta["drawn"]]
    found = np.stack([m.shape(DEFAULT_ROBOT) for m in record_members(ds, index, family)])
    np.testing.assert_allclose(found, logged, atol=1e-6)
    t = np.arange(ds.commands.shape[1]) / ds.config.excitation.sample_rate
    ds.commands[1, :, 1] += 0.05 * np.sin(2 * np.pi * 0.52 * t)  # one yaw joint off the travelling wave
    with pytest.raises(DatasetError, match="record 1 is not a member"):
        record_members(ds, index, family)


@pytest.mark.slow
def test_sampler_gaits_of_another_density_are_refused_and_a_named_mirrored_head_fits(
    member_checkpoint, tmp_path
):
    from snakeloco.model.heads.sampler import SamplerConfig, fit_sampler
    from snakeloco.sim import DatasetError, read_npz, write_npz

    path, data = member_checkpoint
    cfg, gaits = SamplerConfig(samples=2, epochs=2, hidden=16), tmp_path / "gaits.npz"
    fit_sampler(Fit(path, data, tmp_path / "a", gaits, workers=2, log=None), cfg)
    fit_sampler(Fit(path, data, tmp_path / "b", gaits, workers=2, log=None), cfg)  # its own: reused
    stored = dict(read_npz(gaits, "sampler gaits", ["z_b"]))
    write_npz(gaits, **{**stored, "z_b": stored["z_b"] + 0.5})  # as another checkpoint's density drew
    with pytest.raises(DatasetError, match="another checkpoint's slider density"):
        fit_sampler(Fit(path, data, tmp_path / "c", gaits, workers=2, log=None), cfg)
    # The every family's head: named inputs, trained on every member and its mirror image too.
    from snakeloco.model import load_pretrained
    from snakeloco.model.heads.member_path import CURVE_INPUTS, NAMED_INPUTS

    named, fresh = cfg.model_copy(update={"head_inputs": "named"}), tmp_path / "fresh.npz"
    plain = fit_sampler(Fit(path, data, tmp_path / "d", fresh, workers=2, log=None), named)
    mirrored = named.model_copy(update={"mirror": True})
    both = fit_sampler(Fit(path, data, tmp_path / "e", fresh, workers=2, log=None), mirrored)
    # This family is undulation alone, not the library's: no mirror image is a member, none is added.
    assert both["member_head"]["train_examples"] == plain["member_head"]["train_examples"] > 0
    m = load_pretrained(tmp_path / "e")
    head = m.config.member_head
    assert head.inputs == "named" and head.mirrored and len(head.input_mean) == NAMED_INPUTS
    body = m.decode_members(m.sample_z_b(2, seed=1))[3]
    assert body.shape == (2, 500, 6) and np.isfinite(body).all()
    # The arcs family's head reads the curve too (this family's members are all straight: zeros there).
    curving = named.model_copy(update={"head_inputs": "named_curve", "balance_kinds": True})
    summary = fit_sampler(Fit(path, data, tmp_path / "f", fresh, workers=2, log=None), curving)
    assert summary["member_head"]["example_weights"] and set(summary["member_head"]["held_out_by_kind"]) == {
        "undulate"
    }
    m = load_pretrained(tmp_path / "f")
    assert len(m.config.member_head.input_mean) == NAMED_INPUTS + CURVE_INPUTS
    body = m.decode_members(m.sample_z_b(2, seed=1))[3]
    assert body.shape == (2, 500, 6) and np.isfinite(body).all()


@pytest.mark.slow
def test_inverse_design_on_a_sampler_checkpoint_searches_on_the_data(member_checkpoint):
    """The design's prior term is the shipped density's: a component mean costs (about) nothing, a
    z_B far off the data costs metres per unit beyond the bulk, and the search's candidates stay where
    the records are even when the target asks for more than any record does (its best one: the
    tiny model's density is far narrower than the 0.1 that makes a second candidate distinct)."""
    from snakeloco.model import load_pretrained
    from snakeloco.model.design.config import OUTSIDE_COST, DesignConfig, Target
    from snakeloco.model.design.search import design, path_end, prior_cost, search

    m = load_pretrained(member_checkpoint[0])
    cfg = DesignConfig(candidates=2, screen=32, starts=2, generations=8, population=6)
    means = np.asarray(m.config.density.means)
    on = prior_cost(m, means, cfg)
    far = prior_cost(m, means[:1] + 40.0, cfg)
    assert on.max() < 0.05 * m.config.density.dim + 1e-9 < 3 * OUTSIDE_COST < far[0]
    end = path_end(m.decode(means[:1])[1])[0]
    target = Target(forward=float(end[0]) * 5, sideways=float(end[1]) * 5)  # beyond the data's reach
    best = search(m, target, cfg)[0]
    assert not m.off_data(best.z_b[None])[0]
    assert best.cost < 3 * OUTSIDE_COST
    # A target no gait of the family reaches: searched (the reach check off), MuJoCo says not met, with
    # the closest end it reached; with the check (the default) answered at once, one replay.
    far = design(
        m,
        Target(forward=100.0, sideways=0.0),
        cfg.model_copy(update={"rounds": 1, "reach_check": False}),
        workers=2,
    )
    assert far.met is False and far.candidates[0].error_m > 80 and far.replays == 2 + 2 * 3
    at_once = design(m, Target(forward=100.0, sideways=0.0), cfg, workers=2)
    assert at_once.met is False and at_once.replays == 1 and at_once.rounds == 0
    assert at_once.extra["beyond_reach"]["distance_m"] == 100.0 and at_once.candidates[0].error_m > 80


@pytest.mark.slow
def test_the_designer_moves_within_a_cluster_shows_the_member_and_flags_off_the_data(member_checkpoint):

    from helpers import connect_headless, quiet_server

    path, _ = member_checkpoint
    srv = quiet_server(path)
    client = None
    try:
        client, d = connect_headless(srv)
        density = d.model.config.density
        assert d.controls.component is not None and d.controls.component.options == tuple(density.names)
        d.sliders[0].value = 1.0
        assert d.wait_idle(60) and d.decoded.latents.axes[0] == 1.0
        comp = density.names.index(d.controls.component.value)
        np.testing.assert_allclose(
            d.decoded.latents.z_b, density.to_z(comp, np.asarray(d.decoded.latents.axes))
        )
        member = d.decoded.member
        assert member is not None and d.decoded.commands is not None
        np.testing.assert_array_equal(
            d.decoded.commands, member.commands(DEFAULT_ROBOT)
        )  # replayed: exactly the member
        assert "Gait: undulation" in d.controls.readout.content
        text = d.files.export_text()
        np.testing.assert_array_equal(
            read_member(text).commands(DEFAULT_ROBOT), read_gait_csv(text, robot=DEFAULT_ROBOT).commands
        )
        d.moves.show_latents(np.full(d.model.z_b_dim, 8.0))  # far from every record
        assert d.wait_idle(60) and d.decoded.off_data
        assert "Off the data" in d.controls.readout.content
        d.moves.random_z()
        assert d.wait_idle(60)
        lat = d.decoded.latents
        assert lat.component == density.names.index(d.controls.component.value)
        np.testing.assert_allclose([s.value for s in d.sliders], np.clip(np.round(lat.axes, 2), -3, 3))
    finally:
        if client is not None:
            client.close()
        srv.stop()


def test_calibrate_sampler_density_only_gives_the_paper_family_a_sampler_and_a_flag(
    checkpoint, tiny_dataset_path, tmp_path, capsys
):
    from snakeloco.app.cli.main import main
    from snakeloco.model import load_pretrained

    out = tmp_path / "with-density"
    args = ["calibrate", "--data", str(tiny_dataset_path), "--checkpoint", str(checkpoint), "--out", str(out)]
    main([*args, "--sampler", "--sampler.density-only"])
    m, before = load_pretrained(out), load_pretrained(checkpoint)
    assert m.config.density is not None and m.config.density.fitted_on == 3 and not m.projects
    z = m.sample_z_b(4, seed=3)
    np.testing.assert_array_equal(z, m.sample_z_b(4, seed=3))
    np.testing.assert_array_equal(m.decode(z)[0], before.decode(z)[0])  # its decodes unchanged
    assert m.off_data(np.full((1, m.z_b_dim), 40.0))[0]
    # A dataset regenerated must be of the checkpoint's family and at most its size: refused in one line.
    bigger = tmp_path / "bigger.npz"
    generate_dataset(GenerateConfig(num_samples=5, seed=11), bigger, workers=2)
    args[2] = str(bigger)
    with pytest.raises(SystemExit):
        main([*args, "--sampler", "--sampler.density-only", "--sampler.regenerated"])
    assert "cannot be this checkpoint's 4 paper training records" in capsys.readouterr().err


@pytest.mark.slow
def test_the_shipped_structured_path_of_a_members_own_gait_beats_the_path_of_another_member():
    """On the shipped structured checkpoint: six gaits of its family never seen in training (a draw
    seed no dataset used), each replayed once; the path the model predicts for each gait's own member
    must fit its replay better than the path predicted for any member that goes elsewhere. Where the
    head also reads z_B, every prediction gets the same slider position (a sampler draw that is none
    of these gaits'): the member, not z_B, must decide the path."""
    from snakeloco.model import load_pretrained
    from snakeloco.sim import BODY_DOWNSAMPLE
    from snakeloco.sim.physics.simulator import Simulator
    from snakeloco.sim.scores.consistency import xy_r2

    m = load_pretrained("structured")
    assert m.projects and m.member_head is not None
    family = m.config.members
    members = [
        project(draw_structured(family, 99, i, 0, robot=DEFAULT_ROBOT)[0], family, robot=DEFAULT_ROBOT)[0]
        for i in range(6)
    ]
    sim = Simulator(workers=2)
    try:
        result = sim.simulate(np.stack([x.commands(DEFAULT_ROBOT) for x in members]))
    finally:
        sim.close()
    assert all(f is None for f in result.failures)
    replays = result.body[:, ::BODY_DOWNSAMPLE].astype(np.float64)
    z_b = np.repeat(m.sample_z_b(1, seed=99), 6, axis=0) if m.config.member_head.z_b_dim else None
    predicted = m.members.predict_paths(members, z_b)
    ends = replays[:, -1, 1:3]
    for i in range(6):
        own = xy_r2(predicted[i], replays[i])
        # Another member's path, wherever that member's replay ends more than 1 m from this one's (two
        # members may go the same way: a rolling and a sidewinding one both 4.6-4.9 m left).
        elsewhere = [j for j in range(6) if j != i and np.linalg.norm(ends[j] - ends[i]) > 1.0]
        assert len(elsewhere) >= 3, (i, ends)
        for j in elsewhere:
            assert own > xy_r2(predicted[j], replays[i]), (i, j, own)
    assert np.median([xy_r2(p, r) for p, r in zip(predicted, replays, strict=True)]) > 0.8
