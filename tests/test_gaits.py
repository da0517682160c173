"""The gait library: the gait equation as a joint shape, presets that reproduce their figures, the
`snakeloco gait` command and the designer's Baseline dropdown."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pydantic import ValidationError

from snakeloco.app.cli.main import main
from snakeloco.app.export.gait_csv import read_gait_csv
from snakeloco.sim import RECORD, joint_shape
from snakeloco.sim.gaits.library import PRESETS, GaitEquation, measure_gait
from snakeloco.sim.physics.simulator import Simulator, replay
from snakeloco.sim.robot.description import DEFAULT_ROBOT

from helpers import apply, connect_headless, quiet_server


def test_gait_equation_is_a_joint_shape_on_one_excited_bin():
    g = GaitEquation(a_pitch=0.3, a_yaw=0.8, nu_pitch=0.8, nu_yaw=-0.5, delta=np.pi / 4, frequency=0.93)
    u = g.commands(DEFAULT_ROBOT)  # (2000, 8)
    t, k = RECORD.times[:, None], np.arange(1, 9)[None, :]
    wave = 2 * np.pi * 0.93 * t
    expected = np.where(k % 2 == 1, 0.3 * np.sin(0.8 * k + wave), 0.8 * np.sin(-0.5 * k + wave + np.pi / 4))
    np.testing.assert_allclose(u, expected, atol=1e-12)
    np.testing.assert_allclose(
        joint_shape(u), g.shape(DEFAULT_ROBOT), atol=1e-12
    )  # its shape is the FFT of its commands
    energy = (g.shape(DEFAULT_ROBOT) ** 2).sum(axis=(0, 2))  # (L,)
    assert np.count_nonzero(energy) == 1 and RECORD.freqs[np.argmax(energy)] == pytest.approx(0.93)
    with pytest.raises(ValidationError, match="not one of the record's excited frequencies"):
        GaitEquation(frequency=0.5)
    with pytest.raises(ValidationError):
        GaitEquation(a_yaw=2.5)  # beyond the 2.2 rad command limit


def test_library_has_the_gaits_the_designer_offers():
    assert {"sidewind", "roll", "undulate", "turn"} <= set(PRESETS)
    for name, p in PRESETS.items():
        assert p.measured.spread <= 0.1, name  # every library gait is one physics can predict
    assert abs(PRESETS["roll"].measured.net_roll) > 2 * np.pi  # it rolls over
    for name in ("sidewind", "undulate", "turn"):
        assert abs(PRESETS[name].measured.net_roll) < np.pi, name  # these do not
    assert abs(PRESETS["sidewind"].measured.direction_deg) > 45  # sideways
    assert abs(PRESETS["undulate"].measured.direction_deg) < 45  # forward
    assert abs(PRESETS["turn"].measured.net_yaw) > np.pi  # turns more than half a circle


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PRESETS))
def test_presets_reproduce_their_documented_figures(name):
    """Replayed as the library was measured (4-member ensemble, seed 0): displacement within 5% or
    5 cm, heading within 10 deg, net roll and yaw within 5% or 0.3 rad, spread within 0.05."""
    simulator = Simulator(None)
    try:
        got, want = measure_gait(PRESETS[name].gait, simulator), PRESETS[name].measured
    finally:
        simulator.close()
    assert got.displacement == pytest.approx(want.displacement, rel=0.05, abs=0.05)
    assert abs(got.direction_deg - want.direction_deg) < 10
    assert got.net_roll == pytest.approx(want.net_roll, rel=0.05, abs=0.3)
    assert got.net_yaw == pytest.approx(want.net_yaw, rel=0.05, abs=0.3)
    assert abs(got.spread - want.spread) < 0.05


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PRESETS))
def test_presets_worst_cases_reproduce_over_the_default_variation_set(name):
    """``gait --list``'s worst case of each library gait, replayed: the same variation, the same end
    error within 2% (the figures were measured with MuJoCo 4.0.1)."""
    from snakeloco.sim.robot.variations import DEFAULT_SET
    from snakeloco.sim.scores.robustness import robustness

    p, simulator = PRESETS[name], Simulator(None)
    try:
        got = robustness(p.gait.commands(DEFAULT_ROBOT), DEFAULT_SET, simulator)
    finally:
        simulator.close()
    assert got["worst"] == p.worst.variation
    assert got["worst_end_error_m"] == pytest.approx(p.worst.end_error_m, rel=0.02)
    assert got["worst_rel"] == pytest.approx(p.worst.rel, rel=0.02)


def test_gait_command_writes_and_lists_the_library(tmp_path, capsys):
    out = tmp_path / "sidewind.csv"
    main(["gait", "sidewind", "--out", str(out)])
    assert f"wrote {out}" in capsys.readouterr().out
    text = out.read_text()
    assert "# snakeloco gait: library gait sidewind" in text
    np.testing.assert_array_equal(
        read_gait_csv(text, robot=DEFAULT_ROBOT).commands, PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)
    )
    main(["gait", "--list"])
    listed = capsys.readouterr().out
    assert all(name in listed for name in PRESETS) and "BL/s" in listed
    assert "worst variation" in listed and PRESETS["roll"].worst.variation in listed
    for argv, says in (
        (["gait"], "name a library gait"),
        (["gait", "roll"], "--out FILE.csv is needed"),
    ):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2 and says in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["gait", "fly", "--out", str(tmp_path / "x.csv")])
    assert exc.value.code == 2 and not (tmp_path / "x.csv").exists()


@pytest.mark.slow
def test_baseline_dropdown_makes_a_library_gait_the_current_one(checkpoint):

    srv = quiet_server(checkpoint)
    client, d = connect_headless(srv)
    try:
        assert apply(d, d.controls.baseline, "undulate", 120)
        commands = PRESETS["undulate"].gait.commands(DEFAULT_ROBOT)
        assert d.decoded.source == "library: undulate"
        np.testing.assert_array_equal(d.decoded.commands, commands)
        np.testing.assert_array_equal(d.simulated.body, replay(commands).body)  # replayed as it is
        assert d.simulated.figures and len(d.simulated.ensemble_body) == 2
        exported = read_gait_csv(d.files.export_text(), robot=DEFAULT_ROBOT)
        np.testing.assert_array_equal(exported.commands, commands)  # and exportable
        assert "# z_B (encoded)" in d.files.export_text()  # the sliders sit where it encodes
        # A slider move replaces it with a decoded gait and clears the dropdown, so the library gait
        # can be picked again.
        assert apply(d, d.sliders[0], 0.4, 120)
        assert d.decoded.source == "model" and d.controls.baseline.value == "none"
        assert apply(d, d.controls.baseline, "undulate", 120)
        assert d.decoded.source == "library: undulate"
    finally:
        client.close()
        srv.stop()


def test_search_robust_writes_only_the_gaits_that_beat_the_library_into_it(tmp_path):
    """``gait --search-robust --write-library``: the robust-* gaits are replaced by the found ones
    that move less than the library's gait of their kind; the first four stay; figures to 4 digits."""
    from snakeloco.model.design.library import write_library
    from snakeloco.sim.gaits.library import BASE_GAITS, LIBRARY_FILE, GaitPreset

    library = tmp_path / "library.json"
    library.write_text(LIBRARY_FILE.read_text())
    roll = PRESETS["roll"]
    chosen = {
        name: {
            "gait": roll.gait.model_dump(),
            "describe": "rolling",
            "sector": sector,
            "candidates": 7,
            "measured": roll.measured.model_dump() | {"displacement": 8.123456},
            "worst": {"end_error_m": 1.0, "rel": rel, "variation": "servo kp x2"},
            "beats_library": rel < roll.worst.rel,
        }
        for name, sector, rel in (("robust-roll-right", "right", 0.2), ("robust-roll-left", "left", 5.0))
    }
    assert write_library({"chosen": chosen}, library) == ["robust-roll-right"]
    entries = json.loads(library.read_text())
    names = [e["name"] for e in entries]
    assert names[: len(BASE_GAITS)] == list(BASE_GAITS) and names[len(BASE_GAITS) :] == ["robust-roll-right"]
    written = GaitPreset.model_validate({k: v for k, v in entries[-1].items() if k != "name"})
    assert written.measured.displacement == 8.123 and written.worst.rel == 0.2
    assert (
        written.about
        == "rolling; ends right of its start: the most robust of 7 such members over the default variation set"
    )


def test_one_gait_has_one_distance_direction_and_heading_change_everywhere(tmp_path, capsys):
    """Issue 71: the library's sidewinding from ``gait --list``, ``robustness --json``, the gait CSV's
    header and the html page's text: the same distance, direction of travel and heading change."""
    import re

    from snakeloco.app.export.share import readout
    from snakeloco.sim.physics.simulator import replay

    found = {}
    main(["gait", "--list"])
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("sidewind "))
    cells = row.split("|")[1].split()
    found["gait --list"] = (float(cells[2]), cells[4], cells[5])
    gait = tmp_path / "sidewind.csv"
    main(["gait", "sidewind", "--out", str(gait)])
    capsys.readouterr()
    main(["robustness", str(gait), "--set", str(_one_variation(tmp_path)), "--json"])
    nom = json.loads(capsys.readouterr().out.splitlines()[-1])["nominal"]
    found["robustness --json"] = (
        round(nom["distance_m"], 2),
        f"{nom['direction_deg']:+.0f}°",
        f"{nom['heading_change_deg']:+.0f}°",
    )
    header = next(line for line in gait.read_text().splitlines() if line.startswith("# measured:"))
    m = re.search(r"distance ([\d.]+) m .* direction of travel ([+-]\d+°), heading change ([+-]\d+°)", header)
    found["CSV header"] = (float(m[1]), m[2], m[3])
    page = readout(
        replay(PRESETS["sidewind"].gait.commands(DEFAULT_ROBOT)).body, np.zeros((0, 2)), None, "sidewind"
    )
    m = re.search(
        r"distance ([\d.]+) m in 100 s, direction of travel ([+-]\d+°), heading change ([+-]\d+°)", page
    )
    found["html page"] = (float(m[1]), m[2], m[3])
    assert len(set(found.values())) == 1, found
    assert found["gait --list"] == (23.96, "+123°", "+77°")


def _one_variation(tmp_path):
    path = tmp_path / "one.yaml"
    path.write_text("- name: dusty\n  scale: {friction_along: 0.9, friction_across: 0.9}\n")
    return path
