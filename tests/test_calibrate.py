"""Calibration: the model's own prior gaits replayed, the head and the body decoder fitted to them."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import torch

from snakeloco.model import load_pretrained
from snakeloco.model.replays import Fit

from helpers import SMALL


def test_calibration_counts_are_checked_in_the_config():
    from pydantic import ValidationError

    from snakeloco.model.heads.calibrate import CalibrateConfig

    assert CalibrateConfig(prior_samples=2).gait_count == 2 * 3 + 8 + 4 * 2  # defaults 4n and 2n
    assert CalibrateConfig(prior_samples=2, zero_samples=0, sampled_samples=1).gait_count == 6 + 0 + 2
    for bad in ({"prior_samples": 0}, {"zero_samples": -1}, {"sampled_samples": -1}, {"lr": float("nan")}):
        with pytest.raises(ValidationError, match=next(iter(bad))):
            CalibrateConfig(**bad)


@pytest.mark.slow
def test_calibration_tunes_only_the_head_and_body_decoder(checkpoint, tiny_dataset_path, tmp_path):
    from snakeloco.model.checkpoint import load_checkpoint
    from snakeloco.model.heads.calibrate import MODES, CalibrateConfig, calibrate
    from snakeloco.sim import DatasetError, GenerateConfig
    from snakeloco.sim.data.generate import generate_dataset

    out, gaits = tmp_path / "calibrated", tmp_path / "gaits.npz"
    cfg = CalibrateConfig(prior_samples=4, epochs=3)
    summary = calibrate(Fit(checkpoint, tiny_dataset_path, out, gaits, log=None), cfg)
    # 4 z_B in every mode, and by default 4 x 4 more with z_k = 0 only and 2 x 4 more in each
    # sampled mode.
    assert summary["zero_samples"] == 16 and summary["sampled_samples"] == 8
    assert summary["gaits"] + sum(summary["broken"].values()) == 4 * len(MODES) + 16 + 8 * (len(MODES) - 1)
    assert (
        {"generated", "dataset"} <= set(summary["median_rel_err_after"]) <= {"generated", "dataset", *MODES}
    )
    before, _ = load_checkpoint(checkpoint)
    after, config = load_checkpoint(out)
    assert config.summary.model_extra["calibration"]["prior_samples"] == 4

    def changed(net) -> set[str]:
        return {k for k, v in net.state_dict().items() if not torch.equal(v, before.state_dict()[k])}

    # Stage 1 tunes the statistics head, stage 2 the body decoder; the body encoder and the GRUs,
    # and so the decoded shapes and the z_B posteriors, stay as trained.
    head, decoder = ("signal_net.", "stats_head."), ("dec_in.", "dec_film.", "decoder.")
    tuned = changed(after)
    assert all(k.startswith(head + decoder) for k in tuned), tuned
    assert all(any(k.startswith(p) for k in tuned) for p in head + decoder), tuned
    path = summary["path"]
    val = {k: 0.5 * (path[k]["generated"] + path[k]["dataset"]) for k in ("mse_before", "mse_after")}
    assert path["best_epoch"] >= 0 and val["mse_after"] < val["mse_before"]
    # Decoded shapes are unchanged; the predicted statistics and the body path move.
    z = torch.zeros(2, SMALL.z_b_dim)
    with torch.no_grad():
        s0, b0, st0 = before.generate(z)
        s1, b1, st1 = after.generate(z)
        assert torch.equal(s0, s1) and not torch.equal(st0, st1) and not torch.equal(b0, b1)
    other = generate_dataset(GenerateConfig(num_samples=2, seed=99), tmp_path / "other.npz", workers=2)
    with pytest.raises(DatasetError, match="not the dataset this checkpoint was trained on"):
        calibrate(
            Fit(checkpoint, other, tmp_path / "x", log=None), CalibrateConfig(prior_samples=2, epochs=1)
        )


@pytest.mark.slow
def test_calibration_gaits_file_is_reused_and_checked(checkpoint, tiny_dataset_path, tmp_path, monkeypatch):
    import snakeloco.model.heads.calibrate as cal
    from snakeloco.model.checkpoint import load_checkpoint
    from snakeloco.sim import DatasetError

    gaits_file = tmp_path / "gaits.npz"
    cfg = cal.CalibrateConfig(prior_samples=3, epochs=2, zero_samples=1, sampled_samples=1)

    def run(out: str, cfg: cal.CalibrateConfig = cfg) -> dict:
        return cal.calibrate(Fit(checkpoint, tiny_dataset_path, tmp_path / out, gaits_file, log=None), cfg)

    first = run("a")
    assert gaits_file.exists()
    replay = cal.replay_prior_gaits

    def no_replay(*args, **kwargs):
        raise AssertionError("replayed although the gaits file exists")

    # The second run replays nothing and trains to the same weights.
    monkeypatch.setattr(cal, "replay_prior_gaits", no_replay)
    second = run("b")
    assert first["median_rel_err_after"] == second["median_rel_err_after"]
    a, _ = load_checkpoint(tmp_path / "a")
    b, _ = load_checkpoint(tmp_path / "b")
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    # Another learning rate, from the same file: other weights, and the summary records it.
    other_lr = run("c", cfg.model_copy(update={"lr": 1e-3}))
    assert other_lr["lr"] == 1e-3 and first["lr"] == 1e-2
    c, _ = load_checkpoint(tmp_path / "c")
    assert not torch.equal(c.state_dict()["stats_head.0.weight"], a.state_dict()["stats_head.0.weight"])
    model = load_pretrained(checkpoint)
    for change, says in (
        ({"prior_samples": 4}, r"'n': 3, .*'n': 4"),
        ({"zero_samples": 6}, r"'zero_samples': 1, .*'zero_samples': 6"),
        ({"sampled_samples": 0}, r"'sampled_samples': 1, .*'sampled_samples': 0"),
    ):
        with pytest.raises(DatasetError, match=says):
            cal.load_gaits(gaits_file, model, cfg.model_copy(update=change))
    # Gaits decoded by another checkpoint are refused, not silently trained on.
    small = cal.CalibrateConfig(prior_samples=2, seed=5, zero_samples=0, sampled_samples=0)
    gaits = replay(model, small, Fit(checkpoint, "", "", workers=1))
    gaits["shape"] = gaits["shape"] + 0.01
    cal.save_gaits(tmp_path / "other.npz", gaits, small)
    with pytest.raises(DatasetError, match="decoded by another checkpoint"):
        cal.load_gaits(tmp_path / "other.npz", model, small)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match=r"not a calibration-gaits \.npz \(no zip archive"):
        cal.load_gaits(tmp_path / "junk.npz", model, small)
    with zipfile.ZipFile(tmp_path / "garbled.npz", "w") as zf:
        zf.writestr("shape.npy", b"\x93NUMPY garbled header")
    with pytest.raises(DatasetError, match="not a readable calibration-gaits"):
        cal.load_gaits(tmp_path / "garbled.npz", model, small)


def _with_extra_draws(checkpoint, base, first_extra: int, **extra_counts):
    """Calibration gaits replayed for ``base`` and again with more extra draws: both runs, and a mask
    of the second's extra gaits. The gaits before them must be those of the first run, exactly."""
    import snakeloco.model.heads.calibrate as cal

    model = load_pretrained(checkpoint)
    one_thread = Fit(checkpoint, "", "", workers=1)
    before = cal.replay_prior_gaits(model, base, one_thread)
    more = cal.replay_prior_gaits(model, base.model_copy(update=extra_counts), one_thread)
    assert more["broken"].sum() == before["broken"].sum() == 0  # so every draw below is compared
    head = more["z_index"] < first_extra
    for k in ("shape", "stats", "z_b", "z_j", "z_index", "mode"):
        np.testing.assert_array_equal(more[k][head], before[k], err_msg=k)
    return before, more, ~head


@pytest.mark.slow
def test_extra_zero_draws_leave_the_shared_draws_alone(checkpoint):
    import snakeloco.model.heads.calibrate as cal

    base = cal.CalibrateConfig(prior_samples=2, seed=7, zero_samples=0, sampled_samples=0)
    plain, more, extra = _with_extra_draws(checkpoint, base, 2, zero_samples=3)
    assert extra.sum() == 3 and (more["mode"][extra] == cal.ZERO_MODE).all()
    assert (more["z_j"][extra] == 0).all() and set(more["z_index"][extra]) == {2, 3, 4}
    # Their own seed: not the first draws again.
    assert not np.allclose(more["z_b"][extra][:1], plain["z_b"][:1])


@pytest.mark.slow
def test_extra_sampled_draws_come_last_in_every_sampled_mode(checkpoint):
    import snakeloco.model.heads.calibrate as cal

    base = cal.CalibrateConfig(prior_samples=2, seed=7, zero_samples=1, sampled_samples=0)
    before, more, extra = _with_extra_draws(checkpoint, base, 3, sampled_samples=2)
    assert extra.sum() == 2 * len(cal.SAMPLED_MODES)
    assert set(more["mode"][extra]) == set(cal.SAMPLED_MODES) and cal.ZERO_MODE not in cal.SAMPLED_MODES
    assert set(more["z_index"][extra]) == {3, 4}
    # Sampled joint latents (not zeros), different in each mode, on z_B drawn from their own seed.
    assert (np.abs(more["z_j"][extra]).max(axis=(1, 2)) > 0).all()
    first = more["z_index"] == 3
    assert first.sum() == 2 and not np.allclose(*more["z_j"][first])
    assert not np.isin(more["z_b"][extra][:, 0], before["z_b"][:, 0]).any()


def test_head_loss_prefers_the_median():
    from snakeloco.model.heads.finetune import head_loss

    # Nine gaits that barely roll and one that rolls over: absolute error prefers their median (what a
    # median relative error rewards), where training's squared error would prefer their mean.
    y = torch.zeros(10, 4)
    y[-1, 3] = 10.0
    mean, median = torch.zeros(10, 4), torch.zeros(10, 4)
    mean[:, 3] = 1.0
    assert head_loss(median, y) < head_loss(mean, y)
    assert head_loss(median, y) == pytest.approx(10.0 / 40)
    assert torch.nn.functional.mse_loss(mean, y) < torch.nn.functional.mse_loss(median, y)


def test_kind_weights_make_every_kind_of_member_weigh_the_same():
    from types import SimpleNamespace

    from snakeloco.model.heads.member_path import kind_weights

    members = [SimpleNamespace(kind=k) for k in ["undulate"] * 6 + ["roll"] * 2 + ["turn"]]
    w = kind_weights(members)
    assert np.isclose(w.mean(), 1.0)
    for kind in ("undulate", "roll", "turn"):
        assert np.isclose(w[[m.kind == kind for m in members]].sum(), 3.0), kind
    # Another set (the validation examples) by the same shares; a kind the first set lacks weighs 1.
    assert np.allclose(
        kind_weights(members, [SimpleNamespace(kind="roll"), SimpleNamespace(kind="sidewind")]), [1.5, 1.0]
    )
