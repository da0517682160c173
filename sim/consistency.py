"""Predictability and consistency of body paths (DESIGN.md, "Predictability").

Random-phase multisine gaits can be chaotic: a 1e-3 relative perturbation of the commands can move
the 100 s final position by about the distance travelled. So every comparison of a predicted body
path with a simulated one is scored beside the physics' own spread, an ensemble of replays of the
same commands with ``rel_noise`` relative noise.

All statistics take body series (..., T, 6) in ``sim.BODY_CHANNELS`` order at ``sample_rate`` Hz;
compare series at the same rate (path length grows with the sampling rate).
"""

from __future__ import annotations

import numpy as np

ENSEMBLE_NOISE = 1e-3
"""Relative command noise of the ensemble members."""
ENSEMBLE_SIZE = 8
"""Replays per gait by default (the designer's fan, evaluation): the commands and 7 noisy copies."""


def perturbed_commands(
    commands: np.ndarray, k: int, rel_noise: float = ENSEMBLE_NOISE, seed: int = 0
) -> np.ndarray:
    """The commands (T, 8) and k-1 copies with relative noise u (1 + rel_noise eps): (k, T, 8)."""
    rng = np.random.default_rng(seed)
    eps = rng.standard_normal((k - 1, *commands.shape))
    return np.concatenate([commands[None], commands[None] * (1.0 + rel_noise * eps)], axis=0)


def path_stats(body: np.ndarray, sample_rate: float) -> dict[str, np.ndarray]:
    """Predictable statistics of body series (..., T, 6).

    path_length (m): length of the horizontal (forward, sideways) polyline; median_speed (m/s);
    vertical_std (m): standard deviation of the vertical channel; net_roll (rad): unwrapped roll
    change; final_xy (m): (forward, sideways) at the end; displacement (m): |final_xy - start|.
    """
    xy = body[..., [1, 2]]  # (..., T, 2)
    step = np.linalg.norm(np.diff(xy, axis=-2), axis=-1)  # (..., T-1)
    final = xy[..., -1, :] - xy[..., 0, :]
    return {
        "path_length": step.sum(axis=-1),
        "median_speed": np.median(step, axis=-1) * sample_rate,
        "vertical_std": body[..., 0].std(axis=-1),
        "net_roll": body[..., -1, 3] - body[..., 0, 3],
        "final_xy": final,
        "displacement": np.linalg.norm(final, axis=-1),
    }


PREDICTABLE = ("path_length", "median_speed", "vertical_std", "net_roll")


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-9)


def ensemble_spread(ensemble: np.ndarray, sample_rate: float) -> dict[str, float]:
    """The physics' own spread over an ensemble (K, T, 6) whose member 0 is the unperturbed replay.

    final_spread: RMS distance of the perturbed members' final positions from member 0's, relative
    to member 0's displacement (the "predictability score": ~1 means the final position is
    unpredictable). For each predictable statistic: the ensemble's std in the statistic's units
    (``<stat>_std``), its relative std (std / |mean|) (``<stat>_spread``) and the physics' floor
    on a prediction's error (``<stat>_floor``): the relative error of the perturbed members' mean
    against member 0, i.e. what a model that knew the ensemble's mean exactly would score (from
    K - 1 members, so slightly above the true floor).
    """
    s = path_stats(ensemble, sample_rate)
    d = np.linalg.norm(s["final_xy"][1:] - s["final_xy"][0], axis=-1)
    out = {"final_spread": float(np.sqrt((d**2).mean()) / max(float(s["displacement"][0]), 1e-9))}
    for key in PREDICTABLE:
        v = s[key]
        out[f"{key}_std"] = float(v.std())
        out[f"{key}_spread"] = float(v.std() / max(abs(float(v.mean())), 1e-9))
        # The best a predictor of this gait's statistics can do: the perturbed members' mean,
        # scored against member 0 exactly as a decoded prediction is (``compare``'s ``_err``).
        out[f"{key}_floor"] = float(_rel(v[1:].mean(), v[0])) if len(v) > 1 else float("nan")
    return out


def xy_r2(pred: np.ndarray, target: np.ndarray) -> float:
    """R^2 of a predicted horizontal path against a simulated one, both (T, 6), pooled over x and y."""
    p, t = pred[:, [1, 2]], target[:, [1, 2]]
    sst = ((t - t.mean(axis=0)) ** 2).sum()
    return float(1.0 - ((p - t) ** 2).sum() / max(sst, 1e-12))


def compare(
    decoded: np.ndarray,
    ensemble: np.ndarray,
    sample_rate: float,
    decoded_stats: dict[str, float] | None = None,
) -> dict[str, float]:
    """Score a decoded body path (T, 6) against an ensemble of simulated ones (K, T, 6), same rate.

    ``decoded_stats``: the model's own prediction of the predictable statistics (PREDICTABLE names);
    where given it is scored instead of the statistic measured on the decoded path (a smooth
    mean path under-states path length, speed and vertical oscillation of a chaotic gait).

    Returns the ensemble spread (``ensemble_spread``), the decoded-vs-simulated relative error of each
    predictable statistic against the unperturbed replay (``<stat>_err``), ``xy_r2``, and whether
    the decoded final position lies inside the ensemble's spread (``final_inside``: within twice
    the RMS distance of the ensemble's final positions from their mean, or 5 cm, whichever is
    larger), with that distance in units of the spread (``final_z``).
    """
    dec = path_stats(decoded, sample_rate)
    dec.update({k: np.asarray(v, np.float64) for k, v in (decoded_stats or {}).items() if k in PREDICTABLE})
    ens = path_stats(ensemble, sample_rate)
    out = ensemble_spread(ensemble, sample_rate)
    for key in PREDICTABLE:
        out[f"{key}_err"] = float(_rel(dec[key], ens[key][0]))
        out[f"{key}_decoded"] = float(dec[key])
        out[f"{key}_simulated"] = float(ens[key][0])
    centre = ens["final_xy"].mean(axis=0)
    rms = float(np.sqrt((np.linalg.norm(ens["final_xy"] - centre, axis=-1) ** 2).mean()))
    radius = max(2.0 * rms, 0.05)
    dist = float(np.linalg.norm(dec["final_xy"] - centre))
    out["final_inside"] = float(dist <= radius)
    out["final_z"] = dist / max(rms, 1e-9)
    out["final_error_m"] = float(np.linalg.norm(dec["final_xy"] - ens["final_xy"][0]))
    out["xy_r2"] = xy_r2(decoded, ensemble[0])
    return out
