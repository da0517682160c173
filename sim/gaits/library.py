"""The gait equation (Tesch et al. 2009) on this 8-joint snake, and the library of gaits tuned on it.

Joint k = 1..8 sits at module k; odd joints pitch, even joints yaw. Each is an offset-free sinusoid
of one temporal frequency f, with an amplitude and a spatial frequency (rad per module) per group
and a phase offset delta of the yaw wave against the pitch wave:

    pitch (odd k):  u_k(t) = A_pitch sin(nu_pitch k + 2 pi f t)
    yaw (even k):   u_k(t) = A_yaw   sin(nu_yaw k + 2 pi f t + delta)

f is one of the record's excited frequencies (``RECORD.freqs``), so a gait is exactly periodic
over the 100 s record and its joint shape (``sim.gaits.spectra``) is one non-zero bin: a library gait is
a joint shape like any other, and ``shape_to_commands`` of that shape gives back its commands.
Units: rad, rad per module, Hz.

Published parameters for 16-module robots do not transfer to this 8-joint snake (CMU sidewinding,
A 0.6 rad, 0.7 rad per module, 0.5 Hz, delta pi/4, rolls it in a circle): ``PRESETS`` were tuned on
this robot (docs/gaits.md says how, with the figures each preset reproduces).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.gaits.spectra import shape_to_commands
from snakeloco.sim.physics.body import heading_text, travel
from snakeloco.sim.physics.results import SimulationError
from snakeloco.sim.robot.description import BODY_LENGTH, COMMAND_LIMIT, DEFAULT_ROBOT, Robot


@functools.cache
def _layout(n_joints: int, pattern: str) -> tuple[np.ndarray, np.ndarray]:
    modules = np.arange(1, n_joints + 1)
    pitch = modules % 2 == 1 if pattern == "alternate" else np.zeros(n_joints, bool)
    modules.flags.writeable = pitch.flags.writeable = False
    return modules, pitch


def layout(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """A robot's joints for the gait equation: module index k of each joint (1-based, as the MJCF names
    them) and which joints pitch (odd k on an alternating snake, none on a planar one), read-only."""
    return _layout(robot.n_joints, robot.joint_pattern)


MODULES, PITCH = layout(DEFAULT_ROBOT)
"""The default robot's modules (1..8) and pitch joints (odd k)."""


class GaitEquation(BaseModel):
    """One gait of the gait equation (module docstring), all angles in rad."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    a_pitch: float = Field(0.0, ge=0, le=COMMAND_LIMIT, description="Amplitude of the pitch joints (rad).")
    a_yaw: float = Field(0.0, ge=0, le=COMMAND_LIMIT, description="Amplitude of the yaw joints (rad).")
    nu_pitch: float = Field(0.0, description="Spatial frequency of the pitch wave (rad per module).")
    nu_yaw: float = Field(0.0, description="Spatial frequency of the yaw wave (rad per module).")
    delta: float = Field(0.0, description="Phase of the yaw wave against the pitch wave (rad).")
    frequency: float = Field(0.93, gt=0, description="Temporal frequency (Hz): one of RECORD.freqs.")

    @model_validator(mode="after")
    def _on_an_excited_bin(self) -> GaitEquation:
        if np.abs(RECORD.freqs - self.frequency).min() > 0.006:
            raise ValueError(
                f"frequency {self.frequency} Hz is not one of the record's excited frequencies "
                f"{[round(f, 2) for f in RECORD.freqs.tolist()]} (Hz)"
            )
        return self

    @property
    def bin_index(self) -> int:
        """Index l of the excited frequency the gait runs at."""
        return int(np.argmin(np.abs(RECORD.freqs - self.frequency)))

    def shape(self, robot: Robot) -> np.ndarray:
        """The gait's joint shape (N, L, 2) on ``robot``: c_kl = A_k e^{i(phi_k - pi/2)} at its bin,
        zero elsewhere (a planar robot's joints all take the yaw wave).

        A sin(x) = Re(A e^{i(x - pi/2)}), so with x = phi_k + 2 pi f t the coefficient is
        A e^{i(phi_k - pi/2)}, in ``sim.gaits.spectra``'s convention u(t) = Re(c e^{i 2 pi f t}).
        """
        modules, pitch = layout(robot)
        amplitude = np.where(pitch, self.a_pitch, self.a_yaw)  # (N,)
        phase = np.where(pitch, self.nu_pitch * modules, self.nu_yaw * modules + self.delta) - np.pi / 2
        shape = np.zeros((robot.n_joints, RECORD.n_components, 2))
        shape[:, self.bin_index, 0] = amplitude * np.cos(phase)
        shape[:, self.bin_index, 1] = amplitude * np.sin(phase)
        return shape

    def commands(self, robot: Robot) -> np.ndarray:
        """Joint commands (2000, N) rad at 20 Hz over the record on ``robot``."""
        return shape_to_commands(self.shape(robot), limit=robot.command_limit)

    def on_robot(self, robot: Robot) -> GaitEquation:
        """This gait (tuned on the default robot) carried to ``robot`` by the serpenoid rule: the same
        number of waves along the body and the same winding angle in each plane, sampled at the
        robot's own joints (Hirose's serpenoid curve: a joint Delta modules from the next joint of its
        plane bends 2 alpha sin(beta / 2) for a phase step beta = nu Delta). So nu scales by
        8 / N and each amplitude by sin(nu' Delta' / 2) / sin(nu Delta / 2), Delta the spacing of
        the plane's joints (2 on an alternating snake, 1 for a planar snake's yaw joints); offset and
        frequency are kept. The default robot gets the gait back unchanged."""
        if (robot.n_joints, robot.joint_pattern) == (DEFAULT_ROBOT.n_joints, DEFAULT_ROBOT.joint_pattern):
            return self
        ratio = DEFAULT_ROBOT.n_joints / robot.n_joints
        spacing = 2 if robot.joint_pattern == "alternate" else 1

        def carried(a: float, nu: float) -> tuple[float, float]:
            new = nu * ratio
            if abs(nu) < 1e-9:  # no wave along the body: the same bend at every joint
                return a, new
            gain = np.sin(new * spacing / 2) / np.sin(nu * 2 / 2)
            return float(min(a * abs(gain), robot.command_limit)), new

        a_p, nu_p = carried(self.a_pitch, self.nu_pitch)
        a_y, nu_y = carried(self.a_yaw, self.nu_yaw)
        if robot.joint_pattern == "planar":
            a_p = 0.0
        return self.model_copy(update={"a_pitch": a_p, "a_yaw": a_y, "nu_pitch": nu_p, "nu_yaw": nu_y})

    def scaled(self, s: float) -> GaitEquation:
        """The same wave with both amplitudes times ``s``."""
        return self.model_copy(update={"a_pitch": s * self.a_pitch, "a_yaw": s * self.a_yaw})

    def mirrored(self) -> GaitEquation:
        """The same wave with its yaw joints negated: the offset turned by pi."""
        return self.model_copy(update={"delta": turned(self.delta)})


def turned(phase: float) -> float:
    """phase + pi, wrapped to [-pi, pi)."""
    return float((phase + 2 * np.pi) % (2 * np.pi) - np.pi)


class GaitFigures(BaseModel):
    """What physics did with a gait over the 100 s record (the unperturbed replay; spread from its
    ensemble). Positions in the start frame (``sim.physics.body``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    displacement: float = Field(description="Distance from start to end (m): ``travel``'s distance.")
    straightness: float = Field(description="Displacement / path length (1: a straight line).")
    direction_deg: float = Field(
        description="Direction of travel: where the end lies from the start, from the initial heading "
        "(deg, left +; ``sim.physics.body.travel``, as every readout, table and page says it)."
    )
    net_roll: float = Field(description="Roll change over the record (rad).")
    net_yaw: float = Field(description="Heading change over the record (rad, left +).")
    spread: float = Field(
        description="Ensemble final-position spread / displacement (``sim.scores.consistency``)."
    )

    @property
    def speed(self) -> float:
        """Displacement / record length (m/s)."""
        return self.displacement / RECORD.duration

    @property
    def body_lengths_per_s(self) -> float:
        """Speed in body lengths (0.95 m) per second."""
        return self.speed / BODY_LENGTH


def gait_figures(ensemble_body: np.ndarray) -> GaitFigures:
    """Figures of a gait from its ensemble's body series (K, T, 6) at 20 Hz, member 0 unperturbed."""
    from snakeloco.sim.scores.consistency import ensemble_spread, path_stats

    body = np.asarray(ensemble_body, np.float64)
    s = path_stats(body[0], RECORD.sample_rate)
    displacement = float(s["displacement"])
    return GaitFigures(
        displacement=displacement,
        straightness=displacement / max(float(s["path_length"]), 1e-9),
        direction_deg=travel(body[0])["direction_deg"],
        net_roll=float(s["net_roll"]),
        net_yaw=float(body[0, -1, 5] - body[0, 0, 5]),
        spread=ensemble_spread(body, RECORD.sample_rate)["final_spread"],
    )


class WorstCase(BaseModel):
    """How far a gait's 100 s end point moves over the default variation set (``sim.scores.robustness``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    end_error_m: float = Field(description="Largest distance of a variation's end from the nominal end (m).")
    rel: float = Field(description="That distance over max(nominal distance, 0.5 m).")
    variation: str = Field(description="The variation that moved it most.")


class GaitPreset(BaseModel):
    """A named gait of the library, with what it is for and the figures it was measured to give."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    gait: GaitEquation
    about: str
    measured: GaitFigures
    worst: WorstCase


def measure_gait(gait: GaitEquation, simulator, ensemble: int = 4, seed: int = 0) -> GaitFigures:
    """Replay a gait with ``ensemble`` - 1 perturbed copies (``sim.scores.consistency``) on ``simulator`` (a
    ``sim.physics.simulator.Simulator``) and measure it. Raises SimulationError if the unperturbed replay breaks;
    perturbed members that break leave the ensemble."""
    from snakeloco.sim.scores.consistency import perturbed_commands

    result = simulator.simulate(perturbed_commands(gait.commands(simulator.robot), ensemble, seed=seed))
    if result.failures[0] is not None:
        raise SimulationError(result.failures[0])
    ok = [i for i, f in enumerate(result.failures) if f is None]
    return gait_figures(result.body[ok])


LIBRARY_FILE = Path(__file__).with_name("library.json")
"""The library's gaits as data: name, gait equation, what it is for, measured figures (displacement m,
straightness, heading deg, net roll and yaw rad, spread) and worst case over the default variation
set (end error m, relative, which variation)."""


BASE_GAITS = ("sidewind", "undulate", "roll", "turn")
"""The library's first four, one per kind, found by the grid search of docs/gaits.md (the runs that
``fit-robot`` advises and ``bench fit`` measures with)."""
PRESETS: dict[str, GaitPreset] = {
    entry.pop("name"): GaitPreset.model_validate(entry) for entry in json.loads(LIBRARY_FILE.read_text())
}
"""The library: gait-equation gaits tuned on this robot, each with the figures it was measured to
give (``measure_gait``: a 4-member ensemble, seed 0, MuJoCo 4.0.0) and its worst case over the
default variation set (``sim.scores.robustness``, MuJoCo 4.0.1): the four of ``BASE_GAITS``, then the most
robust members found per kind and direction (``gait --search-robust``). docs/gaits.md has the
searches that found them and how each was chosen."""


def library_table() -> str:
    """The library as a text table: parameters and measured figures of each preset."""
    w = max(map(len, PRESETS))
    head = (
        f"{'gait':<{w}} {'A_p':>5} {'A_y':>5} {'nu_p':>6} {'nu_y':>6} {'delta':>6} {'f Hz':>5} | "
        f"{'m/s':>6} {'BL/s':>6} {'distance m':>10} {'straight':>8} {'direction':>9}  {'heading change':<22} "
        f"{'roll':>7} {'spread':>6} | "
        f"{'worst m':>7} {'worst':>6}  worst variation"
    )
    rows = [head, "-" * len(head)]
    for name, p in PRESETS.items():
        g, m = p.gait, p.measured
        rows.append(
            f"{name:<{w}} {g.a_pitch:5.2f} {g.a_yaw:5.2f} {g.nu_pitch:6.2f} {g.nu_yaw:6.2f} {g.delta:6.2f} "
            f"{g.frequency:5.2f} | {m.speed:6.3f} {m.body_lengths_per_s:6.3f} {m.displacement:10.2f} "
            f"{m.straightness:8.2f} {m.direction_deg:+8.0f}°  {heading_text(np.degrees(m.net_yaw)):<22} "
            f"{m.net_roll:7.2f} {m.spread:6.3f} | "
            f"{p.worst.end_error_m:7.2f} {100 * p.worst.rel:5.0f}%  {p.worst.variation}"
        )
    legend = (
        "A_p, A_y: pitch and yaw amplitudes (rad); nu_p, nu_y: spatial frequencies (rad per module); "
        "delta: yaw wave's phase against the pitch wave (rad); f: temporal frequency.\n"
        "m/s, BL/s: speed (BL: body lengths); distance: start to end over 100 s; straight: "
        "distance / path length; direction: of travel, where the end lies from the initial heading (deg, left +); "
        "heading change: how much the body turned (deg, left +; whole turns said apart); roll: net roll (rad); "
        "spread: where 0.1%-noisy replays end, over the distance.\n"
        "worst: how far the end point moves on the default set of physics variations (friction, "
        "masses, servos, slope, latency; `snakeloco robustness`), in m and over the distance."
    )
    return "\n".join(rows) + "\n\n" + legend + "\n"
