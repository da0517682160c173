"""The structured gait family: randomised travelling-wave gaits on the excited bins, each kept only if
physics can predict it.

A record's gait is a gait-equation wave (``sim.gaits.library``) of one of four kinds, drawn with the ranges
of ``StructuredConfig`` (the same kinds and ranges as the search that tuned the library,
docs/gaits.md): lateral undulation (yaw wave only), sidewinding (one spatial frequency, pitch and yaw
waves out of phase), lateral rolling (equal amplitudes a quarter period apart) and turning (different
pitch and yaw waves). With probability ``second_wave`` a weaker wave of another kind on another
excited bin is added, and with probability ``steering`` a slow steering wave on the yaw joints at
the lowest excited frequency (0.05 Hz: the heading swings left and right over 20 s periods). Joint
commands are the sum, scaled to the 2.2 rad command limit where they exceed it.

Everything is a joint shape on the record's excited bins (``sim.gaits.spectra``), so records share the
paper family's file schema and joint-shape convention. Draws are deterministic in (seed, record,
attempt), like the paper family's phases.
"""

from __future__ import annotations

import numpy as np

from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.gaits.library import PRESETS, GaitEquation, layout
from snakeloco.sim.gaits.spectra import shape_to_commands
from snakeloco.sim.gaits.structured_config import AMPLITUDE_RANGES as AMPLITUDE_RANGES  # re-exported
from snakeloco.sim.gaits.structured_config import KINDS as KINDS
from snakeloco.sim.gaits.structured_config import NU_RANGES as NU_RANGES
from snakeloco.sim.gaits.structured_config import StructuredConfig as StructuredConfig
from snakeloco.sim.robot.description import Robot

LIBRARY = StructuredConfig(
    kind_weights=(1.0, 2.0, 0.5, 0.5),
    frequencies={
        "undulate": (0.52, 0.93),
        "sidewind": (0.52,),
        "roll": (0.29, 0.52),
        "turn": (0.29, 0.52),
    },
    second_wave=0.0,
    steering=0.0,
    amplitude_scale=(0.3, 1.0),
    library=True,
    library_offsets={"sidewind": (0.2, 1.1)},
    max_draws=80,
    early_seconds=20.0,
    early_max_spread=0.3,
    sure_spread=0.07,
)
"""The library family (``STRUCTURED_PRESETS["library"]``), which ``compass`` widens."""


STRUCTURED_PRESETS: dict[str, StructuredConfig] = {
    "every": StructuredConfig(
        kind_weights=(1.0, 1.5, 1.0, 1.0),
        frequencies={
            "undulate": (0.29, 0.52, 0.93),
            "sidewind": (0.52,),
            "roll": (0.29, 0.52),
            "turn": (0.29, 0.52),
        },
        second_wave=0.0,
        amplitude_scale=(0.35, 1.0),
        max_draws=80,
        early_seconds=20.0,
        early_max_spread=0.3,
        sure_spread=0.07,
    ),
    "library": LIBRARY,
    "compass": LIBRARY.model_copy(
        update={
            "kind_weights": (1.5, 2.0, 0.5, 0.5),
            "frequencies": LIBRARY.frequencies | {"undulate": (0.29, 0.52, 0.93)},
        }
    ),
    "arcs": LIBRARY.model_copy(
        update={
            "kind_weights": (2.5, 2.0, 0.5, 0.5),
            "frequencies": LIBRARY.frequencies | {"undulate": (0.29, 0.52, 0.93)},
            "curve": 0.6,
        }
    ),
    "mixed": StructuredConfig(),
    "undulate": StructuredConfig(
        kind_weights=(1.0, 0.0, 0.0, 0.0),
        frequencies={"undulate": (0.52,), "sidewind": (0.52,), "roll": (0.52,), "turn": (0.52,)},
        second_wave=0.0,
        steering=0.5,
        coefficient_noise=0.1,
        max_draws=80,
        undulate_amplitude=(0.5, 0.9),
        undulate_wavenumber=(0.4, 1.0),
    ),
}
"""Named structured families (``snakeloco generate --family structured --structured-preset NAME``).
arcs (the default, ``DEFAULT_PRESET``): the compass family with undulation drawn 2.5 times as often,
60% of the undulations at 0.52 and 0.93 Hz curving (``curve_wave``): arcs to the diagonals, where the
compass family ends no gait 12-15 m away; docs/gaits.md. compass: the library family below with
undulation at 0.29 Hz as well (short paths straight ahead and behind: 2.4-11 m where 0.52 Hz starts
at 3.5 m), undulation drawn 1.5 times as often (the structured checkpoint shipped before arcs). every: one wave of every kind, at 0.29-0.93 Hz (sidewinding at 0.52 Hz only: 11 of 28
draws at 0.93 Hz passed the screen, 23 of 33 at 0.52 Hz) and 0.35-1 of its amplitude range (slow
to fast, forward, backward, sideways, rolling, turning), with steering in 30% of the draws, screened
against command noise by the cheap screen (a pause at 20 s, a 2-replay verdict where it is clear;
docs/gaits.md; its model could not learn where its gaits end: docs/every-model.md). library: the
gait library's four gaits at 0.3-1 of their amplitudes, mirrored or
not, undulation either way, sidewinding's offset swept over 0.2-1.1 rad (its direction of travel
over -15 to 150 deg), no steering (it spins sidewinding and rolling in place), screened alike. mixed: every kind with second waves, screened in full (the first structured
dataset's). undulate:
lateral undulation at 0.52 Hz, forward or backward, with slow steering in half the draws, each kept
only if it also survives 10% errors on its joint shape (a model's decoding error): the family whose
decoded gaits replay as decoded, used for inverse design (docs/design.md)."""
DEFAULT_PRESET = "arcs"
"""What ``snakeloco generate --family structured`` draws with no preset flag: the family the shipped
structured checkpoint is trained on."""


def draw_wave(
    kind: str,
    rng: np.random.Generator,
    frequencies: tuple[float, ...],
    undulation: tuple[tuple[float, float], tuple[float, float]] = ((0.5, 1.3), (0.4, 1.6)),
) -> GaitEquation:
    """A random gait-equation wave of ``kind`` (``KINDS``), the ranges of the library's search;
    ``undulation``: the (yaw amplitude, |spatial frequency|) ranges of a lateral undulation."""
    f = float(rng.choice(frequencies))
    sign = float(rng.choice([-1.0, 1.0]))
    if kind == "undulate":
        (a_lo, a_hi), (nu_lo, nu_hi) = undulation
        return GaitEquation(
            a_yaw=rng.uniform(a_lo, a_hi), nu_yaw=sign * rng.uniform(nu_lo, nu_hi), frequency=f
        )
    if kind == "sidewind":
        nu = rng.uniform(*NU_RANGES["sidewind"])
        (p_lo, p_hi), (y_lo, y_hi) = AMPLITUDE_RANGES["sidewind"]
        return GaitEquation(
            a_pitch=rng.uniform(p_lo, p_hi),
            a_yaw=rng.uniform(y_lo, y_hi),
            nu_pitch=nu,
            nu_yaw=nu,
            delta=sign * rng.uniform(np.pi / 8, np.pi / 2),
            frequency=f,
        )
    if kind == "roll":
        a, nu = rng.uniform(*AMPLITUDE_RANGES["roll"][0]), rng.uniform(*NU_RANGES["roll"])
        delta = sign * np.pi / 2 + rng.uniform(-0.4, 0.4)
        return GaitEquation(a_pitch=a, a_yaw=a, nu_pitch=nu, nu_yaw=nu, delta=delta, frequency=f)
    if kind == "turn":
        (p_lo, p_hi), (y_lo, y_hi) = AMPLITUDE_RANGES["turn"]
        nu_p, nu_y = NU_RANGES["turn_pitch"][1], NU_RANGES["turn_yaw"][1]
        return GaitEquation(
            a_pitch=rng.uniform(p_lo, p_hi),
            a_yaw=rng.uniform(y_lo, y_hi),
            nu_pitch=rng.uniform(-nu_p, nu_p),
            nu_yaw=rng.uniform(-nu_y, nu_y),
            delta=rng.uniform(-np.pi, np.pi),
            frequency=f,
        )
    raise ValueError(f"unknown wave kind {kind!r}; one of {KINDS}")


PITCH_KINDS = ("sidewind", "roll", "turn")
"""Kinds whose wave needs pitch joints: a planar robot's family draws none of them."""


def for_robot(cfg: StructuredConfig, robot: Robot) -> StructuredConfig:
    """The family ``cfg`` as ``robot`` can draw it: on a planar robot (no pitch joints) undulation
    only, each other kind's weight 0 (a sidewinding or rolling wave on yaw joints alone is an
    undulation under another name); otherwise ``cfg`` itself."""
    if robot.joint_pattern != "planar":
        return cfg
    weights = tuple(
        w if kind not in PITCH_KINDS else 0.0 for kind, w in zip(KINDS, cfg.kind_weights, strict=True)
    )
    return cfg.model_copy(update={"kind_weights": weights})


def library_gait(kind: str, robot: Robot) -> GaitEquation:
    """The gait library's ``kind`` gait (``sim.gaits.library.PRESETS``) on ``robot`` (carried there by the
    serpenoid rule, ``GaitEquation.on_robot``), which a library family scales."""
    return PRESETS[kind].gait.on_robot(robot)


def draw_library_wave(
    kind: str, rng: np.random.Generator, cfg: StructuredConfig, robot: Robot
) -> GaitEquation:
    """A library family's ``kind`` wave (``StructuredConfig.library``): the library gait scaled by s
    in amplitude_scale, at one of the kind's frequencies, its offset drawn where library_offsets
    names the kind, mirrored (offset + pi) or not, an undulation forward or backward."""
    base = library_gait(kind, robot)
    f = float(rng.choice(cfg.frequencies[kind]))
    s = rng.uniform(*cfg.amplitude_scale)
    delta = rng.uniform(*cfg.library_offsets[kind]) if kind in cfg.library_offsets else base.delta
    delta += np.pi * float(rng.integers(2))  # the mirror image
    nu_yaw = base.nu_yaw * (float(rng.choice([-1.0, 1.0])) if kind == "undulate" else 1.0)
    return base.scaled(s).model_copy(
        update={
            "nu_yaw": nu_yaw,
            "delta": float(np.angle(np.exp(1j * delta))),
            "frequency": f,
        }
    )


def undulation_scale(wave: GaitEquation, robot: Robot) -> float:
    """An undulation's yaw amplitude relative to the library undulation's (on ``robot``)."""
    return wave.a_yaw / library_gait("undulate", robot).a_yaw


def curve_wave(scale: float, frequency: float, mirrored: bool, robot: Robot) -> GaitEquation:
    """The library's turning gait at ``scale`` of its amplitudes and at ``frequency``, as tuned or
    mirrored (yaw joints negated). Beside an undulation at another frequency it bends the path into
    an arc (docs/gaits.md, "The arcs family")."""
    base = library_gait("turn", robot)
    delta = base.delta + (np.pi if mirrored else 0.0)
    return base.scaled(scale).model_copy(
        update={
            "delta": float(np.angle(np.exp(1j * delta))),
            "frequency": frequency,
        }
    )


def draw_structured(
    cfg: StructuredConfig, seed: int, index: int, attempt: int, robot: Robot
) -> tuple[np.ndarray, dict]:
    """Record ``index``'s gait at ``attempt`` on ``robot``: its commanded joint shape (N, L, 2) rad
    and what was drawn (kinds, waves, steering, curve, scale), JSON-ready. Waves are in the robot's
    own units (rad per module of its joints); a library family's gaits are carried to it by the
    serpenoid rule (``library_gait``)."""
    cfg = for_robot(cfg, robot)
    rng = np.random.default_rng([seed, index, attempt])
    weights = np.asarray(cfg.kind_weights, np.float64)
    kind = str(rng.choice(KINDS, p=weights / weights.sum()))
    undulation = (cfg.undulate_amplitude, cfg.undulate_wavenumber)
    if cfg.library:
        main = draw_library_wave(kind, rng, cfg, robot)
    else:
        main = draw_wave(kind, rng, cfg.frequencies[kind], undulation)
    if cfg.amplitude_scale != (1.0, 1.0) and not cfg.library:  # no draw at (1, 1): streams unchanged
        s = rng.uniform(*cfg.amplitude_scale)
        main = main.scaled(s)
    shape = main.shape(robot)
    drawn: dict = {"kind": kind, "wave": main.model_dump()}
    if rng.random() < cfg.second_wave:
        second_kind = str(rng.choice(KINDS))
        others = [f for f in cfg.frequencies[second_kind] if abs(f - main.frequency) > 1e-6]
        others = others or [
            f for fs in cfg.frequencies.values() for f in fs if abs(f - main.frequency) > 1e-6
        ]
        second = draw_wave(second_kind, rng, tuple(sorted(set(others))), undulation)
        scale = rng.uniform(*cfg.second_scale)
        shape = shape + scale * second.shape(robot)
        drawn["second_wave"] = second.model_dump() | {"scale": scale}
    if rng.random() < cfg.steering:
        amplitude, phase = rng.uniform(*cfg.steering_amplitude), rng.uniform(-np.pi, np.pi)
        yaw = ~layout(robot)[1]  # joints 2, 4, 6, 8 of the default robot
        shape[yaw, 0, 0] += amplitude * np.cos(phase)  # bin 0: the lowest excited frequency
        shape[yaw, 0, 1] += amplitude * np.sin(phase)
        drawn["steering"] = {"amplitude": amplitude, "phase": phase, "frequency": float(RECORD.freqs[0])}
    if (  # after every other draw, and only where the family curves: other families' streams unchanged
        cfg.curve > 0
        and kind == "undulate"
        and abs(main.frequency - cfg.curve_frequency) > 1e-6
        and rng.random() < cfg.curve
    ):
        scale = np.exp(rng.uniform(*np.log(cfg.curve_scale))) * undulation_scale(main, robot)  # log-uniform
        curve = curve_wave(scale, cfg.curve_frequency, bool(rng.integers(2)), robot)
        shape = shape + curve.shape(robot)
        drawn["curve"] = curve.model_dump()
    peak = np.abs(shape_to_commands(shape, limit=np.inf)).max()
    scale = min(1.0, robot.command_limit / peak)  # within the command limit without clipping the waves
    drawn["scale"] = scale
    return shape * scale, drawn
