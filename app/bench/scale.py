"""``snakeloco bench scale``: the Ray backend against the local one, and zarr against .npz, side by side.

1. Throughput: the same records (family, N, seed) generated on the local backend, then on a Ray
   instance started for the run (its start-up and shut-down included); ratio = local time / Ray time
   (records/s on Ray over records/s here). The two files are compared array by array.
2. Ray's start-up alone: ``ray.init`` on this machine until a first task has come back.
3. Memory: peak RSS of a process that writes a dataset of ``--memory-records`` records (the throughput
   run's records repeated: storage does not care what they are) through each writer, then loads it as
   training does (``shape``, ``body_ds``, the servo response over the training split) and trains one
   epoch of the small test-size model; its first-epoch losses are compared between the formats.
"""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from snakeloco.model import TrainConfig, train
from snakeloco.model.vae.config import TINY
from snakeloco.sim import GenerateConfig, load_dataset
from snakeloco.sim.data.generate import default_chunk_size, generate_dataset
from snakeloco.sim.data.writer import open_writer
from snakeloco.sim.physics.backend import BackendConfig, open_backend

KEYS = ("commands", "joint_angles", "body", "body_ds", "phases", "amplitude", "attempts", "shape")
MEMORY_MODEL = TINY
"""A small model for the memory run's one epoch: the figure measured is the data path's."""


def _ray_startup_s(workers: int) -> float:
    t0 = time.perf_counter()
    backend = open_backend(BackendConfig(backend="ray"), workers)
    try:
        list(backend.map(_noop, [0]))
        return time.perf_counter() - t0
    finally:
        backend.close()


def _noop(_simulator, job):
    return job


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def memory_run(source: str, out: str, records: int, train_dir: str) -> dict:
    """In a fresh process: write ``records`` records (``source``'s, repeated) to ``out`` through its
    writer, reopen it, train one epoch; peak RSS (MiB) after writing and after training, losses."""
    src = load_dataset(source)
    cfg = src.config.model_copy(update={"num_samples": records})
    arrays = {key: getattr(src, key) for key in KEYS}
    n = len(src)
    chunk = default_chunk_size(1, cfg)
    t0 = time.perf_counter()
    with open_writer(cfg, out, chunk, {"bench": "repeated records"}) as writer:
        for start in writer.starts():
            rows = np.arange(start, min(records, start + chunk)) % n
            writer.write(start, {"failures": []}, **{k: v[rows] for k, v in arrays.items()})
        del arrays, src
        writer.finish({"failures": []})
    write_s = time.perf_counter() - t0
    after_write = _peak_rss_mib()
    t0 = time.perf_counter()
    train(out, train_dir, TrainConfig(epochs=1, batch_size=64), MEMORY_MODEL, log=None, progress=False)
    first = json.loads((Path(train_dir) / "metrics.jsonl").read_text().splitlines()[0])
    return {
        "write_s": write_s,
        "train_s": time.perf_counter() - t0,
        "peak_rss_after_write_mib": after_write,
        "peak_rss_mib": _peak_rss_mib(),
        "first_epoch": {k: v for k, v in first.items() if "loss" in k},
    }


def _measure_memory(source: Path, out: Path, records: int) -> dict:
    code = (
        "import json, sys; from snakeloco.app.bench.scale import memory_run; "
        "print(json.dumps(memory_run(*sys.argv[1:3], int(sys.argv[3]), sys.argv[4])))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(source), str(out), str(records), str(out) + ".ckpt"],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"memory run for {out.name} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def bench_scale(
    records: int = 256,
    family: str = "paper",
    seed: int = 7,
    workers: int | None = None,
    memory_records: int = 4096,
    log=print,
) -> dict:
    """Run the three measurements in one go (see the module docstring); returns the figures."""
    from snakeloco.sim.physics.threads import resolve_workers

    workers = resolve_workers(workers)
    cfg = GenerateConfig(num_samples=records, seed=seed, family=family)
    work = Path(tempfile.mkdtemp(prefix="snakeloco-bench-scale-"))
    try:
        t0 = time.perf_counter()
        local = generate_dataset(cfg, work / "local.npz", workers=workers)
        local_s = time.perf_counter() - t0
        log(f"local: {records} {family} records in {local_s:.1f} s")
        t0 = time.perf_counter()
        remote = generate_dataset(
            cfg, work / "ray.zarr", workers=workers, backend=BackendConfig(backend="ray")
        )
        ray_s = time.perf_counter() - t0
        log(f"ray:   {records} {family} records in {ray_s:.1f} s (start-up and shut-down included)")
        a, b = load_dataset(local), load_dataset(remote)
        identical = (
            all(np.array_equal(getattr(a, k), getattr(b, k)) for k in (*KEYS, "freqs")) and a.meta == b.meta
        )
        startup_s = _ray_startup_s(workers)
        log(f"ray start-up alone: {startup_s:.1f} s")
        memory = {}
        if memory_records:
            for name in ("npz", "zarr"):
                memory[name] = _measure_memory(local, work / f"mem.{name}", memory_records)
                (work / f"mem.{name}").unlink() if name == "npz" else shutil.rmtree(work / f"mem.{name}")
                log(f"{name}: {memory_records} records, peak RSS {memory[name]['peak_rss_mib']:.0f} MiB")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result = {
        "records": records,
        "family": family,
        "workers": workers,
        "local_s": local_s,
        "ray_s": ray_s,
        "local_records_per_s": records / local_s,
        "ray_records_per_s": records / ray_s,
        "ratio": local_s / ray_s,
        "identical": bool(identical),
        "ray_startup_s": startup_s,
        "memory_records": memory_records,
        "memory": memory,
    }
    if memory:
        result["memory_ratio"] = memory["zarr"]["peak_rss_mib"] / memory["npz"]["peak_rss_mib"]
        result["same_first_epoch_loss"] = memory["zarr"]["first_epoch"] == memory["npz"]["first_epoch"]
    return result
