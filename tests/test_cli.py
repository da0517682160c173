"""The console script, called with explicit argument lists."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from sim import load_dataset


def test_generate_command(tmp_path, capsys, tiny_dataset):
    out = tmp_path / "g.npz"
    main(["generate", "--num-samples", "2", "--seed", "11", "--out", str(out), "--workers", "1"])
    assert "wrote" in capsys.readouterr().out
    np.testing.assert_array_equal(load_dataset(out).body, tiny_dataset.body[:2])


def test_bench_sim_json(capsys):
    main(["bench", "sim", "--json", "--samples", "2", "--repeats", "1"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads(last)
    for key in ("raw_steps_per_s", "generator_steps_per_s", "ratio", "replay_ratio"):
        assert result[key] > 0
    assert 0.3 < result["ratio"] < 3.0


def test_unknown_subcommand_exits_with_usage():
    with pytest.raises(SystemExit):
        main(["fly"])
