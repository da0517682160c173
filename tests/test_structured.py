"""The structured family: travelling-wave gaits drawn deterministically, kept only where physics can
predict them, generated resumably into the paper family's file schema."""

from __future__ import annotations

import json

import numpy as np
import pytest

from snakeloco.app.cli.main import main
from snakeloco.sim import GenerateConfig, SimulationError, joint_shape, load_dataset
from snakeloco.sim.data.chunks import perturbed_shapes, simulate_structured
from snakeloco.sim.data.dataset import DatasetError
from snakeloco.sim.data.generate import generate_dataset
from snakeloco.sim.gaits.library import GaitEquation
from snakeloco.sim.gaits.members import Member
from snakeloco.sim.gaits.projection import project
from snakeloco.sim.gaits.structured import (
    DEFAULT_PRESET,
    KINDS,
    STRUCTURED_PRESETS,
    StructuredConfig,
    curve_wave,
    draw_structured,
    library_gait,
)
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.robot.description import DEFAULT_ROBOT
from snakeloco.sim.scores.consistency import ensemble_spread, perturbed_commands

CFG = GenerateConfig(
    num_samples=3, seed=3, family="structured", structured=STRUCTURED_PRESETS[DEFAULT_PRESET]
)
"""Three records of the family ``generate --family structured`` draws by default."""
"""The default structured family (``snakeloco generate --family structured``)."""
SAMPLE_SEED = 99
"""Draws (99, i, 0) of the every family were replayed as 4-member ensembles over 100 s (docs/gaits.md,
"The every family"); the tests below name draws of that sample by their index."""


def _screen(sc: StructuredConfig, indices: list[int]):
    """Screen draws (SAMPLE_SEED, i, 0) once each: the kept chunk, or the SimulationError naming why
    the first of them was rejected."""
    cfg = GenerateConfig(
        num_samples=max(indices) + 1,
        seed=SAMPLE_SEED,
        family="structured",
        structured=sc.model_copy(update={"max_draws": 1}),
    )
    simulator = Simulator(workers=2)
    try:
        return simulate_structured(cfg, simulator, np.array(indices))
    except SimulationError as exc:
        return exc
    finally:
        simulator.close()


def test_draws_are_deterministic_joint_shapes_within_the_command_limit():
    sc = StructuredConfig()
    kinds = set()
    for index in range(24):
        shape, drawn = draw_structured(sc, 5, index, 0, robot=DEFAULT_ROBOT)
        again, _ = draw_structured(sc, 5, index, 0, robot=DEFAULT_ROBOT)
        np.testing.assert_array_equal(shape, again)
        assert not np.array_equal(
            shape, draw_structured(sc, 5, index, 1, robot=DEFAULT_ROBOT)[0]
        )  # a redraw is another gait
        from snakeloco.sim import shape_to_commands

        u = shape_to_commands(shape, limit=np.inf)
        assert np.abs(u).max() <= 2.2 + 1e-9  # scaled, not clipped: still exactly its joint shape
        np.testing.assert_allclose(joint_shape(u), shape, atol=1e-12)
        kinds.add(drawn["kind"])
    assert kinds == set(KINDS)


@pytest.mark.slow
def test_structured_generation_is_deterministic_resumable_and_keeps_predictable_gaits(tmp_path):
    whole = load_dataset(generate_dataset(CFG, tmp_path / "a.npz", workers=2, chunk_size=3))
    meta = whole.meta
    assert meta["family"] == "structured" and meta["config"]["family"] == "structured"
    assert len(meta["spreads"]) == 3 and max(meta["spreads"]) <= CFG.structured.max_spread
    assert meta["draws"] == int(whole.attempts.sum()) == 3 + len(meta["failures"])
    assert 0.0 <= meta["rejection_rate"] < 1.0 and meta["rejection_rate"] == pytest.approx(
        1 - 3 / meta["draws"]
    )
    np.testing.assert_allclose(joint_shape(whole.joint_angles), whole.shape, atol=1e-6)  # same convention

    def interrupt(_n: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_dataset(CFG, tmp_path / "b.npz", workers=1, chunk_size=1, progress=interrupt)
    assert (tmp_path / "b.npz.partial").is_dir() and not (tmp_path / "b.npz").exists()
    main(
        [
            "generate",
            "--family",
            "structured",
            "--num-samples",
            "3",
            "--seed",
            "3",
            "--out",
            str(tmp_path / "b.npz"),
        ]
    )
    resumed = load_dataset(tmp_path / "b.npz")  # resumed by the command, in other chunks and threads
    for key in ("commands", "joint_angles", "body", "shape", "phases", "attempts"):
        np.testing.assert_array_equal(getattr(resumed, key), getattr(whole, key), err_msg=key)
    assert resumed.meta == meta


@pytest.mark.slow
def test_rejected_records_are_redrawn_and_logged(tmp_path):
    strict = StructuredConfig(max_spread=0.02, max_draws=40)
    ds = load_dataset(
        generate_dataset(CFG.model_copy(update={"structured": strict}), tmp_path / "s.npz", workers=2)
    )
    assert (ds.attempts > 1).any()  # at least one record's first gait was not predictable enough
    failures = ds.meta["failures"]
    assert len(failures) == int((ds.attempts - 1).sum())
    assert all(
        "final spread" in f["reason"] or "thrown" in f["reason"] or "diverged" in f["reason"]
        for f in failures
    )
    assert max(ds.meta["spreads"]) <= 0.02
    hopeless = StructuredConfig(max_spread=1e-9, max_draws=2)
    with pytest.raises(SimulationError, match="no predictable gait in 2 draws"):
        generate_dataset(CFG.model_copy(update={"structured": hopeless}), tmp_path / "never.npz", workers=2)
    assert not (tmp_path / "never.npz").exists() and not (tmp_path / "never.npz.partial").exists()


@pytest.mark.slow
def test_a_screening_log_rebuilds_the_same_dataset_with_one_replay_per_record(tmp_path, monkeypatch):
    reference = load_dataset(generate_dataset(CFG, tmp_path / "a.npz", workers=2))
    log = tmp_path / "a.npz.screening.json"  # the run's log, kept beside the file it wrote
    assert log.is_file() and not (tmp_path / "a.npz.partial").exists()

    rows = []
    simulate = Simulator.simulate
    monkeypatch.setattr(Simulator, "simulate", lambda self, c: rows.append(len(c)) or simulate(self, c))
    main(
        [
            *("generate", "--family", "structured", "--num-samples", "3", "--seed", "3"),
            *("--out", str(tmp_path / "b.npz"), "--screened", str(log)),
        ]
    )
    assert sum(rows) == 3  # one replay per record, no ensemble
    rebuilt = load_dataset(tmp_path / "b.npz")
    for key in ("commands", "joint_angles", "body", "body_ds", "shape", "phases", "amplitude", "attempts"):
        np.testing.assert_array_equal(getattr(rebuilt, key), getattr(reference, key), err_msg=key)
    assert rebuilt.meta == reference.meta

    # A log that does not fit is refused before anything is simulated, naming what differs.
    progress = json.loads(log.read_text())
    other_physics = tmp_path / "other_physics.json"
    other_physics.write_text(json.dumps(progress | {"physics": {"mujoco_version": "0.0"}}))
    with pytest.raises(DatasetError, match="simulated with other physics"):
        generate_dataset(CFG, tmp_path / "c.npz", workers=2, screened=other_physics)
    with pytest.raises(DatasetError, match="is a run of another config"):
        generate_dataset(CFG.model_copy(update={"seed": 4}), tmp_path / "c.npz", workers=2, screened=log)
    progress["chunks"]["0"]["drawn"][0]["wave"]["a_yaw"] += 0.1
    tampered = tmp_path / "tampered.json"
    tampered.write_text(json.dumps(progress))
    with pytest.raises(DatasetError, match="differ from the logged ones"):
        generate_dataset(CFG, tmp_path / "c.npz", workers=2, screened=tampered)
    (tmp_path / "junk.json").write_text("[1, 2")
    with pytest.raises(DatasetError, match="not a generation progress file"):
        generate_dataset(CFG, tmp_path / "c.npz", workers=2, screened=tmp_path / "junk.json")
    assert not (tmp_path / "c.npz").exists()


def test_coefficient_noise_perturbs_the_shape_of_each_screened_replay():
    from snakeloco.sim.data.chunks import _ensemble, draw_record

    shape, _ = draw_structured(StructuredConfig(), 3, 0, 0, robot=DEFAULT_ROBOT)
    copies = perturbed_shapes(shape, 4, 0.1, np.random.default_rng(0))
    np.testing.assert_array_equal(copies[0], shape)
    c = shape[..., 0] + 1j * shape[..., 1]
    excited = np.abs(c) > 1e-9
    for noisy in copies[1:]:
        e = noisy[..., 0] + 1j * noisy[..., 1]
        rel = np.abs(e[excited] / c[excited] - 1)
        assert 0.02 < np.sqrt(np.mean(rel**2)) < 0.3  # ~10% per coefficient
        np.testing.assert_array_equal(e[~excited], c[~excited])  # no bin is excited that was not
    plain = GenerateConfig(num_samples=3, seed=3, family="structured")
    noisy_cfg = plain.model_copy(update={"structured": StructuredConfig(coefficient_noise=0.1)})
    commands = draw_record(plain, 0, 0)[0]
    a, b = _ensemble(plain, 0, 0, commands), _ensemble(noisy_cfg, 0, 0, commands)
    np.testing.assert_array_equal(a[0], b[0])  # the record itself is the draw, unperturbed
    np.testing.assert_array_equal(b, _ensemble(noisy_cfg, 0, 0, commands))  # deterministic
    for m in range(1, len(a)):
        plain_dev = np.sqrt(np.mean((a[m] - a[0]) ** 2))
        noisy_dev = np.sqrt(np.mean((b[m] - b[0]) ** 2))
        assert noisy_dev > 20 * plain_dev  # 10% of the shape against 0.1% of the commands


def test_the_undulate_preset_draws_only_undulation_in_its_ranges_and_old_metas_keep_their_hash():
    sc = STRUCTURED_PRESETS["undulate"]
    signs, steered = set(), 0
    for index in range(40):
        shape, drawn = draw_structured(sc, 0, index, 0, robot=DEFAULT_ROBOT)
        wave = drawn["wave"]
        assert drawn["kind"] == "undulate" and "second_wave" not in drawn and wave["frequency"] == 0.52
        assert 0.5 <= wave["a_yaw"] <= 0.9 and 0.4 <= abs(wave["nu_yaw"]) <= 1.0 and wave["a_pitch"] == 0
        assert np.all(shape[0::2] == 0)  # the pitch joints stay still
        signs.add(np.sign(wave["nu_yaw"]))
        steered += "steering" in drawn
    assert signs == {-1.0, 1.0} and 10 <= steered <= 30  # forward and backward; steering in about half
    # A config at the default ranges is stored as before the ranges existed (its meta hash unchanged);
    # another range is stored, so a dataset says which family it holds.
    mixed = GenerateConfig(num_samples=4, family="structured").to_meta()["structured"]
    assert "undulate_amplitude" not in mixed and "undulate_wavenumber" not in mixed
    narrow = GenerateConfig(num_samples=4, family="structured", structured=sc).to_meta()["structured"]
    assert narrow["undulate_amplitude"] == [0.5, 0.9] and narrow["undulate_wavenumber"] == [0.4, 1.0]


def test_the_compass_family_draws_what_its_committed_screening_log_records():
    """New family options (the arcs family's curves) leave the compass family's config meta and its
    random draws as they were: the committed log of the shipped checkpoint's dataset still rebuilds."""
    from pathlib import Path

    log = json.loads((Path(__file__).parents[1] / "data/screening/compass-n4096-seed0.json").read_text())
    cfg = GenerateConfig(
        num_samples=4096, seed=0, family="structured", structured=STRUCTURED_PRESETS["compass"]
    )
    assert cfg.to_meta() == log["config"]
    chunk = log["chunks"]["0"]
    for index, drawn in enumerate(chunk["drawn"]):
        attempt = sum(f["index"] == index for f in chunk["failures"])  # rejected draws came first
        assert draw_structured(cfg.structured, 0, index, attempt, robot=DEFAULT_ROBOT)[1] == drawn, index


def test_the_structured_preset_flag_needs_the_structured_family(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "generate",
                "--structured-preset",
                "undulate",
                "--num-samples",
                "2",
                "--out",
                str(tmp_path / "d.npz"),
            ]
        )
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["snakeloco: error: --structured-preset undulate needs --family structured"]
    assert not list(tmp_path.iterdir())


KIND_EXAMPLES = [  # (kind, a_pitch, a_yaw, nu_pitch, nu_yaw, delta, Hz, steering, its phase; heading or yaw way)
    ("undulate", 0.0, 0.515, 0.0, 0.787, 0.0, 0.52, 0.0, 0.0, -10),  # forward: the wave runs to the tail
    ("undulate", 0.0, 0.482, 0.0, -0.496, 0.0, 0.52, 0.136, 0.200, -165),  # backward, steered
    ("sidewind", 0.164, 0.231, 0.740, 0.740, 0.532, 0.52, 0.0, 0.0, 81),  # to the left
    ("sidewind", 0.098, 0.587, 1.194, 1.194, -1.459, 0.52, 0.390, 2.362, -59),  # to the right
    ("roll", 0.440, 0.440, 0.964, 0.964, 1.862, 0.29, 0.0, 0.0, -101),  # rolling right (delta > 0)
    ("roll", 0.418, 0.418, 0.975, 0.975, -1.337, 0.29, 0.0, 0.0, 109),  # rolling left (delta < 0)
    ("turn", 0.230, 0.808, 1.228, 0.848, -1.635, 0.29, 0.0, 0.0, "left"),  # in place, ccw (15 rad)
    ("turn", 0.129, 0.927, -1.310, 0.656, -3.005, 0.29, 0.0, 0.0, "right"),  # in place, cw (-9.6 rad)
]
"""Members of the default family kept by its screen in the sample docs/gaits.md tabulates, one of
each kind each way, with where they go (heading of the final position, deg; or the way they turn)."""


@pytest.mark.slow
def test_each_kind_replays_to_its_documented_direction_within_the_spread():
    every = STRUCTURED_PRESETS["every"]
    members = []
    for kind, a_p, a_y, nu_p, nu_y, delta, f, s, psi, _ in KIND_EXAMPLES:
        wave = GaitEquation(a_pitch=a_p, a_yaw=a_y, nu_pitch=nu_p, nu_yaw=nu_y, delta=delta, frequency=f)
        member = Member(kind=kind, wave=wave, steering_amplitude=s, steering_phase=psi)
        again, r = project(
            member.shape(DEFAULT_ROBOT), every, robot=DEFAULT_ROBOT
        )  # a member of the family, kind and all
        assert r < 1e-9 and again.kind == kind
        members.append(member)
    _replays_to_their_directions(every, members, [e[-1] for e in KIND_EXAMPLES])


LIBRARY_EXAMPLES = [
    # kind, a_pitch, a_yaw, nu_pitch, nu_yaw, delta, f (Hz), heading of the end (deg) or the way it turns
    ("undulate", 0.0, 0.36574012255332233, 0.0, 0.7, 0.0, 0.93, -11),  # forward, 19.6 m
    ("undulate", 0.0, 0.3020959734821988, 0.0, 0.7, np.pi, 0.93, 6),  # forward, mirrored, 14.8 m
    ("undulate", 0.0, 0.2615238942488645, 0.0, -0.7, 0.0, 0.52, -177),  # backward, 7.2 m
    ("undulate", 0.0, 0.21780085767750373, 0.0, -0.7, np.pi, 0.52, 176),  # backward, mirrored, 4.9 m
    ("sidewind", 0.233432453263781, 0.4085067932116167, 0.8, 0.8, 0.43184828558497873, 0.52, 99),  # 5.6 m
    ("sidewind", 0.23461256864936272, 0.4105719951363847, 0.8, 0.8, -2.2910720668500444, 0.52, -91),
    ("roll", 0.342004320724247, 0.342004320724247, 0.71, 0.71, 1.5708, 0.52, -115),  # 8.4 m
    ("roll", 0.24638556595488673, 0.24638556595488673, 0.71, 0.71, -1.5707926535897931, 0.52, 100),
    ("turn", 0.05773219487471832, 0.4570465427581867, 1.95, -0.66, -1.9, 0.29, "right"),  # -9.4 rad
    ("turn", 0.04972085407426025, 0.3936234280878937, 1.95, -0.66, 1.2415926535897932, 0.29, "left"),  # 8.0
    ("undulate", 0.0, 0.3103987954474488, 0.0, 0.7, 0.0, 0.29, -9),  # compass: forward, 4.1 m
    ("undulate", 0.0, 0.21780085767750373, 0.0, -0.7, np.pi, 0.29, 175),  # compass: backward, 2.4 m
]
"""Members of the library family kept by its screen in its held-out set (seed 2, records 11, 90, 31, 29,
9, 19, 86, 46, 71, 53), each kind each way (the second of each pair its mirror image); then the
compass family's slow undulations, forward and backward, from its held-out set (seed 2, records 36
and 29). The library's members are compass members too."""


def _replays_to_their_directions(family, members, ways) -> None:
    """Each member's ensemble (``family.members`` replays with 1e-3 command noise) stays within the
    family's spread and goes where ``ways`` says: a heading (deg, within 20) or a way round."""
    ensembles = np.concatenate(
        [perturbed_commands(m.commands(DEFAULT_ROBOT), family.members, seed=i) for i, m in enumerate(members)]
    )
    simulator = Simulator(workers=2)
    result = simulator.simulate(ensembles)
    simulator.close()
    assert result.failures == [None] * len(ensembles)
    body = result.body.reshape(len(members), family.members, *result.body.shape[1:])
    for member, way, ensemble in zip(members, ways, body, strict=True):
        kind = member.kind
        spread = ensemble_spread(ensemble, 20.0)["final_spread"]
        assert spread <= family.max_spread, kind
        final = ensemble[0, -1]
        if isinstance(way, str):  # turning in place: more than a turn, that way round
            assert abs(final[5]) > 2 * np.pi and np.sign(final[5]) == (1 if way == "left" else -1), (
                kind,
                final[5],
            )
            continue
        assert np.hypot(final[1], final[2]) > 2.0, kind
        off = (np.degrees(np.arctan2(final[2], final[1])) - way + 180) % 360 - 180
        assert abs(off) < 20, (kind, way, off)


@pytest.mark.slow
def test_each_compass_kind_replays_to_its_direction_within_the_spread():
    compass = STRUCTURED_PRESETS["compass"]
    members = []
    for kind, a_p, a_y, nu_p, nu_y, delta, f, _ in LIBRARY_EXAMPLES:
        wave = GaitEquation(a_pitch=a_p, a_yaw=a_y, nu_pitch=nu_p, nu_yaw=nu_y, delta=delta, frequency=f)
        again, r = project(Member(kind=kind, wave=wave).shape(DEFAULT_ROBOT), compass, robot=DEFAULT_ROBOT)
        assert r < 1e-9 and again.kind == kind  # a member of the family
        members.append(again)
    _replays_to_their_directions(compass, members, [e[-1] for e in LIBRARY_EXAMPLES])


@pytest.mark.slow
def test_curving_undulations_replay_to_their_arcs_within_the_spread():
    """The library undulation at 0.52 Hz with the arcs family's curve at 0.07 (both ways): 11.4 m
    away at -90 and 24 deg in the pilot (2026-12-04), where a straight one ends ahead."""
    arcs = STRUCTURED_PRESETS["arcs"]
    wave = library_gait("undulate", robot=DEFAULT_ROBOT).model_copy(update={"frequency": 0.52})
    members = []
    for mirrored in (False, True):
        member = Member(
            kind="undulate", wave=wave, curve=curve_wave(0.07, 0.29, mirrored, robot=DEFAULT_ROBOT)
        )
        again, r = project(member.shape(DEFAULT_ROBOT), arcs, robot=DEFAULT_ROBOT)
        assert r < 1e-9 and again.curve is not None  # a member of the family, curve and all
        np.testing.assert_allclose(again.shape(DEFAULT_ROBOT), member.shape(DEFAULT_ROBOT), atol=1e-12)
        members.append(member)
    _replays_to_their_directions(arcs, members, [-90, 24])


@pytest.mark.slow
def test_a_draw_the_early_check_rejects_the_full_screen_rejects_too():
    """Draws of the sample whose 2-replay spread at 20 s exceeds 0.3 (undulation, rolling): the cheap screen
    redraws them at 20 s, and the full screen (4 replays over 100 s, no pause, no 2-replay verdict)
    rejects each of them as well."""
    every = STRUCTURED_PRESETS["every"]
    full = every.model_copy(update={"early_seconds": 0.0, "sure_spread": 0.0})
    for index in (59, 157, 159):
        early = _screen(every, [index])
        assert isinstance(early, SimulationError) and "at 20 s" in str(early), (index, early)
        late = _screen(full, [index])
        assert isinstance(late, SimulationError) and "final spread" in str(late), (index, late)


@pytest.mark.slow
def test_bench_screen_compares_the_screens_side_by_side(capsys):
    main(["bench", "screen", "--records", "2", "--draws", "3", "--workers", "2", "--json"])
    r = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rates = r["rates"]
    # (the undulation family runs the first half of the 8-record chunks: here the one chunk)
    assert rates["cheap"]["records"] == rates["full"]["records"] == rates["undulate"]["records"] == 2
    for f in rates.values():  # a record costs 0.5-20 s of 2-core physics, whichever screen
        assert 0.05 < f["records_per_s"] < 2 and 0 <= f["rejection_rate"] < 1, f
    assert 0.1 < r["ratio_full"] < 20 and 0.1 < r["ratio_undulate"] < 50, r
    a = r["agreement"]
    assert a["draws"] == 3 and a["early_seconds"] == 20
    assert a["disagree"] == a["cheap_keeps_full_rejects"] + a["cheap_rejects_full_keeps"] <= 3
    assert sum(kept for kept, _ in a["kept_by_kind"].values()) == a["cheap_kept"] <= 3
    assert sum(drawn for _, drawn in a["kept_by_kind"].values()) == 3
