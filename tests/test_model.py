"""The hierarchical VAE: shapes, losses, MMD, scheduler, what each decoder sees; checkpoints and the
GaitModel API are in test_api.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from snakeloco.model import (
    HierarchicalVAE,
    ModelConfig,
    TrainConfig,
    cyclic_lr,
    gaussian_mmd,
    load_pretrained,
    loss_terms,
    train,
)
from snakeloco.model.checkpoint import Normalization
from snakeloco.model.vae.metrics import mmd_null_quantile, mmd_numpy, r2_per_channel
from snakeloco.model.vae.train import make_scheduler, shape_support
from snakeloco.sim import shape_to_commands
from snakeloco.sim.gaits.excitation import RECORD

from helpers import SMALL, fresh_net


def test_forward_shapes_and_finite_losses():
    torch.manual_seed(0)
    net = fresh_net()
    shape, body = torch.randn(5, 8, 8, 2), torch.randn(5, 500, 6)
    out = net(shape, body)
    assert out.shape.shape == (5, 8, 8, 2)
    assert out.body.shape == (5, 500, 6)
    assert out.z_b.shape == (5, 3) and out.z_j.shape == (5, 8, 4)
    terms = loss_terms(net, shape, body, torch.randn(5, 4))
    assert out.stats.shape == (5, 4)
    assert set(terms) == {"loss", "rec_joint", "rec_body", "rec_stats", "mmd_joint", "mmd_body"}
    assert all(torch.isfinite(v) for v in terms.values())
    g_shape, g_body, g_stats = net.generate(torch.zeros(2, 3))
    assert g_shape.shape == (2, 8, 8, 2) and g_body.shape == (2, 500, 6) and g_stats.shape == (2, 4)


def test_body_decoder_signals_follow_the_spectral_convention():
    """The signal branch resynthesises exactly what sim.shape_to_commands does, at the body's stamps."""
    rng = np.random.default_rng(0)
    shape = 0.1 * rng.standard_normal((3, 8, 8, 2))  # small: the commands' clip does not bite
    net = fresh_net()
    with torch.no_grad():
        sig = net.joint_signals(torch.as_tensor(shape, dtype=torch.float32)).numpy()  # (3, 16, 500)
    commands = shape_to_commands(shape)  # (3, 2000, 8) at 20 Hz
    np.testing.assert_allclose(sig[:, :8].transpose(0, 2, 1), commands[:, ::4], atol=1e-5)
    # The rate channels are d/dt / (2 pi): compare with a central difference of a 400 Hz synthesis.
    fine = shape_to_commands(shape, n_samples=40000, sample_rate=400.0)
    rate = (np.roll(fine, -1, axis=1) - np.roll(fine, 1, axis=1)) * 400.0 / 2.0 / (2 * np.pi)
    np.testing.assert_allclose(sig[:, 8:].transpose(0, 2, 1), rate[:, ::80], atol=1e-3 * np.abs(rate).max())
    # A body decoder whose transform was never set refuses instead of decoding from zeros.
    with pytest.raises(RuntimeError, match="signal branch not initialised"):
        HierarchicalVAE(SMALL).generate(torch.zeros(1, 3))


def test_mmd_estimator():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(256, 4, generator=gen)
    y = torch.randn(256, 4, generator=gen)
    assert gaussian_mmd(x, x).item() == pytest.approx(0.0, abs=1e-6)
    same = gaussian_mmd(x, y).item()
    shifted = gaussian_mmd(x, y + 1.0).item()
    assert 0.0 <= same < 0.02
    assert shifted > 10 * same
    # The numpy twin agrees, and the null quantile sits above typical same-distribution values.
    assert mmd_numpy(x.numpy(), y.numpy()) == pytest.approx(same, rel=1e-4)
    assert mmd_null_quantile(256, 4, 0.95, repeats=50) > same * 0.5


def test_tiny_model_loss_falls():
    torch.manual_seed(0)
    net = fresh_net()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    # Learnable data: smooth body series whose amplitude and shape coefficients follow one factor.
    a = torch.linspace(-1.5, 1.5, 16)
    t = torch.linspace(0, 1, 500)
    body = a[:, None, None] * torch.cos(torch.pi * t)[None, :, None].expand(16, 500, 6)
    shape = a[:, None, None, None] * torch.ones(16, 8, 8, 2)
    first = first_stats = None
    for _ in range(60):
        terms = loss_terms(net, shape, body, a[:, None].expand(16, 4))
        opt.zero_grad()
        terms["loss"].backward()
        opt.step()
        first = first if first is not None else terms["rec_joint"].item() + terms["rec_body"].item()
        first_stats = first_stats if first_stats is not None else terms["rec_stats"].item()
    last = terms["rec_joint"].item() + terms["rec_body"].item()
    assert terms["rec_stats"].item() < 0.5 * first_stats
    assert last < 0.5 * first


def test_cyclic_schedule_values():
    cfg = TrainConfig(lr_min=2e-4, lr_max=4e-3, cycle_epochs=100, peak_decay=0.5)
    assert cyclic_lr(0, cfg) == pytest.approx(2e-4)
    assert cyclic_lr(50, cfg) == pytest.approx(4e-3)  # first peak
    assert cyclic_lr(100, cfg) == pytest.approx(2e-4)
    assert cyclic_lr(150, cfg) == pytest.approx(2e-4 + 0.5 * (4e-3 - 2e-4))  # decayed once per cycle
    assert cyclic_lr(25, cfg) == pytest.approx(2e-4 + 0.5 * (4e-3 - 2e-4))
    # The torch scheduler realises it per step, and Adam's betas stay put.
    net = torch.nn.Linear(2, 2)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr_max)
    sched = make_scheduler(opt, steps_per_epoch=10, cfg=cfg)
    lrs = []
    for _ in range(1501):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[500] == pytest.approx(4e-3) and lrs[1500] == pytest.approx(cyclic_lr(150, cfg))
    assert opt.param_groups[0]["betas"] == (0.9, 0.999)


def test_body_decoder_sees_the_gait_statistics_but_does_not_train_them():
    torch.manual_seed(0)
    net = fresh_net()
    assert net.cfg.body_sees_stats
    z_b, z_j = torch.randn(3, 3), torch.zeros(3, 8, 4)
    with torch.no_grad():
        net.dec_film.weight.normal_()  # as after training (it starts at zero: the z_B-only decoder)
        a = net.decode_body(z_b, z_j, torch.zeros(3, 4))
        b = net.decode_body(z_b, z_j, torch.ones(3, 4))
    assert not torch.allclose(a, b)
    with pytest.raises(ValueError, match="pass stats"):
        net.decode_body(z_b, z_j)
    # The body loss reaches the decoder but not the statistics head (its input is detached).
    shape, body = torch.randn(4, 8, 8, 2), torch.randn(4, 500, 6)
    torch.nn.functional.mse_loss(net(shape, body).body, body).backward()
    assert all(p.grad is None for p in net.stats_head.parameters())
    assert all(p.grad is None for p in net.signal_net.parameters())
    assert net.dec_film.weight.grad.abs().sum() > 0


def _trained(data, out, cfg: ModelConfig):
    """A checkpoint of ``cfg`` trained for one epoch on ``data``, loaded through the API."""
    train(data, out, TrainConfig(epochs=1, batch_size=2, val_fraction=0.25), cfg, log=None, progress=False)
    return load_pretrained(out)


def test_body_decoder_that_sees_the_joint_signals_starts_as_the_z_b_decoder_and_learns_from_them(
    tiny_dataset_path, tmp_path
):
    torch.manual_seed(0)
    net = fresh_net(SMALL.model_copy(update={"body_sees_signals": True}))
    plain = fresh_net()
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if not k.startswith("body_sig.")})
    z_b, z_j, st = torch.randn(3, 3), torch.zeros(3, 8, 4), torch.zeros(3, 4)
    shape = torch.randn(3, 8, 8, 2)
    with torch.no_grad():  # zero-initialised: the z_B decoder's output exactly
        assert torch.equal(net.decode_body(z_b, z_j, st, shape), plain.decode_body(z_b, z_j, st))
        net.body_sig[-1].weight.normal_()
        assert not torch.allclose(net.decode_body(z_b, z_j, st, shape), net.decode_body(z_b, z_j, st, -shape))
    with pytest.raises(ValueError, match="pass its shape"):
        net.decode_body(z_b, z_j, st)
    # Trained, saved, loaded and decoded through the API like any checkpoint.
    model = _trained(tiny_dataset_path, tmp_path, SMALL.model_copy(update={"body_sees_signals": True}))
    assert model.config.model.body_sees_signals
    _, body_np = model.decode(np.zeros((2, 3)))
    assert np.isfinite(body_np).all() and body_np.shape == (2, 500, 6)


def test_encoder_and_signal_decoder_that_see_each_other_take_the_shape_and_z_b(tiny_dataset_path, tmp_path):
    """The structured preset's options: z_B reaches the signal convolution, the joint signals reach
    the encoder; a call without the shape is refused, and the checkpoint round-trips through the API."""
    cfg = SMALL.model_copy(
        update={"body_sees_signals": True, "body_signals_see_latent": True, "encoder_sees_signals": True}
    )
    torch.manual_seed(0)
    net = fresh_net(cfg)
    z_j, st = torch.zeros(3, 8, 4), torch.zeros(3, 4)
    shape, body = torch.randn(3, 8, 8, 2), torch.randn(3, 500, 6)
    with torch.no_grad():
        net.body_sig[-1].weight.normal_()
        z_b = torch.randn(3, 3)
        # Only the signal branch sees z_B through this path: with the z_B decoder's contribution
        # subtracted, the output still moves with z_B.
        a = net.decode_body(z_b, z_j, st, shape) - net.decode_body(z_b, z_j, st, 0 * shape)
        b = net.decode_body(-z_b, z_j, st, shape) - net.decode_body(-z_b, z_j, st, 0 * shape)
        assert (a - b).abs().max() > 1e-2  # without the option: 6e-8 (rounding)
        mu, _ = net.encode_body(body, shape)
        assert not torch.allclose(mu, net.encode_body(body, -shape)[0])
    with pytest.raises(ValueError, match="pass its shape"):
        net.encode_body(body)
    model = _trained(tiny_dataset_path, tmp_path, cfg)
    data = np.load(tiny_dataset_path)
    z_b_np, _ = model.encode(data["shape"][:2], data["body_ds"][:2])
    assert np.allclose(model.encode_body(data["body_ds"][:2], data["shape"][:2])[0], z_b_np, atol=1e-5)
    _, body_np = model.decode(z_b_np)
    assert np.isfinite(body_np).all() and body_np.shape == (2, 500, 6)


def test_signal_decoder_that_sees_the_whole_shape(tiny_dataset_path, tmp_path):
    """body_signals_see_shape: the gait's shape embedding reaches the signal convolution at every
    time step (a change of one bin's coefficient moves every output step), at the width asked; old
    configs load without it."""
    cfg = SMALL.model_copy(
        update={"body_sees_signals": True, "body_signals_see_shape": True, "body_signal_channels": 6}
    )
    old = {
        k: v
        for k, v in ModelConfig().model_dump().items()
        if k not in ("body_signals_see_shape", "body_signal_channels")
    }
    assert ModelConfig.model_validate(old).body_signals_see_shape is False
    torch.manual_seed(0)
    net = fresh_net(cfg)
    assert net.body_sig[0].out_channels == 6
    z_b, z_j, st = torch.randn(2, 3), torch.zeros(2, 8, 4), torch.zeros(2, 4)
    shape = torch.randn(2, 8, 8, 2)
    with torch.no_grad():
        net.body_sig[-1].weight.normal_()
        other = shape.clone()
        other[:, 3, 5] += 1.0
        moved = (net.decode_body(z_b, z_j, st, other) - net.decode_body(z_b, z_j, st, shape)).abs()
        assert (moved.amax(dim=2) > 0).all()
        # Without the embedding the same change moves the output less (only through the signals).
        net.body_gait[-1].weight.zero_()
        net.body_gait[-1].bias.zero_()
        without = (net.decode_body(z_b, z_j, st, other) - net.decode_body(z_b, z_j, st, shape)).abs()
        assert not torch.allclose(moved, without)
    model = _trained(tiny_dataset_path, tmp_path, cfg)
    assert model.config.model.body_signals_see_shape
    _, body_np = model.decode(np.zeros((2, 3)))
    assert np.isfinite(body_np).all() and body_np.shape == (2, 500, 6)


def test_a_barely_excited_bin_is_not_blown_up_by_the_shape_normalisation():
    rng = np.random.default_rng(0)
    shape = rng.normal(0.0, 0.2, (50, 8, 8, 2))
    body, stats = rng.normal(size=(50, 500, 6)), rng.normal(size=(50, 4))
    even = np.array(Normalization.fit(shape, body, stats).shape_std)
    np.testing.assert_array_equal(even, shape.std(axis=(0, 1)))  # paper-like bins: as they are
    shape[:, :, 1] *= 1e-3  # a bin the data barely use (a structured gait's unused frequency)
    floored = np.array(Normalization.fit(shape, body, stats).shape_std)
    assert floored[1].min() == pytest.approx(0.05 * floored.max())
    np.testing.assert_array_equal(np.delete(floored, 1, axis=0), np.delete(shape.std(axis=(0, 1)), 1, axis=0))


def test_r2_per_channel():
    rng = np.random.default_rng(0)
    t = rng.standard_normal((10, 50, 2))
    np.testing.assert_allclose(r2_per_channel(t, t), 1.0)
    np.testing.assert_allclose(
        r2_per_channel(t, np.broadcast_to(t.mean(axis=(0, 1)), t.shape)), 0.0, atol=1e-12
    )


def test_statistics_head_is_invariant_to_a_time_shift_of_the_gait():
    """Shifting a gait by m body steps (0.2 s each) rotates every coefficient by 2 pi f_l 0.2 m; the
    circular signal CNN and its time pooling then see the same signals, so the statistics agree."""
    torch.manual_seed(0)
    net = fresh_net().eval()
    rng = np.random.default_rng(1)
    shape = 0.3 * rng.standard_normal((2, 8, 8, 2))
    c = shape[..., 0] + 1j * shape[..., 1]
    rot = np.exp(1j * 2 * np.pi * RECORD.freqs * 0.2 * 37)  # 37 steps later
    shifted = c * rot
    with torch.no_grad():
        a = net.predict_stats(torch.as_tensor(shape, dtype=torch.float32))
        b = net.predict_stats(
            torch.as_tensor(np.stack([shifted.real, shifted.imag], -1), dtype=torch.float32)
        )
    torch.testing.assert_close(a, b, atol=2e-5, rtol=1e-4)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_training_on_cuda_without_cuda_is_refused(tiny_dataset_path, tmp_path):
    with pytest.raises(RuntimeError, match="no CUDA device"):
        train(
            tiny_dataset_path, tmp_path, TrainConfig(epochs=1, device="cuda"), SMALL, log=None, progress=False
        )


def test_joint_latent_dropout_trains_the_designers_decoding_and_keeps_the_posteriors_for_the_mmd():
    torch.manual_seed(0)
    shape, body = torch.randn(6, 8, 8, 2), torch.randn(6, 500, 6)
    net = fresh_net(SMALL.model_copy(update={"joint_latent_dropout": 0.999}))  # all 6 dropped: p 0.994
    net.train()
    out = net(shape, body, sample=False)
    assert out.z_j.abs().sum() > 0  # the MMD still sees the posterior's z_k
    with torch.no_grad():  # decoded as generate() decodes: z_k = 0, no teacher forcing
        designer = net.run_joints(out.z_b, z_j=torch.zeros_like(out.z_j))["shape"]
        forced = net.run_joints(out.z_b, shape, sample_posterior=False)["shape"]
    torch.testing.assert_close(out.shape, designer)
    assert not torch.allclose(forced, designer)
    net.eval()  # outside training the posterior's z_k and the true shapes are decoded
    torch.testing.assert_close(net(shape, body, sample=False).shape, forced)


def test_encoder_that_sees_the_shape_reads_it_exactly_not_through_the_signals():
    torch.manual_seed(0)
    net = fresh_net(SMALL.model_copy(update={"encoder_sees_shape": True}))
    shape, body = torch.randn(3, 8, 8, 2), torch.randn(3, 500, 6)
    with torch.no_grad():
        mu, _ = net.encode_body(body, shape)
        moved = shape.clone()
        moved[:, 3, 5] += 1.0  # one coefficient of one joint
        assert (net.encode_body(body, moved)[0] - mu).abs().max() > 1e-4
        plain = fresh_net(SMALL)  # without the option the encoder reads the body alone
        assert torch.equal(plain.encode_body(body, shape)[0], plain.encode_body(body, moved)[0])
    with pytest.raises(ValueError, match="joint shape: pass it"):
        net.encode_body(body)


def test_shape_support_keeps_the_coefficients_the_records_excite():
    shapes = np.zeros((6, 8, 8, 2))
    shapes[:, 1::2, 4, 0] = 0.7  # the yaw joints at one frequency
    shapes[:3, 1::2, 0, 1] = 0.2  # steering in half the records
    shapes[:, 0::2, 4, 0] = 1e-3  # the pitch joints barely move: below 1% of the largest
    support = shape_support(shapes)
    assert support.shape == (8, 8) and support.sum() == 8
    assert support[1::2, 4].all() and support[1::2, 0].all() and not support[0::2].any()


def test_the_designers_shape_decode_skips_the_prior_and_gives_the_same_bits():
    torch.manual_seed(0)
    net = fresh_net(SMALL)
    z_b, z_j = torch.randn(5, SMALL.z_b_dim), torch.randn(5, SMALL.n_joints, SMALL.z_j_dim)
    with torch.no_grad():
        full = net.run_joints(z_b, z_j=z_j)
        torch.manual_seed(1)
        fast = net.generate_shape(z_b, z_j)
        after = torch.rand(1)
    assert torch.equal(fast, full["shape"]) and full["prior_sample"].shape == z_j.shape
    torch.manual_seed(1)
    assert torch.equal(after, torch.rand(1))  # the prior's draws, skipped: no random numbers taken
