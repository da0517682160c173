"""Gait families in the designer: a dropdown per tab switches checkpoints (sliders rebuilt for that
model's z_B), another tab keeps its own, and each family's decoded path is drawn as what it promises."""

from __future__ import annotations

import numpy as np
import pytest

from snakeloco.app.export.gait_csv import read_gait_csv
from snakeloco.model import TrainConfig, load_pretrained, train
from snakeloco.sim import GenerateConfig
from snakeloco.sim.data.generate import generate_dataset
from snakeloco.sim.robot.description import DEFAULT_ROBOT

from helpers import SMALL, apply, connect_headless, quiet_server


@pytest.fixture(scope="module")
def structured_checkpoint(tmp_path_factory):
    """A tiny checkpoint of the structured family with another z_B size (2) than the shared one (3)."""
    work = tmp_path_factory.mktemp("structured")
    data = generate_dataset(
        GenerateConfig(num_samples=3, seed=3, family="structured"), work / "s.npz", workers=2
    )
    cfg = TrainConfig(epochs=2, batch_size=2, val_fraction=0.34)
    train(data, work / "ckpt", cfg, SMALL.model_copy(update={"z_b_dim": 2}), log=None, progress=False)
    return work / "ckpt"


@pytest.mark.slow
def test_the_gait_family_dropdown_switches_one_tab_and_everything_works_in_both(
    checkpoint, structured_checkpoint
):
    assert load_pretrained(structured_checkpoint).family == "structured"  # recorded from its data
    families = {"paper": checkpoint, "structured": structured_checkpoint}
    srv = quiet_server("paper", families=families, ensemble=3)
    clients = []
    try:
        c1, d1 = connect_headless(srv)
        c2, d2 = connect_headless(srv)
        clients += [c1, c2]
        assert d1.controls.family.options == ("paper", "structured") and d1.controls.family.value == "paper"
        assert len(d1.sliders) == 3 and d1.scene.band is not None and d1.scene.band.visible  # a mean + a ring

        assert apply(d1, d1.controls.family, "structured")
        assert d1.model is srv.models["structured"] and d1.session.model is d1.model
        assert len(d1.sliders) == 2 and d1.decoded.latents.z_b == (0.0, 0.0)
        assert not d1.scene.band.visible  # drawn as the line it is
        assert d1.simulated is not None and d1.simulated.ensemble_body.shape[0] == 3
        assert d2.model is srv.models["paper"] and len(d2.sliders) == 3  # the other tab keeps its family
        assert "paper family: random multisines are chaotic" in d2.controls.readout.content  # said why

        # Sliders, export/import and design all work for the new family's z_B.
        assert apply(d1, d1.sliders[1], 0.5)
        assert d1.decoded.latents.z_b == (0.0, 0.5) and d1.simulated is not None
        text = d1.files.export_text()
        before = d1.version
        assert d1.files.import_bytes("again.csv", text.encode()) is not None
        assert d1.version > before and d1.wait_idle(60)
        # an export of this family comes back as the gait it was (its z_B decoded again)
        assert d1.decoded.source == "model" and d1.decoded.latents.z_b == (0.0, 0.5) and len(d1.sliders) == 2
        np.testing.assert_array_equal(
            d1.decoded.commands, read_gait_csv(text, robot=DEFAULT_ROBOT).commands
        )  # exactly as exported
        from snakeloco.model.design.config import DesignConfig

        d1.design.config = DesignConfig(candidates=1, screen=16, starts=1, generations=3, population=4)
        d1.design.request()
        assert d1.design.worker.wait_idle(120) and len(d1.design.candidates[0].z_b) == 2

        before = d1.version
        assert d1.moves.switch_family("paper") is not None
        assert d1.version > before and d1.wait_idle(60)
        assert len(d1.sliders) == 3 and d1.decoded.latents.z_b == (0.0, 0.0, 0.0)
        assert d1.design.candidates == []  # the other model's candidates are gone
        assert srv.errors == []
    finally:
        for c in clients:
            c.close()
        srv.stop()


def test_a_newcomers_designer_opens_on_the_structured_family(tmp_path):
    """`snakeloco serve` with no --checkpoint: the family whose promise holds, the paper one a click away."""
    from snakeloco.app.server.lifecycle import load_families

    models, default = load_families(None)
    assert default == "structured" and list(models) == ["structured", "paper"]
    srv = quiet_server()
    client, d = connect_headless(srv)
    try:
        assert d.model.family == "structured" and d.controls.family.value == "structured"
        assert "paper family: random multisines are chaotic" not in d.controls.readout.content
    finally:
        client.close()
        srv.stop()
