"""``snakeloco bench model``: decode latency of the slider path and batch throughput."""

from __future__ import annotations

import time

import numpy as np

from snakeloco.model.api import load_pretrained


def bench_model(checkpoint=None, n: int = 200, batch: int = 256) -> dict:
    """Decode latency for one z_B (p50/p95 over n calls, after warm-up) and batch decodes per second."""
    model = load_pretrained(checkpoint)
    rng = np.random.default_rng(0)
    z = rng.standard_normal((n, model.z_b_dim))
    for w in rng.standard_normal((10, model.z_b_dim)):  # warm-up draws of their own: --calls may be < 10
        model.decode(w[None])
    times = []
    for i in range(n):
        t0 = time.perf_counter()
        model.decode(z[i : i + 1])
        times.append(time.perf_counter() - t0)
    zb = rng.standard_normal((batch, model.z_b_dim))
    model.decode(zb)
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        model.decode(zb)
    per_s = reps * batch / (time.perf_counter() - t0)
    ms = 1e3 * np.asarray(times)
    return {
        "decode_p50_ms": float(np.percentile(ms, 50)),
        "decode_p95_ms": float(np.percentile(ms, 95)),
        "batch": batch,
        "batch_decodes_per_s": per_s,
    }
