"""The Consistency panel's text: what the model predicted beside what physics did, and the spread
physics itself allows (markdown for viser's ``add_markdown``)."""

from __future__ import annotations

import math

import numpy as np

from snakeloco.app.designer.session import DecodedGait, SimulatedGait
from snakeloco.sim.scores.consistency import PREDICTABLE

STAT_ROWS: dict[str, tuple[str, float]] = dict(
    zip(
        PREDICTABLE,
        (
            ("path length (m)", 1.0),
            ("speed (m/s)", 1.0),
            ("vertical osc. (mm)", 1000.0),
            ("net roll (rad)", 1.0),
        ),
        strict=True,
    )
)
"""Each predictable statistic's row label and the factor from its SI unit to the label's unit."""

SAMPLED_FAILURE_HINT = (
    "\n\nAbout 1 in 30 sampled-z_k gaits throws the simulated snake or breaks the simulation: "
    "**Resample z_k** or lower the temperature."
)
"""Measured on the shipped model (implicit integrator): 3.3% of 512 sampled gaits at T = 1 broke,
2.1% at T = 0.5, none with z_k = 0 (calibration replays)."""


def spread_text(std: float, relative: float) -> str:
    """An ensemble's spread of one statistic: its std in the statistic's units and, where the
    ensemble's mean is a meaningful scale (larger than the spread), relative to it. A net roll that
    goes either way across the ensemble has a mean near 0: its relative spread (e.g. ±15 rad about a
    mean of 1.9, 789%) says nothing the std does not."""
    text = f"±{std:.2g}"
    return text + (f" ({100 * relative:.1f}%)" if relative < 1.0 else "")


RELATIVE_FLOOR: dict[str, float] = dict(zip(PREDICTABLE, (0.5, 0.005, 0.001, math.pi), strict=True))
"""Smallest simulated value (SI units) of each statistic that is a base for a percentage: a path of
0.5 m, 5 mm/s, 1 mm of vertical oscillation, half a turn of roll. Below it the error is said in the
statistic's units: a net roll error of 618% where the gait does not roll (0.03 rad against 0.2) says
nothing a person can use."""
R2_MIN_DISTANCE_M = 0.5
"""Shortest simulated path (start to end, m) whose xy-path R² is shown: the R² of a path that barely
moves divides by a variance of millimetres (R² -1.42 beside "inside the ensemble spread")."""


def error_text(key: str, f: dict, unit: float) -> str:
    """A statistic's model error: relative where the simulated value is a base for it
    (``RELATIVE_FLOOR``), else absolute in the row's units."""
    if abs(f[key + "_simulated"]) >= RELATIVE_FLOOR[key]:
        return f"{100 * f[key + '_err']:.0f}%"
    return f"{unit * abs(f[key + '_decoded'] - f[key + '_simulated']):.2g}"


def r2_text(f: dict) -> str:
    """The xy-path R², or why it is not shown (a path too short for it)."""
    travelled = f.get("displacement_m", np.inf)
    if travelled < R2_MIN_DISTANCE_M:
        return f"xy-path R²: not shown (the replay moved {travelled:.2f} m: too little for a fit to mean anything)"
    return f"xy-path R²: {f['xy_r2']:.2f}"


OFF_DATA = (
    "⚠ **Off the data**: this z_B is less likely under the training records' density than 99% of "
    "them; its gait and path are the model's extrapolation."
)


def gait_text(gait: DecodedGait) -> str:
    """What the gait is: the family member replayed (kind and parameters in words, the projection's
    residual) and the off-the-data flag; empty for a gait with neither."""
    lines = []
    if gait.member is not None:
        lines.append(f"**Gait**: {gait.member.describe()}")
        if (
            gait.residual is not None
        ):  # the member is what is replayed: the residual is the decode's, not an error
            lines.append(
                f"The model decoded a joint shape {100 * gait.residual:.0f}% (relative distance) from this "
                "member; the member itself is replayed, drawn and exported."
            )
    if gait.off_data:
        lines.append(OFF_DATA)
    return "\n\n".join(lines)


def _with_gait(gait: DecodedGait, text: str) -> str:
    head = gait_text(gait)
    return f"{head}\n\n{text}" if head else text


def decoded_text(gait: DecodedGait) -> str:
    """The panel while a decoded gait waits for its replay."""
    source = "model decode" if gait.source == "model" else gait.source
    return _with_gait(gait, f"Decoded in {gait.decode_ms:.1f} ms ({source}); simulating...")


def failed_text(gait: DecodedGait, reason: str) -> str:
    """The panel when physics could not replay a decoded gait."""
    sampled = gait.latents is not None and gait.latents.zk_mode == "sampled"
    return _with_gait(
        gait,
        f"**Replay failed**: {reason}\n\nThe decoded gait is shown; physics could not replay it."
        + (SAMPLED_FAILURE_HINT if sampled else ""),
    )


def simulated_text(gait: DecodedGait, sim: SimulatedGait, ensemble: bool) -> str:
    """The panel after the replay (``ensemble`` False: its ensemble is still running) or the ensemble."""
    origin = f"decode {gait.decode_ms:.1f} ms" if gait.source == "model" else gait.source
    timing = f"{origin} · replay {sim.replay_ms:.0f} ms" + (
        f" · ensemble of {len(sim.ensemble_body)} {sim.ensemble_ms:.0f} ms"
        if ensemble
        else " · ensemble running..."
    )
    lines = [timing]
    f = sim.figures
    if ensemble and f:
        lines.append(
            "**Predictability** (ensemble final-position spread / distance travelled): "
            f"**{f['final_spread']:.2f}**"
        )
        if gait.body_ds is not None:
            table = ["| | model | simulated | error | physics spread (± std) |", "|---|---|---|---|---|"]
            for key, (label, unit) in STAT_ROWS.items():
                table.append(
                    f"| {label} | {unit * f[key + '_decoded']:.3g} | {unit * f[key + '_simulated']:.3g} | "
                    f"{error_text(key, f, unit)} | {spread_text(unit * f[key + '_std'], f[key + '_spread'])} |"
                )
            inside = "**inside**" if f["final_inside"] else "**outside**"
            lines += [
                "\n".join(table),
                f"{r2_text(f)} · decoded final position {inside} the ensemble spread ({f['final_z']:.1f}× RMS)",
            ]
        if f.get("ensemble_broken"):
            lines.append(f"{int(f['ensemble_broken'])} ensemble member(s) broke and were left out.")
    # Paragraphs apart: a line right after a markdown table would be drawn as one more table row.
    return _with_gait(gait, "\n\n".join(lines))
