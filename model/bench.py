"""``snakeloco bench model``: decode latency of the slider path and batch throughput.

For a checkpoint that decodes family members (``GaitModel.projects``) the network's own decode
(``decode_raw``: what the slider path cost before projection and path prediction) is timed in the
same run, interleaved call by call, so the two p50s are measured side by side."""

from __future__ import annotations

import time

import numpy as np

from snakeloco.model.api import load_pretrained


def bench_model(checkpoint=None, calls: int = 200, batch: int = 256) -> dict:
    """Decode latency for one z_B (p50/p95 over ``calls`` calls, after warm-up) and batch decodes per second."""
    model = load_pretrained(checkpoint)
    rng = np.random.default_rng(0)
    z = rng.standard_normal((calls, model.z_b_dim))
    for w in rng.standard_normal((10, model.z_b_dim)):  # warm-up draws of their own: --calls may be < 10
        model.decode(w[None])
    times, raw = [], []
    for i in range(calls):
        t0 = time.perf_counter()
        model.decode(z[i : i + 1])
        times.append(time.perf_counter() - t0)
        if model.projects:
            t0 = time.perf_counter()
            model.decode_raw(z[i : i + 1])
            raw.append(time.perf_counter() - t0)
    zb = rng.standard_normal((batch, model.z_b_dim))
    model.decode(zb)
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        model.decode(zb)
    per_s = reps * batch / (time.perf_counter() - t0)
    ms = 1e3 * np.asarray(times)
    out = {
        "decode_p50_ms": float(np.percentile(ms, 50)),
        "decode_p95_ms": float(np.percentile(ms, 95)),
        "batch": batch,
        "batch_decodes_per_s": per_s,
    }
    if raw:
        raw_ms = 1e3 * np.asarray(raw)
        out["decode_raw_p50_ms"] = float(np.percentile(raw_ms, 50))
        out["decode_raw_p95_ms"] = float(np.percentile(raw_ms, 95))
        out["projection_cost_ratio"] = out["decode_p50_ms"] / out["decode_raw_p50_ms"]
    return out
