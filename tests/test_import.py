"""Import CSV round-trips an exported gait: the sliders, the model's path and the readout come back as
they were exported; a file with no model path says why (issue 59, point 5)."""

from __future__ import annotations

import pytest

from snakeloco.app.export.gait_csv import exported_latents, library_gait_csv
from snakeloco.sim.robot.description import DEFAULT_ROBOT

from helpers import apply, connect_headless, quiet_server


def test_the_export_comments_name_the_latents_exactly():
    text = "# z_B: [0.1, -0.30000000000000004]\n# z_k mode: sampled (seed 3, temperature 0.5)\n# checkpoint sha256: ab\n"
    found, why = exported_latents(text)
    assert why == "" and found["z_b"] == (0.1, -0.30000000000000004)
    assert (found["zk_mode"], found["seed"], found["temperature"], found["checkpoint"]) == (
        "sampled",
        3,
        0.5,
        "ab",
    )
    assert exported_latents("time_s,joint_1\n")[0] is None
    assert "not a list of numbers" in exported_latents("# z_B: [a, b]\n")[1]


@pytest.mark.slow
def test_an_exported_gait_imports_as_it_was_exported(member_checkpoint):
    srv = quiet_server(member_checkpoint[0])
    client, d = connect_headless(srv)
    try:
        assert apply(d, d.sliders[0], 0.37)  # somewhere off the slider grid's zero
        exported, z = d.files.export_text(), d.decoded.latents.z_b
        model_row = d.controls.readout.content.split("Model")[1][:200]
        assert apply(d, d.sliders[0], -1.0)
        before = d.version
        assert d.files.import_bytes("mine.csv", exported.encode()) is not None and d.version > before
        assert d.wait_idle(60)
        assert d.decoded.latents is not None and d.decoded.latents.z_b == z  # the model's gait again
        assert d.sliders[0].value == pytest.approx(0.37)
        assert d.controls.readout.content.split("Model")[1][:200] == model_row  # the same model path
        assert d.controls.plots["forward (m)"] is not None and d.simulated is not None

        # A file with no model path says so in the readout, and the sliders show where it encodes.
        assert d.files.import_bytes(
            "roll.csv", library_gait_csv("roll", robot=DEFAULT_ROBOT).encode()
        ) is not None and d.wait_idle(60)
        assert d.decoded.latents is None and "none: the file names no z_B" in d.controls.readout.content
        other = exported.replace(d.model.hash, "f" * 64)
        assert d.files.import_bytes("other.csv", other.encode()) is not None and d.wait_idle(60)
        assert "exported from another checkpoint" in d.controls.readout.content
        assert srv.errors == []
    finally:
        client.close()
        srv.stop()
