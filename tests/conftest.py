"""Shared fixtures, made once per test session: a tiny dataset (4 records, ~2 s on 2 cores) and a
two-epoch checkpoint of the small test model trained on it (read-only for the tests that use it)."""

from __future__ import annotations

import os

import pytest

from snakeloco.sim import GenerateConfig, load_dataset
from snakeloco.sim.data.generate import generate_dataset

from helpers import SMALL, quiet_server

TINY = GenerateConfig(num_samples=4, seed=11)


@pytest.fixture(scope="session", autouse=True)
def _work_outside_the_repo(tmp_path_factory):
    """MuJoCo writes MUJOCO_LOG.TXT into the working directory when a simulation warns (the tests of
    diverging gaits make it warn): the tests run from a scratch folder, so nothing lands in the repo."""
    here = os.getcwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    yield
    os.chdir(here)


@pytest.fixture(scope="session")
def tiny_dataset_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "tiny.npz"
    return generate_dataset(TINY, path, workers=2)


@pytest.fixture(scope="session")
def tiny_dataset(tiny_dataset_path):
    return load_dataset(tiny_dataset_path)


@pytest.fixture(scope="session")
def checkpoint(tiny_dataset_path, tmp_path_factory):
    """The one tiny checkpoint every test shares: SMALL trained for 2 epochs on the tiny dataset."""
    from snakeloco.model import TrainConfig, train

    out = tmp_path_factory.mktemp("ckpt_tiny")
    cfg = TrainConfig(epochs=2, batch_size=2, val_fraction=0.25)
    train(tiny_dataset_path, out, cfg, SMALL, log=None, progress=False)
    return out


@pytest.fixture(scope="session")
def member_checkpoint(tmp_path_factory):
    """A tiny structured-family checkpoint with what ``calibrate --sampler`` adds: the slider density,
    the family its decodes project onto and a member path head. Its records are the undulate preset's
    draws screened leniently (two replays each, any spread kept), so it builds in seconds."""
    from snakeloco.model import TrainConfig, train
    from snakeloco.model.heads.sampler import SamplerConfig, fit_sampler
    from snakeloco.model.replays import Fit
    from snakeloco.sim.gaits.structured import STRUCTURED_PRESETS

    family = STRUCTURED_PRESETS["undulate"].model_copy(
        update={"max_spread": 1e3, "coefficient_noise": 0.0, "members": 2}
    )
    cfg = GenerateConfig(num_samples=6, seed=5, family="structured", structured=family)
    data = generate_dataset(cfg, tmp_path_factory.mktemp("data") / "structured.npz", workers=2)
    trained = tmp_path_factory.mktemp("ckpt_structured_vae")
    train(
        data, trained, TrainConfig(epochs=2, batch_size=2, val_fraction=0.34), SMALL, log=None, progress=False
    )
    out = tmp_path_factory.mktemp("ckpt_structured")
    cfg = SamplerConfig(samples=4, epochs=3, hidden=16, head_sees_z_b=True)  # the shipped head: member alone
    fit_sampler(Fit(trained, data, out, workers=2, log=None), cfg)
    return out, data


@pytest.fixture
def server(checkpoint):
    """A designer on the tiny checkpoint on a free port (no variation or closed-loop replays), stopped
    after the test."""

    srv = quiet_server(checkpoint, ensemble=3)
    yield srv
    srv.stop()
