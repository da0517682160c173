"""Shown is done: exact family members, their projection, mirror images and exported files
(the sampler that keeps sliders on the members: ``test_sampler.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from snakeloco.app.export.gait_csv import GaitCSVError, read_gait_csv, read_member, write_gait_csv
from snakeloco.sim import shape_to_commands
from snakeloco.sim.gaits.library import GaitEquation
from snakeloco.sim.gaits.members import Member, member_from_draw
from snakeloco.sim.gaits.projection import project, residual
from snakeloco.sim.gaits.structured import STRUCTURED_PRESETS, curve_wave, draw_structured
from snakeloco.sim.robot.description import DEFAULT_ROBOT

UNDULATE = STRUCTURED_PRESETS["undulate"]
MIXED = STRUCTURED_PRESETS["mixed"]


def test_a_record_projects_onto_its_own_member_and_a_member_onto_itself():
    for index in range(12):
        shape, drawn = draw_structured(UNDULATE, 7, index, 0, robot=DEFAULT_ROBOT)
        member, r = project(shape, UNDULATE, robot=DEFAULT_ROBOT)
        np.testing.assert_allclose(
            member.shape(DEFAULT_ROBOT), member_from_draw(drawn).shape(DEFAULT_ROBOT), atol=1e-13
        )
        assert r < 1e-12
        again, r2 = project(member.shape(DEFAULT_ROBOT), UNDULATE, robot=DEFAULT_ROBOT)
        np.testing.assert_allclose(
            again.shape(DEFAULT_ROBOT), member.shape(DEFAULT_ROBOT), rtol=0, atol=1e-14
        )  # nothing changes
        assert r2 < 1e-12


@pytest.mark.parametrize("preset", ["mixed", "every", "library", "arcs"])
def test_every_kind_of_a_family_projects_to_its_own_kind(preset):
    """Exact members hold for every kind: the mixed family's one-wave draws, the every family's
    (whose amplitudes are also scaled 0.35-1: the fit's ranges widen with it) and the library
    family's (scaled library gaits, mirrored or not, sidewinding's offset free in its range)."""
    family = STRUCTURED_PRESETS[preset]
    seen = set()
    for index in range(120):
        shape, drawn = draw_structured(family, 3, index, 0, robot=DEFAULT_ROBOT)
        if "second_wave" in drawn:
            continue
        member, r = project(shape, family, robot=DEFAULT_ROBOT)
        assert r < 1e-9, (drawn["kind"], r)
        assert member.kind == drawn["kind"]
        seen.add(member.kind)
    assert seen == {"undulate", "sidewind", "roll", "turn"}


def test_a_curving_undulation_projects_onto_itself_and_its_mirror_image_curves_the_other_way():
    """The arcs family's undulations with a weak turning wave beside them (``curve_wave``): a draw
    projects onto its own member, curve and all, scale and mirror included; the same shape without
    the curve projects onto the straight undulation; the mirror image's curve is mirrored."""
    arcs, curved = STRUCTURED_PRESETS["arcs"], []
    for index in range(200):
        shape, drawn = draw_structured(arcs, 5, index, 0, robot=DEFAULT_ROBOT)
        if "curve" in drawn:
            member, r = project(shape, arcs, robot=DEFAULT_ROBOT)
            assert r < 1e-9 and member.kind == "undulate" and member.curve is not None
            np.testing.assert_allclose(
                member.shape(DEFAULT_ROBOT), member_from_draw(drawn).shape(DEFAULT_ROBOT), atol=1e-12
            )
            curved.append(member)
    assert len(curved) >= 20
    assert {
        abs(m.curve.delta - curve_wave(1, 0.29, False, robot=DEFAULT_ROBOT).delta) < 1e-9 for m in curved
    } == {True, False}
    m = curved[0]
    straight, r = project(m.wave.shape(DEFAULT_ROBOT), arcs, robot=DEFAULT_ROBOT)
    assert r < 1e-9 and straight.curve is None
    image = m.mirrored()
    np.testing.assert_allclose(
        image.shape(DEFAULT_ROBOT)[1::2], -m.shape(DEFAULT_ROBOT)[1::2], atol=1e-12
    )  # yaw joints negated
    np.testing.assert_allclose(image.shape(DEFAULT_ROBOT)[::2], m.shape(DEFAULT_ROBOT)[::2], atol=1e-12)
    assert "curving" in m.describe() and Member.model_validate(m.params()) == m
    from snakeloco.model.heads.member_path import CURVE_INPUTS, NAMED_INPUTS, named_inputs

    # The path head's named inputs carry the curve ("named_curve"; "named" stays 14 wide for the
    # checkpoints trained with it): its yaw amplitude, and its offset's cosine and sine, which the
    # mirror image negates; a straight member has zeros there.
    x = named_inputs([*curved, straight], curve=True)
    xm = named_inputs([c.mirrored() for c in curved], curve=True)
    assert (
        x.shape == (len(curved) + 1, NAMED_INPUTS + CURVE_INPUTS)
        and named_inputs(curved).shape[1] == NAMED_INPUTS
    )
    np.testing.assert_allclose(xm[:, -2:], -x[:-1, -2:], atol=1e-12)
    np.testing.assert_allclose(xm[:, -3], x[:-1, -3], atol=1e-12)
    assert (x[:-1, -3] > 0).all() and (x[-1, -3:] == 0).all()


def test_a_noisy_member_keeps_its_kind_where_a_freer_kind_fits_it_only_a_little_better():
    """A decoded shape is never exactly one kind's; turning's free pitch and yaw waves absorb the most
    of any error. 15 draws of each kind of the every family with 15% noise on their coefficients:
    the least residual alone (margin 1) keeps 28 of the 60 kinds, the shipped margin 53."""
    family = STRUCTURED_PRESETS["every"]
    rng = np.random.default_rng(0)
    kept = {1.0: 0, None: 0}
    for want in ("undulate", "sidewind", "roll", "turn"):
        drawn_shapes = (draw_structured(family, 5, i, 0, robot=DEFAULT_ROBOT) for i in range(200))
        shapes = [s for s, d in drawn_shapes if d["kind"] == want][:15]
        for shape in shapes:
            noise = 0.15 * np.abs(shape).max() * rng.standard_normal(shape.shape) * (np.abs(shape) > 0)
            kept[1.0] += project(shape + noise, family, margin=1.0, robot=DEFAULT_ROBOT)[0].kind == want
            kept[None] += project(shape + noise, family, robot=DEFAULT_ROBOT)[0].kind == want
    assert kept[1.0] <= 35 and kept[None] >= 50, kept


def test_a_members_mirror_image_negates_its_yaw_joints_and_named_inputs_flip_only_the_phases():
    from snakeloco.model.heads.member_path import named_inputs, with_mirror_images
    from snakeloco.sim.gaits.library import PITCH

    family = STRUCTURED_PRESETS["every"]
    draws = [member_from_draw(draw_structured(family, 3, i, 0, robot=DEFAULT_ROBOT)[1]) for i in range(40)]
    members = [m for m in draws if m.steering_amplitude > 0][:4] + [m for m in draws if m.kind == "roll"][:2]
    for m in members:
        image = m.mirrored()
        np.testing.assert_allclose(
            image.shape(DEFAULT_ROBOT)[~PITCH], -m.shape(DEFAULT_ROBOT)[~PITCH], atol=1e-14
        )
        np.testing.assert_array_equal(image.shape(DEFAULT_ROBOT)[PITCH], m.shape(DEFAULT_ROBOT)[PITCH])
        np.testing.assert_allclose(image.mirrored().shape(DEFAULT_ROBOT), m.shape(DEFAULT_ROBOT), atol=1e-14)
        in_family = project(image.shape(DEFAULT_ROBOT), family, robot=DEFAULT_ROBOT)[1] < 1e-9
        assert image.kind == m.kind and in_family == family.mirrors(m.kind) == (m.kind != "undulate")
    bodies = np.random.default_rng(0).standard_normal((len(members), 5, 6))
    pairs, body = with_mirror_images(members, bodies, family)
    kept = [i for i, m in enumerate(members) if m.kind != "undulate"]
    assert 0 < len(kept) < len(members)  # both cases are seen
    assert pairs == members + [members[i].mirrored() for i in kept]
    np.testing.assert_array_equal(body, np.concatenate([bodies, bodies[kept] * [1, 1, -1, -1, 1, -1]]))
    library = STRUCTURED_PRESETS["library"]
    for i in range(40):  # in the library family every kind's mirror image is a member
        m = member_from_draw(draw_structured(library, 3, i, 0, robot=DEFAULT_ROBOT)[1])
        assert (
            library.mirrors(m.kind)
            and project(m.mirrored().shape(DEFAULT_ROBOT), library, robot=DEFAULT_ROBOT)[1] < 1e-9
        )
    x, xm = named_inputs(members), named_inputs([m.mirrored() for m in members])
    flips = np.zeros(x.shape[1], bool)
    flips[[8, 9, 12, 13]] = True  # cos, sin of the offset; the steering's two components
    np.testing.assert_allclose(xm[:, flips], -x[:, flips], atol=1e-12)
    np.testing.assert_allclose(xm[:, ~flips], x[:, ~flips], atol=1e-12)
    assert np.abs(x[:, flips]).min(axis=0).max() > 0.01  # the flipped ones are not all zero


def test_a_members_mirror_image_replays_to_the_mirror_image_of_its_path():
    """The symmetry the every family's head is trained with: a sidewinding member with steering (8.4 m
    in 100 s) and its mirror image; sideways, roll and yaw flip, the rest stays (to 1 cm, 0.01 rad;
    measured: to the bit, where a chaotic draw (not screened) parts by metres)."""
    from snakeloco.sim.physics.body import mirror_body
    from snakeloco.sim.physics.simulator import Simulator

    m = member_from_draw(draw_structured(STRUCTURED_PRESETS["every"], 3, 44, 0, robot=DEFAULT_ROBOT)[1])
    assert m.kind == "sidewind" and m.steering_amplitude > 0
    result = Simulator().simulate(np.stack([m.commands(DEFAULT_ROBOT), m.mirrored().commands(DEFAULT_ROBOT)]))
    assert result.failures == [None, None]
    body, image = result.body[0, ::4], result.body[1, ::4]
    assert np.hypot(*body[-1, 1:3]) > 0.5  # it travels: a sideways flip is seen
    np.testing.assert_allclose(mirror_body(image), body, atol=0.01)


def test_a_noisy_shape_projects_onto_a_member_inside_the_family_with_its_residual():
    rng = np.random.default_rng(0)
    shape, drawn = draw_structured(UNDULATE, 1, 4, 0, robot=DEFAULT_ROBOT)
    noisy = shape + 0.05 * rng.standard_normal(shape.shape)  # every coefficient, zeros included
    member, r = project(noisy, UNDULATE, robot=DEFAULT_ROBOT)
    assert r == pytest.approx(residual(noisy, member, robot=DEFAULT_ROBOT)) and 0.05 < r < 1.0
    lo, hi = UNDULATE.undulate_amplitude
    assert member.kind == "undulate" and lo <= member.wave.a_yaw <= hi and member.wave.a_pitch == 0.0
    assert UNDULATE.undulate_wavenumber[0] <= abs(member.wave.nu_yaw) <= UNDULATE.undulate_wavenumber[1]
    # the fit finds the drawn wave under the noise
    truth = member_from_draw(drawn)
    assert member.wave.nu_yaw == pytest.approx(truth.wave.nu_yaw, abs=0.1)
    c = member.shape(DEFAULT_ROBOT)
    np.testing.assert_array_equal(c[0::2], 0.0)  # pitch joints still, as in every record
    assert np.abs(shape_to_commands(c, limit=np.inf)).max() <= 2.2 + 1e-12


def test_a_member_scaled_to_the_command_limit_stays_a_member():
    big = Member(kind="turn", wave=GaitEquation(a_pitch=0.5, a_yaw=1.2, nu_yaw=0.3, frequency=0.52))
    shape = 2.5 * big.shape(DEFAULT_ROBOT)  # beyond the command limit
    member, _ = project(shape, MIXED, robot=DEFAULT_ROBOT)
    assert np.abs(member.commands(DEFAULT_ROBOT)).max() <= 2.2 + 1e-12
    np.testing.assert_allclose(
        project(member.shape(DEFAULT_ROBOT), MIXED, robot=DEFAULT_ROBOT)[0].shape(DEFAULT_ROBOT),
        member.shape(DEFAULT_ROBOT),
        atol=1e-14,
    )


def test_the_exported_csv_carries_the_member_whose_parameters_give_its_commands_to_the_bit():
    from types import SimpleNamespace

    from snakeloco.app.export.gait_csv import gait_comments

    member, _ = project(
        draw_structured(UNDULATE, 0, 2, 0, robot=DEFAULT_ROBOT)[0], UNDULATE, robot=DEFAULT_ROBOT
    )
    gait = SimpleNamespace(latents=None, source="model", member=member)
    text = write_gait_csv(member.commands(DEFAULT_ROBOT), gait_comments(gait, None, "abc"), DEFAULT_ROBOT)
    assert "# gait: undulation" in text
    again = read_member(text)
    assert again == member
    np.testing.assert_array_equal(
        again.commands(DEFAULT_ROBOT), read_gait_csv(text, robot=DEFAULT_ROBOT).commands
    )  # to the bit
    with pytest.raises(GaitCSVError, match="member"):
        read_member(text.replace('"a_yaw":', '"a_yaw_typo":'))


def test_a_yaw_wave_near_the_range_edge_projects_onto_itself_not_its_clipped_alias():
    """Yaw joints sit two modules apart, so with a free phase nu and nu - pi fit alike; record 1084
    of the every family (nu_yaw 1.54 of 1.6) projected onto -1.6, 0.25% off, before both halves'
    best were polished."""
    drawn = {
        "kind": "turn",
        "wave": {
            "a_pitch": 0.19,
            "a_yaw": 0.32,
            "nu_pitch": 0.12,
            "nu_yaw": 1.54,
            "delta": -1.28,
            "frequency": 0.29,
        },
        "steering": {"amplitude": 0.27, "phase": -1.16, "frequency": 0.05},
        "scale": 1.0,
    }
    member = member_from_draw(drawn)
    again, res = project(member.shape(DEFAULT_ROBOT), STRUCTURED_PRESETS["every"], robot=DEFAULT_ROBOT)
    assert res < 1e-12 and again.wave.nu_yaw == pytest.approx(1.54, abs=1e-9)
