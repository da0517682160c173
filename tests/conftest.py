"""Shared fixtures, made once per test session: a tiny dataset (4 records, ~2 s on 2 cores) and a
one-epoch checkpoint of the small test model trained on it (read-only for the tests that use it)."""

from __future__ import annotations

import pytest

from sim import GenerateConfig, generate_dataset, load_dataset

TINY = GenerateConfig(num_samples=4, seed=11)


@pytest.fixture(scope="session")
def tiny_dataset_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "tiny.npz"
    return generate_dataset(TINY, path, workers=2)


@pytest.fixture(scope="session")
def tiny_dataset(tiny_dataset_path):
    return load_dataset(tiny_dataset_path)


@pytest.fixture(scope="session")
def checkpoint(tiny_dataset_path, tmp_path_factory):
    from model import TrainConfig, train

    from .test_model import SMALL

    out = tmp_path_factory.mktemp("ckpt_tiny")
    train(tiny_dataset_path, out, TrainConfig(epochs=1, batch_size=2), SMALL, log=None, progress=False)
    return out
