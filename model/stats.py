"""The body statistics the model predicts (``HierarchicalVAE.predict_stats``), in one place.

A vector per record: log path length (m), log median speed (m/s), log vertical-oscillation std (m)
and net roll (rad), all as ``sim.consistency.path_stats`` defines them on the 5 Hz body series.
Logs make the three positive statistics' errors relative, which is how they are judged.
"""

from __future__ import annotations

import numpy as np

from sim import BODY_DOWNSAMPLE
from sim.consistency import path_stats

STAT_NAMES = ("path_length", "median_speed", "vertical_std", "net_roll")
MODEL_RATE = 20.0 / BODY_DOWNSAMPLE
"""Sample rate of the model's body series (Hz): the 20 Hz record, every ``BODY_DOWNSAMPLE``-th sample."""
_FLOOR = 1e-6


def stats_vector(body_ds: np.ndarray, rate: float = MODEL_RATE) -> np.ndarray:
    """Body series (..., T, 6) -> (..., 4) statistics vector (logs of the positive ones)."""
    s = path_stats(np.asarray(body_ds, np.float64), rate)
    return np.stack(
        [
            np.log(np.maximum(s["path_length"], _FLOOR)),
            np.log(np.maximum(s["median_speed"], _FLOOR)),
            np.log(np.maximum(s["vertical_std"], _FLOOR)),
            s["net_roll"],
        ],
        axis=-1,
    )


def stats_dict(vector: np.ndarray) -> dict[str, np.ndarray]:
    """(..., 4) statistics vector -> {name: (...)} in physical units."""
    v = np.asarray(vector, np.float64)
    return {
        "path_length": np.exp(v[..., 0]),
        "median_speed": np.exp(v[..., 1]),
        "vertical_std": np.exp(v[..., 2]),
        "net_roll": v[..., 3],
    }


def median_relative_errors(predicted: dict, true: dict) -> dict[str, float]:
    """Median over records of |predicted - true| / |true| for each of ``STAT_NAMES`` (physical units)."""
    return {
        k: float(np.median(np.abs(predicted[k] - true[k]) / np.maximum(np.abs(true[k]), 1e-9)))
        for k in STAT_NAMES
    }
