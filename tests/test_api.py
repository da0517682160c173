"""Checkpoints and the GaitModel API: writing, loading (shipped ones by family), refusing bad ones, the
traced decodes equal to the eager ones."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from snakeloco.model import (
    CheckpointError,
    load_checkpoint,
    load_pretrained,
    save_checkpoint,
)
from snakeloco.model.checkpoint import CheckpointConfig
from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.robot.description import DEFAULT_ROBOT

from helpers import SMALL, fresh_net, unit_normalization


def test_training_writes_metrics_and_checkpoint(checkpoint):
    rows = [json.loads(line) for line in (checkpoint / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [0, 1]
    for key in ("train_loss", "val_loss", "val_r2_shape", "val_r2_body", "lr"):
        assert np.isfinite(rows[-1][key])
    cfg = json.loads((checkpoint / "config.json").read_text())
    assert cfg["schema_version"] == 4 and cfg["model"]["z_b_dim"] == 3
    assert len(cfg["freqs"]) == 8 and cfg["summary"]["epochs_run"] == 2


def test_checkpoint_round_trip_is_bit_identical(checkpoint, tmp_path):
    net, cfg = load_checkpoint(checkpoint)
    save_checkpoint(tmp_path, net, cfg)
    net2, cfg2 = load_checkpoint(tmp_path)
    assert cfg2 == cfg
    for (k, a), (k2, b) in zip(net.state_dict().items(), net2.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(a, b)
    assert (tmp_path / "model.safetensors").read_bytes() == (checkpoint / "model.safetensors").read_bytes()


def test_gait_model_api_units_and_shapes(checkpoint, tiny_dataset):
    model = load_pretrained(checkpoint)
    assert model.z_b_dim == 3 and model.z_j_dim == 4
    np.testing.assert_allclose(model.freqs, tiny_dataset.freqs)
    z_b, z_j = model.encode(tiny_dataset.shape[:2], tiny_dataset.body_ds[:2])
    assert z_b.shape == (2, 3) and z_j.shape == (2, 8, 4)
    shape, body = model.decode(z_b)
    assert shape.shape == (2, 8, 8, 2) and body.shape == (2, 500, 6)
    # Physical units: a decode of the normalised origin sits near the training data's mean scale.
    norm = model.config.normalization.arrays()
    assert np.abs(body).max() < 10 * (np.abs(norm["body_mean"]).max() + norm["body_std"].max())
    draws = model.sample_joint_latents(z_b[0], 5, seed=3)
    assert draws.shape == (5, 8, 4)
    np.testing.assert_array_equal(draws, model.sample_joint_latents(z_b[0], 5, seed=3))
    assert not np.array_equal(draws, model.sample_joint_latents(z_b[0], 5, seed=4))
    assert model.sample_joint_latents(z_b, 2, seed=0).shape == (2, 2, 8, 4)
    with pytest.raises(ValueError, match="z_b must be"):
        model.decode(np.zeros((1, 5)))
    # Wrong shapes and non-finite values are named, not reshaped or decoded to NaN commands.
    with pytest.raises(ValueError, match=r"z_j must be \(2, 8, 4\) for 2 z_b, got \(2, 8, 2\)"):
        model.decode(z_b, np.zeros((2, 8, 2)))
    with pytest.raises(ValueError, match="z_b holds 1 non-finite"):
        model.decode(np.array([[0.0, np.nan, 0.0]]))
    bad_z_j = np.zeros((1, 8, 4))
    bad_z_j[0, 2, 1] = np.inf
    with pytest.raises(ValueError, match="z_j holds 1 non-finite"):
        model.decode(z_b[:1], bad_z_j)
    with pytest.raises(ValueError, match="body_ds holds"):
        model.encode(tiny_dataset.shape[:1], np.full((1, 500, 6), np.nan))
    with pytest.raises(ValueError, match="shape must be"):
        model.predict_stats(tiny_dataset.shape[0])
    with pytest.raises(ValueError, match="n must be at least 1"):
        model.sample_joint_latents(z_b[0], 0)
    # Trained on this robot: no warning; a checkpoint of another MJCF says so.
    assert model.robot_warning() is None
    other = type(model)(model.net, model.config.model_copy(update={"mjcf_sha256": "f" * 64}))
    assert "trained on robot snakeloco-8 (MJCF sha256 ffffffffffff)" in other.robot_warning()


def test_bad_checkpoints_are_refused_clearly(checkpoint, tmp_path):
    with pytest.raises(CheckpointError, match=r"missing config\.json"):
        load_checkpoint(tmp_path / "nothing")
    bad = _copy(checkpoint, tmp_path / "trunc")
    data = (bad / "model.safetensors").read_bytes()
    (bad / "model.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"corrupt model\.safetensors"):
        load_checkpoint(bad)
    bad = _copy(checkpoint, tmp_path / "json")
    (bad / "config.json").write_text("{ not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(bad)
    bad = _copy(checkpoint, tmp_path / "schema")
    cfg = json.loads((bad / "config.json").read_text())
    (bad / "config.json").write_text(json.dumps(cfg | {"schema_version": 7}))
    with pytest.raises(CheckpointError, match="schema version 7"):
        load_checkpoint(bad)
    bad = _copy(checkpoint, tmp_path / "mismatch")
    cfg["model"]["z_b_dim"] = 5
    (bad / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="weights do not match its config"):
        load_checkpoint(bad)
    bad = _copy(checkpoint, tmp_path / "invalid")
    cfg["model"]["z_b_dim"] = 3
    cfg["freqs"] = [1.0]
    (bad / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match=r"invalid config\.json"):
        load_checkpoint(bad)


def test_schema_2_checkpoint_loads_with_its_statistics_blind_decoder(tmp_path):
    """Checkpoints written before the decoder saw the statistics still load and decode as built."""
    old_cfg = SMALL.model_copy(update={"body_sees_stats": False})
    net = fresh_net(old_cfg)
    config = CheckpointConfig(
        schema_version=3,
        model=old_cfg,
        normalization=unit_normalization(),
        freqs=RECORD.freqs.tolist(),
        dataset_meta_sha256="0" * 64,
        mjcf_sha256="0" * 64,
    )
    save_checkpoint(tmp_path, net, config)
    raw = json.loads((tmp_path / "config.json").read_text())
    del raw["model"]["body_sees_stats"]
    (tmp_path / "config.json").write_text(json.dumps(raw | {"schema_version": 2}))
    loaded, cfg = load_checkpoint(tmp_path)
    assert not cfg.model.body_sees_stats
    z = torch.randn(2, 3)
    with torch.no_grad():
        assert torch.equal(loaded.generate(z)[1], net.generate(z)[1])
    raw["model"]["body_sees_stats"] = True  # a version-2 file claiming the new decoder: refused
    (tmp_path / "config.json").write_text(json.dumps(raw | {"schema_version": 2}))
    with pytest.raises(CheckpointError, match="weights do not match its config"):
        load_checkpoint(tmp_path)


def test_single_z_decode_runs_traced_and_matches_eager_exactly(checkpoint):
    m = load_pretrained(checkpoint)
    rng = np.random.default_rng(3)
    for z_j in (None, rng.standard_normal((1, 8, m.z_j_dim))):
        z_b = rng.standard_normal((1, m.z_b_dim))
        shape, body, stats = m.decode_with_stats(z_b, z_j)
        with torch.inference_mode():
            zj = None if z_j is None else torch.as_tensor(z_j, dtype=torch.float32)
            e_shape, e_body, e_stats = m.net.generate(torch.as_tensor(z_b, dtype=torch.float32), zj)
        ref_shape, ref_body = m._phys(e_shape, e_body)
        np.testing.assert_array_equal(shape, ref_shape)
        np.testing.assert_array_equal(body, ref_body)
        ref_stats = m.stats_from_network(e_stats.numpy())
        for k, v in ref_stats.items():
            np.testing.assert_array_equal(stats[k], v)
    assert m._graphs.made["generate"] is not None  # the slider path ran the traced graph
    z_b = rng.standard_normal(m.z_b_dim)
    sampled = m.sample_joint_latents(z_b, 1, seed=5, temperature=0.7)
    assert m._graphs.made["sample_joints"] is not None
    eps = torch.randn(1, 1, 8, m.z_j_dim, generator=torch.Generator().manual_seed(5)) * 0.7
    with torch.inference_mode():
        eager = m.net.sample_joints(torch.as_tensor(z_b[None], dtype=torch.float32), eps[0])
    np.testing.assert_array_equal(sampled[0], eager.numpy().astype(np.float64)[0])


def test_one_members_path_and_statistics_run_traced_and_match_eager_exactly():
    from snakeloco.model.heads.member_path import member_inputs

    m = load_pretrained("structured")  # the shipped checkpoint with a member path head
    z_b = m.sample_z_b(1, seed=4)
    members, _, measured, body, stats = m.decode_members(z_b)
    assert m._graphs.made["member_head"] is not None and m._graphs.made["predict_stats"] is not None
    head = m.config.member_head
    x = member_inputs(
        members, np.asarray(head.support), z_b if head.z_b_dim else None, head.inputs, DEFAULT_ROBOT
    )
    with torch.inference_mode():
        eager_body = m.member_head(torch.as_tensor(x, dtype=torch.float32)).numpy().astype(np.float64)
        eager_stats = m.stats_from_network(m.net.predict_stats(m.normalize_shape(measured)).numpy())
    np.testing.assert_array_equal(body, eager_body * m._body_std + m._body_mean)
    for k, v in eager_stats.items():
        np.testing.assert_array_equal(stats[k], v)


def test_shipped_checkpoints_load_by_family_name(tmp_path, monkeypatch, capsys):
    from snakeloco.app.cli.main import main
    from snakeloco.model.checkpoint import PRETRAINED_DIR, SHIPPED, STRUCTURED_DIR

    assert SHIPPED == {"paper": PRETRAINED_DIR, "structured": STRUCTURED_DIR}
    structured, default = load_pretrained("structured"), load_pretrained()
    assert structured.path == default.path == STRUCTURED_DIR and structured.config == default.config
    by_name = load_pretrained("paper")
    assert by_name.path == PRETRAINED_DIR
    assert structured.family == "structured" and structured.robot_warning() is None
    # The library family: the pitch joints' waves at 0.29 and 0.52 Hz (rolling, turning, sidewinding),
    # the yaw joints' also at 0.93 Hz (undulation); no steering bin.
    support = np.asarray(structured.config.shape_support, bool)
    freqs = np.asarray(structured.config.freqs)
    assert [freqs[row].tolist() for row in support[0::2]] == [[0.29, 0.52]] * 4
    assert [freqs[row].tolist() for row in support[1::2]] == [[0.29, 0.52, 0.93]] * 4
    # Both ship a slider density; the structured one decodes exact members with their predicted paths.
    assert by_name.config.density is not None and not by_name.projects
    assert (
        structured.config.density is not None and structured.projects and structured.member_head is not None
    )
    for m in (by_name, structured):
        z = m.sample_z_b(64, seed=11)
        assert m.off_data(z).mean() < 0.1 and m.off_data(np.full((1, m.z_b_dim), 6.0))[0]
    main(["bench", "model", "--checkpoint", "paper", "--calls", "3", "--json"])
    bench = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 0 < bench["decode_p50_ms"] <= bench["decode_p95_ms"] < 5e3, bench
    # A directory of that name here is what the user means; a name that is neither says what is shipped.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "paper").mkdir()
    with pytest.raises(CheckpointError, match=r"checkpoint paper: missing config\.json$"):
        load_pretrained("paper")
    with pytest.raises(
        CheckpointError,
        match=r"missing config.json \(no such directory; shipped checkpoints: structured, paper\)",
    ):
        load_pretrained("undulate")


def test_decoded_coefficients_outside_the_support_are_zero(checkpoint, tmp_path):
    cfg = json.loads((checkpoint / "config.json").read_text())
    assert np.asarray(cfg["shape_support"]).all()  # the paper's multisines excite every coefficient
    still = _copy(checkpoint, tmp_path / "still")
    support = np.ones((8, SMALL.n_components), bool)
    support[0::2] = False  # a family that keeps its pitch joints still
    (still / "config.json").write_text(json.dumps(cfg | {"shape_support": support.tolist()}))
    z = np.random.default_rng(0).standard_normal((5, SMALL.z_b_dim))
    free, _ = load_pretrained(checkpoint).decode(z)
    kept, _ = load_pretrained(still).decode(z)
    assert np.abs(free[:, 0::2]).max() > 1e-3 and np.all(kept[:, 0::2] == 0)
    np.testing.assert_array_equal(kept[:, 1::2], free[:, 1::2])
    (still / "config.json").write_text(json.dumps(cfg | {"shape_support": support[:4].tolist()}))
    with pytest.raises(CheckpointError, match="shape_support must be"):
        load_checkpoint(still)


def _copy(src, dst):
    dst.mkdir()
    for p in src.iterdir():
        (dst / p.name).write_bytes(p.read_bytes())
    return dst
