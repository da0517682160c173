"""Predictability and consistency of body paths (docs/evaluation.md: the consistency promise against the physics' own spread).

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
    """The commands (T, n_joints) and k-1 copies with relative noise u (1 + rel_noise eps): (k, T, n_joints)."""
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
    larger), with that distance in units of the spread (``final_z``), the decoded final position's
    distance from the replay's (``final_error_m``; over the replay's displacement:
    ``final_error_rel``), the decoded net yaw's relative error (``net_yaw_error_rel``: the figure of
    a gait that turns in place) and where the replay went (``where_it_went``).
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
    travelled = float(ens["displacement"][0])
    out["final_error_rel"] = out["final_error_m"] / max(travelled, 1e-9)
    out["xy_r2"] = xy_r2(decoded, ensemble[0])
    # Turning in place travels little: its figure is the net yaw (rad, unwrapped), not the end.
    yaw_decoded, yaw_simulated = decoded[-1, 5] - decoded[0, 5], ensemble[0, -1, 5] - ensemble[0, 0, 5]
    out["net_yaw_error_rel"] = float(_rel(yaw_decoded, yaw_simulated))
    out.update(where_it_went(ensemble[0], sample_rate))
    return out


ROLLING = 2 * np.pi
"""|net roll| (rad) from which a gait counts as rolling: at least one full turn about its axis."""


def where_it_went(body: np.ndarray, sample_rate: float) -> dict[str, float]:
    """Where one simulated body series (T, 6) went: ``displacement_m``, ``speed_bl_s`` (displacement
    over the record's duration, in body lengths per second), ``direction_deg`` (the direction of travel: the displacement's
    direction in the start frame: 0 forward, +90 left), ``net_roll`` (rad) and ``rolls`` (1.0 when
    |net roll| >= ``ROLLING``)."""
    from snakeloco.sim.robot.description import BODY_LENGTH

    s = path_stats(body, sample_rate)
    fx, fy = (float(v) for v in s["final_xy"])
    duration = (body.shape[-2] - 1) / sample_rate
    roll = float(s["net_roll"])
    return {
        "displacement_m": float(s["displacement"]),
        "speed_bl_s": float(s["displacement"]) / duration / BODY_LENGTH,
        "direction_deg": float(np.degrees(np.arctan2(fy, fx))),
        "net_roll": roll,
        "rolls": float(abs(roll) >= ROLLING),
    }


def diversity(rows: list[dict[str, float]]) -> dict:
    """Where a set of gaits went (rows of ``where_it_went``): final headings by quadrant (centred on
    forward, left, backward, right) and in 30-degree bins, speed quantiles in body lengths per
    second, the share at least 0.15 body lengths/s, the shares travelling at least 2 and 5 m and
    the share rolling."""
    if not rows:
        return {}
    heading = np.array([r["direction_deg"] for r in rows])
    speed = np.array([r["speed_bl_s"] for r in rows])
    quadrant = (((heading + 45.0) % 360.0) // 90.0).astype(int)  # 0 forward, 1 left, 2 back, 3 right
    names = ("forward", "left", "backward", "right")
    return {
        "heading_quadrants": {n: int((quadrant == i).sum()) for i, n in enumerate(names)},
        "heading_hist_30deg": np.histogram(heading, bins=np.arange(-180, 181, 30))[0].tolist(),
        "speed_bl_s_quantiles": dict(
            zip(("p10", "p50", "p90", "max"), np.quantile(speed, [0.1, 0.5, 0.9, 1.0]).tolist(), strict=True)
        ),
        "share_speed_ge_0.15_bl_s": float((speed >= 0.15).mean()),
        "share_travel_ge_2m": float(np.mean([r["displacement_m"] >= 2.0 for r in rows])),
        "share_travel_ge_5m": float(np.mean([r["displacement_m"] >= 5.0 for r in rows])),
        "share_rolling": float(np.mean([r["rolls"] for r in rows])),
    }
