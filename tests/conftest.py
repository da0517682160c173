"""Shared fixtures: a tiny dataset generated once per test session (4 records, ~2 s on 2 cores)."""

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
