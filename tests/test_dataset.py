"""Dataset files: generation (deterministic, regenerating broken samples, atomic) and the validated loader."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

import snakeloco.sim as sim
from snakeloco.sim import (
    CommandRule,
    DatasetError,
    ExcitationConfig,
    GenerateConfig,
    joint_shape,
    load_dataset,
)
from snakeloco.sim.data.generate import generate_dataset
from snakeloco.sim.physics.simulator import Simulator

EXC = ExcitationConfig()


def test_dataset_contents(tiny_dataset):
    ds = tiny_dataset
    n = len(ds)
    assert ds.commands.shape == (n, 2000, 8) and ds.commands.dtype == np.float32
    assert ds.joint_angles.shape == (n, 2000, 8)
    assert ds.body.shape == (n, 2000, 6) and ds.body_ds.shape == (n, 500, 6)
    np.testing.assert_array_equal(ds.body_ds, ds.body[:, ::4])
    np.testing.assert_allclose(ds.freqs, EXC.freqs)
    assert ds.phases.shape == (n, 8, 8) and ds.shape.shape == (n, 8, 8, 2)
    np.testing.assert_allclose(ds.shape, joint_shape(ds.joint_angles), atol=1e-6)
    for key in ("commands", "joint_angles", "body", "shape"):
        assert np.isfinite(getattr(ds, key)).all()
    assert ds.meta["schema_version"] == sim.SCHEMA_VERSION
    assert ds.meta["mjcf_sha256"] == sim.mjcf_sha256()
    assert ds.meta["config"]["num_samples"] == n
    assert (ds.attempts >= 1).all()


def test_generation_is_deterministic_and_independent_of_workers(tmp_path, tiny_dataset):
    cfg = GenerateConfig(num_samples=2, seed=11)
    a = load_dataset(generate_dataset(cfg, tmp_path / "a.npz", workers=1))
    for key in ("commands", "joint_angles", "body", "shape", "phases"):
        np.testing.assert_array_equal(getattr(a, key), getattr(tiny_dataset, key)[:2])
    assert a.meta["config"]["seed"] == 11
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]  # no screening log: nothing was screened
    b = load_dataset(generate_dataset(GenerateConfig(num_samples=2, seed=12), tmp_path / "b.npz", workers=2))
    assert not np.array_equal(a.commands, b.commands)


def test_broken_samples_are_regenerated_and_logged(tmp_path):
    # A CoM ceiling of 0.27 m is below the peak of about half of all healthy gaits: those get new phases.
    cfg = GenerateConfig(num_samples=4, seed=3, sim=CommandRule(max_com_height=0.27), max_attempts=8)
    ds = load_dataset(generate_dataset(cfg, tmp_path / "r.npz", workers=2))
    failures = ds.meta["failures"]
    assert failures and all("thrown" in f["reason"] for f in failures)
    assert ds.attempts.max() > 1
    assert sum(ds.attempts - 1) == len(failures)
    assert np.isfinite(ds.body).all()
    # The regenerated sample replays as stored with the same limits.
    i = int(np.argmax(ds.attempts))
    again = Simulator(workers=1, config=cfg.sim).replay(ds.commands[i])
    np.testing.assert_array_equal(again.body.astype(np.float32), ds.body[i])


def test_unrecoverable_generation_fails_clearly_and_writes_nothing(tmp_path):
    cfg = GenerateConfig(num_samples=2, seed=0, sim=CommandRule(max_com_height=0.03), max_attempts=2)
    out = tmp_path / "never.npz"
    with pytest.raises(RuntimeError, match="all 2 phase draws"):
        generate_dataset(cfg, out, workers=2)
    assert list(tmp_path.iterdir()) == []


def test_interrupted_generation_keeps_the_old_file_and_resumes(tmp_path, tiny_dataset):
    out = tmp_path / "d.npz"
    out.write_bytes(b"previous contents")
    cfg = GenerateConfig(num_samples=4, seed=11)  # the tiny dataset's

    def interrupt(_n: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_dataset(cfg, out, workers=2, chunk_size=2, progress=interrupt)
    assert out.read_bytes() == b"previous contents"  # nothing half-written at the destination
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz", "d.npz.partial"]  # its first chunk
    seen = []
    generate_dataset(cfg, out, workers=2, chunk_size=4, progress=seen.append)  # a resumed run keeps 2
    assert seen == [2, 2]  # the finished chunk, then the one it still had to simulate
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz"]
    resumed = load_dataset(out)
    for key in ("commands", "joint_angles", "body", "shape", "attempts"):
        np.testing.assert_array_equal(getattr(resumed, key), getattr(tiny_dataset, key), err_msg=key)
    assert resumed.meta == tiny_dataset.meta
    # A partial run of another config is never mixed in: it is named, and kept.
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(cfg, tmp_path / "e.npz", workers=2, chunk_size=2, progress=interrupt)
    with pytest.raises(DatasetError, match=r"e.npz.partial/progress.json is a run of another config"):
        generate_dataset(GenerateConfig(num_samples=4, seed=12), tmp_path / "e.npz", workers=2)


# --- loader refusals -------------------------------------------------------------------------------


def test_loader_refuses_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset"):
        load_dataset(tmp_path / "nope.npz")


def test_loader_refuses_truncated_file(tmp_path, tiny_dataset_path):
    data = tiny_dataset_path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="truncated"):
        load_dataset(cut)


def test_loader_refuses_foreign_files(tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("time_s,joint_1\n0,0\n")
    with pytest.raises(DatasetError, match=r"not a complete \.npz"):
        load_dataset(text)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(DatasetError, match="not a snakeloco dataset"):
        load_dataset(other)


def _rewrite(src, dst, **replace):
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.namelist():
            key = item[:-4]
            if key in replace:
                if replace[key] is not None:
                    import io

                    buf = io.BytesIO()
                    np.save(buf, replace[key])
                    zout.writestr(item, buf.getvalue())
            else:
                zout.writestr(item, zin.read(item))


def test_loader_refuses_wrong_schema_and_wrong_arrays(tmp_path, tiny_dataset_path, tiny_dataset):
    meta = dict(tiny_dataset.meta, schema_version=99)
    _rewrite(tiny_dataset_path, tmp_path / "v99.npz", meta=np.array(json.dumps(meta)))
    with pytest.raises(DatasetError, match="schema version 99"):
        load_dataset(tmp_path / "v99.npz")
    _rewrite(tiny_dataset_path, tmp_path / "nokey.npz", body_ds=None)
    with pytest.raises(DatasetError, match=r"missing arrays \['body_ds'\]"):
        load_dataset(tmp_path / "nokey.npz")
    _rewrite(tiny_dataset_path, tmp_path / "shape.npz", shape=np.zeros((4, 8, 7, 2), np.float32))
    with pytest.raises(DatasetError, match="'shape' is float32"):
        load_dataset(tmp_path / "shape.npz")
    _rewrite(tiny_dataset_path, tmp_path / "meta.npz", meta=np.array("{not json"))
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_dataset(tmp_path / "meta.npz")


def test_loader_never_unpickles(tmp_path, tiny_dataset_path):
    """A dataset whose meta is a pickled object array is refused, not unpickled."""
    evil = tmp_path / "evil.npz"
    _rewrite(tiny_dataset_path, evil, meta=np.array([{"schema_version": 1}], dtype=object))
    with pytest.raises(DatasetError, match="unreadable dataset"):
        load_dataset(evil)
