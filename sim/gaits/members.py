"""Exact members of the structured family (projected onto: ``sim.gaits.projection``).

A *member* is what the structured family draws (``sim.gaits.structured``): one gait-equation wave of a
kind the family allows, at one of that kind's excited frequencies, plus (where the family steers) a
slow steering wave of amplitude S and phase psi on the yaw joints at the lowest excited frequency:

    c_k(main bin)  = wave coefficients (``GaitEquation.shape``)
    c_k(bin 0)    += S e^{i psi}   on the yaw joints (k = 2, 4, 6, 8 on the default robot; every joint on a planar one)

scaled as a whole to the command limit where its peak command would exceed it. Its parameters are
named, JSON-ready and re-synthesise its commands to the bit (``Member.commands``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from snakeloco.sim.gaits.excitation import RECORD
from snakeloco.sim.gaits.library import PITCH, GaitEquation, layout, turned
from snakeloco.sim.gaits.spectra import shape_to_commands
from snakeloco.sim.robot.description import COMMAND_LIMIT, Robot

STEERING_BIN = 0
"""The steering wave runs at the lowest excited frequency (0.05 Hz: 20 s periods)."""
YAW = ~PITCH
"""The default robot's yaw joints (``sim.gaits.library.layout`` gives any robot's)."""
FREQS = RECORD.freqs
"""(L,) excited frequencies (Hz)."""


class Member(BaseModel):
    """One gait of the structured family, by its parameters (rad, rad per module, Hz)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    kind: Literal["undulate", "sidewind", "roll", "turn"] = Field(description="Kind of the main wave.")
    wave: GaitEquation = Field(description="The main travelling wave (``sim.gaits.library``).")
    steering_amplitude: float = Field(0.0, ge=0, le=COMMAND_LIMIT, description="Steering wave (rad).")
    steering_phase: float = Field(0.0, description="Phase of the steering wave (rad).")
    curve: GaitEquation | None = Field(
        None,
        description="A weak turning wave beside an undulation, at a frequency of its own "
        "(``sim.gaits.structured.curve_wave``): the path bends into an arc. None: straight.",
    )

    def shape(self, robot: Robot) -> np.ndarray:
        """The member's commanded joint shape (N, L, 2) rad on ``robot`` (``sim.gaits.spectra``
        convention; its parameters are in that robot's units, rad per module of its joints)."""
        shape = self.wave.shape(robot)
        if self.curve is not None:
            shape += self.curve.shape(robot)
        yaw = ~layout(robot)[1]
        shape[yaw, STEERING_BIN, 0] += self.steering_amplitude * np.cos(self.steering_phase)
        shape[yaw, STEERING_BIN, 1] += self.steering_amplitude * np.sin(self.steering_phase)
        return shape

    def commands(self, robot: Robot) -> np.ndarray:
        """Its joint commands (2000, N) rad at 20 Hz on ``robot``: what is replayed, drawn and
        exported."""
        return shape_to_commands(self.shape(robot), limit=robot.command_limit)

    def mirrored(self) -> Member:
        """The member's mirror image: its yaw joints' commands negated (the yaw wave's offset and the
        steering phase turned by pi), which the robot's left-right symmetry answers with the mirror
        image of the path (``sim.physics.body.mirror_body``; measured on 6 every-family members: final
        positions equal to 0.01 m with sideways, roll and yaw negated). A member of the family again
        where the family says so (``StructuredConfig.mirrors``): an undulation's offset is fixed at 0
        outside a library family, so there its image (the same yaw wave half a period later) is no
        member."""
        return self.model_copy(
            update={
                "wave": self.wave.mirrored(),
                "steering_phase": turned(self.steering_phase) if self.steering_amplitude > 0 else 0.0,
                "curve": None if self.curve is None else self.curve.mirrored(),
            }
        )

    def scaled(self, s: float) -> Member:
        """The member with every amplitude (its waves', its steering's) times ``s``: its commands
        times ``s``."""
        return self.model_copy(
            update={
                "wave": self.wave.scaled(s),
                "steering_amplitude": s * self.steering_amplitude,
                "curve": None if self.curve is None else self.curve.scaled(s),
            }
        )

    def params(self) -> dict:
        """JSON-ready parameters; ``Member.model_validate(params)`` gives the same member back."""
        return self.model_dump(mode="json")

    def describe(self) -> str:
        """The member in words, e.g. "undulation, wave to the tail (forward), 0.71 rad, 0.62 rad/module
        at 0.52 Hz; steering 0.25 rad at 0.05 Hz"."""
        w = self.wave
        if self.kind == "undulate":
            way = "wave to the tail (forward)" if w.nu_yaw > 0 else "wave to the head (backward)"
            text = f"undulation, {way}, {w.a_yaw:.2f} rad, {abs(w.nu_yaw):.2f} rad/module"
            if abs(w.delta) > np.pi / 2:
                text += ", mirrored"  # the library family's: yaw joints negated
        else:
            text = (
                f"{ {'sidewind': 'sidewinding', 'roll': 'rolling', 'turn': 'turning'}[self.kind] }, pitch "
                f"{w.a_pitch:.2f} rad / {w.nu_pitch:.2f} rad/module, yaw {w.a_yaw:.2f} rad / "
                f"{w.nu_yaw:.2f} rad/module, offset {w.delta:.2f} rad"
            )
        text += f" at {w.frequency:.2f} Hz"
        if self.curve is not None:
            c = self.curve
            text += (
                f"; curving: turning wave, pitch {c.a_pitch:.3f} rad, yaw {c.a_yaw:.3f} rad, offset "
                f"{c.delta:.2f} rad at {c.frequency:.2f} Hz"
            )
        if self.steering_amplitude > 0:
            f0 = FREQS[STEERING_BIN]
            text += f"; steering {self.steering_amplitude:.2f} rad at {f0:.2f} Hz"
        return text


def member_from_draw(drawn: dict) -> Member:
    """The member of a record as ``draw_structured`` logged it (``drawn``: kind, wave, steering,
    curve, scale). Records with a second wave are not members (the mixed preset's)."""
    if "second_wave" in drawn:
        raise ValueError("a record with a second wave is not a member of a one-wave family")
    steering = drawn.get("steering") or {"amplitude": 0.0, "phase": 0.0}
    curve = drawn.get("curve")
    return Member(
        kind=drawn["kind"],
        wave=GaitEquation(**drawn["wave"]),
        steering_amplitude=steering["amplitude"],
        steering_phase=steering["phase"],
        curve=None if curve is None else GaitEquation(**curve),
    ).scaled(float(drawn["scale"]))
