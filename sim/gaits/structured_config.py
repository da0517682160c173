"""How the structured family draws and screens its gaits (``StructuredConfig``) and the ranges of its
waves; ``sim.gaits.structured`` draws them (and re-exports these names)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

KINDS = ("undulate", "sidewind", "roll", "turn")
"""The kinds of travelling wave a record's main wave is drawn from (``draw_wave``)."""
NU_RANGES: dict[str, tuple[float, float]] = {
    "sidewind": (0.4, 1.4),
    "roll": (0.0, 1.2),
    "turn_pitch": (0.0, 2.0),
    "turn_yaw": (0.0, 1.6),
}
"""|Spatial frequency| ranges (rad per module) ``draw_wave`` draws for the kinds other than undulation
(``StructuredConfig.undulate_wavenumber``); a turning wave's pitch and yaw waves have their own."""
AMPLITUDE_RANGES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "sidewind": ((0.1, 0.6), (0.5, 1.2)),
    "roll": ((0.2, 1.0), (0.2, 1.0)),
    "turn": ((0.05, 0.5), (0.4, 1.2)),
}
"""(pitch, yaw) amplitude ranges (rad) ``draw_wave`` draws for the kinds other than undulation
(``StructuredConfig.undulate_amplitude``), before ``StructuredConfig.amplitude_scale``."""


class StructuredConfig(BaseModel):
    """How the structured family draws and screens its gaits."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    kind_weights: tuple[float, float, float, float] = Field(
        (1.0, 1.5, 1.0, 1.0),
        description="Relative odds of undulate, sidewind, roll and turn main waves. Sidewinding is drawn "
        "more: half of its draws moved and stayed predictable in the library's search (docs/gaits.md).",
    )
    frequencies: dict[str, tuple[float, ...]] = Field(
        {"undulate": (0.52, 0.93), "sidewind": (0.52, 0.93), "roll": (0.29, 0.52), "turn": (0.52,)},
        description="Excited frequencies (Hz) each kind of wave runs at (the servos track them to 0.99 or "
        "better). Left out where the search found that kind mostly unpredictable: rolling at 0.93 Hz "
        "(4 of 12 predictable), turning at 0.93 Hz (2 of 20).",
    )
    second_wave: float = Field(
        0.25, ge=0, le=1, description="Probability of a second, weaker wave on another bin."
    )
    second_scale: tuple[float, float] = Field(
        (0.2, 0.5), description="That wave's amplitude relative to its draw."
    )
    steering: float = Field(
        0.3, ge=0, le=1, description="Probability of a slow steering wave on the yaw joints."
    )
    steering_amplitude: tuple[float, float] = Field((0.1, 0.4), description="Its amplitude (rad).")
    curve: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Probability that an undulation also carries a weak turning wave (``curve_wave``) at "
        "curve_frequency, which bends its path into an arc (none where the undulation runs at that "
        "frequency).",
    )
    curve_scale: tuple[float, float] = Field(
        (0.03, 0.35),
        description="That wave's scale on the library's turning gait's amplitudes, relative to the "
        "undulation's scale on the library's undulation (``undulation_scale``): the arc's curvature "
        "follows the ratio of the two waves.",
    )
    curve_frequency: float = Field(0.29, gt=0, description="That wave's frequency (Hz).")
    max_spread: float = Field(
        0.1,
        gt=0,
        description="Largest ensemble final spread (RMS distance of perturbed final positions from the "
        "replay's / distance travelled) of a kept record.",
    )
    coefficient_noise: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Relative complex noise on every excited coefficient of the joint shape of each perturbed "
        "replay (beside the 1e-3 command noise): a record is kept only if its path also survives shape "
        "errors of this size, such as a model's decoding error (10% rejects every sidewinding, rolling "
        "and turning draw at 0.52 Hz and keeps 3 of 8 undulations, docs/gaits.md). 0: command noise only.",
    )
    screen_members: int = Field(
        2, ge=2, description="Replays in the first, cheap check (the gait and noisy copies)."
    )
    members: int = Field(4, ge=2, description="Replays in the full check of a gait that passed the first.")
    max_draws: int = Field(40, ge=1, description="Gaits drawn per record before giving up.")
    undulate_amplitude: tuple[float, float] = Field(
        (0.5, 1.3),
        description="Range of a lateral undulation's yaw amplitude (rad). The undulation-only family "
        "the design figures use narrows it to (0.5, 0.9), where 27-33% of draws survive 10% shape "
        "errors (docs/design.md).",
    )
    undulate_wavenumber: tuple[float, float] = Field(
        (0.4, 1.6),
        description="Range of a lateral undulation's |spatial frequency| (rad per module; either sign, "
        "forward or backward).",
    )
    amplitude_scale: tuple[float, float] = Field(
        (1.0, 1.0),
        description="Range of a factor on the main wave's amplitudes (drawn per record where the range "
        "is not (1, 1)): slow gaits as well as fast ones, the waves' shapes unchanged.",
    )
    library: bool = Field(
        False,
        description="Draw the gait library's gaits (``sim.gaits.library.PRESETS``, one a kind) instead of random "
        "waves: each at amplitude_scale times its amplitudes, at one of its kind's frequencies, as tuned "
        "or mirrored (yaw joints negated), undulation forward or backward, sidewinding's yaw offset "
        "drawn in library_offsets. A few smooth parameters a kind, so the records sample each densely "
        "(docs/every-model.md).",
    )
    library_offsets: dict[str, tuple[float, float]] = Field(
        {},
        description="In a library family: the yaw-offset range (rad) drawn per kind (its mirror image "
        "adds pi); kinds not named keep the library gait's offset.",
    )
    early_seconds: float = Field(
        0.0,
        ge=0,
        lt=100,
        description="Pause the first check's replays after this many seconds (0: no pause) and redraw "
        "a draw whose spread there already exceeds early_max_spread; the others carry on to 100 s "
        "from where they paused (docs/gaits.md: how often this early verdict differs from the 100 s one).",
    )
    early_max_spread: float = Field(
        0.3, gt=0, description="Largest spread at early_seconds of a draw that carries on."
    )
    sure_spread: float = Field(
        0.0,
        ge=0,
        description="A draw whose first check's 100 s spread is at most this is kept without the rest "
        "of its members (0: every kept draw gets all of them).",
    )

    def verdict(self, spread: float, replays: int) -> str:
        """What the screen does with a draw whose 100 s spread over its first ``replays`` replays is
        ``spread``: "redraw" (above ``max_spread``), "keep" (within it after all ``members``, or
        within ``sure_spread``) or "more" (run the rest of its members first)."""
        if spread > self.max_spread:
            return "redraw"
        return "keep" if replays >= self.members or spread <= self.sure_spread else "more"

    def mirrors(self, kind: str) -> bool:
        """Whether the mirror image of a ``kind`` member (yaw joints negated) is a member too: in a
        library family every kind's; otherwise every kind's but undulation's (its offset is fixed)."""
        return self.library or kind != "undulate"

    def amplitude_ranges(self, kind: str) -> tuple[tuple[float, float], tuple[float, float]]:
        """(pitch, yaw) amplitude ranges (rad) of a ``kind`` member of this family: what
        ``draw_wave`` draws times ``amplitude_scale`` (before the command-limit scale)."""
        s_lo, s_hi = self.amplitude_scale
        (p_lo, p_hi), (y_lo, y_hi) = (
            ((0.0, 0.0), self.undulate_amplitude) if kind == "undulate" else AMPLITUDE_RANGES[kind]
        )
        return (p_lo * s_lo, p_hi * s_hi), (y_lo * s_lo, y_hi * s_hi)
