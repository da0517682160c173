"""The body statistics the model predicts (``HierarchicalVAE.predict_stats``), in one place.

A vector per record: log path length (m), log median speed (m/s), log vertical-oscillation std (m)
and net roll (rad), all as ``sim.scores.consistency.path_stats`` defines them on the 5 Hz body series.
Logs make the three positive statistics' errors relative, which is how they are judged.
"""

from __future__ import annotations

import numpy as np

from snakeloco.sim import BODY_RATE
from snakeloco.sim.scores.consistency import PREDICTABLE, path_stats

STAT_NAMES = PREDICTABLE
"""The statistics' names, in the vector's order (``sim.scores.consistency.PREDICTABLE``)."""
_FLOOR = 1e-6


LOGGED = dict(zip(STAT_NAMES, (True, True, True, False), strict=True))
"""Which statistics the vector holds as logs: the positive ones, whose errors are judged relative."""


def stats_vector(body_ds: np.ndarray, rate: float = BODY_RATE) -> np.ndarray:
    """Body series (..., T, 6) -> (..., 4) statistics vector (logs of the positive ones)."""
    s = path_stats(np.asarray(body_ds, np.float64), rate)
    return np.stack([np.log(np.maximum(s[k], _FLOOR)) if LOGGED[k] else s[k] for k in STAT_NAMES], axis=-1)


def stats_dict(vector: np.ndarray) -> dict[str, np.ndarray]:
    """(..., 4) statistics vector -> {name: (...)} in physical units."""
    v = np.asarray(vector, np.float64)
    return {k: np.exp(v[..., i]) if LOGGED[k] else v[..., i] for i, k in enumerate(STAT_NAMES)}


def median_relative_errors(predicted: dict, true: dict) -> dict[str, float]:
    """Median over records of |predicted - true| / |true| for each of ``STAT_NAMES`` (physical units)."""
    return {
        k: float(np.median(np.abs(predicted[k] - true[k]) / np.maximum(np.abs(true[k]), 1e-9)))
        for k in STAT_NAMES
    }
