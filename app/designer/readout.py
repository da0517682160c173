"""The readout at the top of a tab's panel: what each line in the scene is, how far and where each
path went, how far the model's end point is from MuJoCo's, and what the replay is doing.

Distances are straight-line displacements of a path's end from the start (the start frame's origin,
where the scene draws it; m); directions of travel are measured
from the initial heading (deg, left +); heading change is the body's yaw at the end minus at the
start (deg, left +). All in the start frame of ``sim.physics.body``, from the body series the tab draws.
"""

from __future__ import annotations

import html
from dataclasses import dataclass

import numpy as np

from snakeloco.sim.physics.body import heading_text

READOUT_ID = "snakeloco-readout"
"""The readout's HTML element id (what a page test looks up)."""


@dataclass(frozen=True)
class PathEnd:
    """Where a body path (T, 6) ended, in the start frame."""

    distance_m: float
    direction_deg: float
    heading_change_deg: float
    forward_m: float
    sideways_m: float

    @classmethod
    def of(cls, body: np.ndarray) -> PathEnd:
        b = np.asarray(body, np.float64)
        f, s = float(b[-1, 1]), float(b[-1, 2])  # the start frame's origin is where the snake started
        return cls(
            distance_m=float(np.hypot(f, s)),
            direction_deg=float(np.degrees(np.arctan2(s, f))),
            heading_change_deg=float(np.degrees(b[-1, 5] - b[0, 5])),
            forward_m=f,
            sideways_m=s,
        )


@dataclass(frozen=True)
class Readout:
    """What the readout says about the tab's current gait."""

    model: PathEnd | None  # the decoded (predicted) path's end; None for an imported gait
    mujoco: PathEnd | None  # the replay's end (so far, while streaming)
    state: str  # "simulating", "streaming", "done" or "failed"
    t_s: float = 0.0  # replay time simulated so far (s)
    duration_s: float = 100.0
    reason: str = ""  # why a replay failed
    gait: str = ""  # the gait in words (its family member, or where it came from)
    off_data: bool = False
    ring: bool = False  # the tab's family draws a ring where the replay is likely to end
    sliders: tuple[float, ...] | None = None  # the slider values of the gait (None: a file's gait)
    robot: str = ""  # why the model's path is another robot's than the replay's (``robot_warning``)
    variations: str = (
        ""  # how far the end point moves on other robots (``sim.scores.robustness.readout_line``)
    )
    no_model: str = ""  # why a gait has no model path (an imported file, a library gait)
    cluster: str = ""  # where a slider move left the chosen Gait cluster ('' while it is inside it)

    @property
    def gap_m(self) -> float | None:
        """Distance between the model's and MuJoCo's end points (m), once the replay is done."""
        if self.model is None or self.mujoco is None or self.state != "done":
            return None
        return float(
            np.hypot(
                self.model.forward_m - self.mujoco.forward_m, self.model.sideways_m - self.mujoco.sideways_m
            )
        )

    @property
    def gap_share(self) -> float | None:
        """The gap over the distance MuJoCo's snake travelled."""
        gap = self.gap_m
        return None if gap is None else gap / max(self.mujoco.distance_m, 1e-9)


def swatch(color: tuple[int, int, int], height: int = 4) -> str:
    r, g, b = color
    return (
        f'<span style="display:inline-block;width:18px;height:{height}px;background:rgb({r},{g},{b});'
        'vertical-align:middle;margin-right:4px"></span>'
    )


GAP_BASE_M = 0.5
"""A path shorter than this is no base for a percentage: the gap is then said in metres alone (a
0.48 m gap read "196% of the distance" for a gait that went 0.25 m)."""


def _cells(end: PathEnd | None, who: str, why: str = "") -> str:
    if end is None:
        return f"<td>{who}</td><td colspan=3>{html.escape(why) if why else '—'}</td>"
    return (
        f"<td>{who}</td>"
        f'<td data-key="{who.lower()}-distance">{end.distance_m:.2f} m</td>'
        f'<td data-key="{who.lower()}-direction">{end.direction_deg:+.0f}°</td>'
        f'<td data-key="{who.lower()}-heading">{heading_text(end.heading_change_deg)}</td>'
    )


def readout_html(r: Readout, colors: dict[str, tuple[int, int, int]]) -> str:
    """The readout as HTML for viser's ``add_html`` (``colors``: the scene's line colours by name:
    model, mujoco, ensemble, ring)."""
    legend = [
        swatch(colors["model"]) + "model's path",
        swatch(colors["mujoco"]) + "MuJoCo replay",
        swatch(colors["ensemble"], 2) + "ensemble (0.1% noise)",
    ]
    if r.ring:
        legend.append(swatch(colors["ring"], 2) + "ring: where replays likely end")
        legend.append(
            "<br><i>paper family: random multisines are chaotic on this robot, so its paths are a spread "
            "(the orange path is their mean), not a line; the structured family's are</i>"
        )
    if r.state == "done":
        state = "replay done"
    elif r.state == "streaming":
        state = f"replay streaming: t = {r.t_s:.0f} s of {r.duration_s:.0f}"
    elif r.state == "failed":
        state = f'<b style="color:#c00">replay failed</b>: {html.escape(r.reason)}'
    else:
        state = "simulating..."
    gap = r.gap_m
    if r.model is None and r.no_model:
        gap_text = "<b>End-point gap</b>: none without a model path"
    elif gap is None:
        gap_text = "<b>End-point gap</b> after the replay"
    elif r.mujoco.distance_m >= GAP_BASE_M:
        gap_text = (
            f'<b>End-point gap</b> <span data-key="gap">{gap:.2f} m</span> '
            f'(<span data-key="gap-share">{100 * r.gap_share:.0f}%</span> of the distance)'
        )
    else:
        gap_text = (
            f'<b>End-point gap</b> <span data-key="gap">{gap:.2f} m</span> '
            f"(MuJoCo's snake went {r.mujoco.distance_m:.2f} m: too short a base for a percentage)"
        )
    # Which slider values this readout is for: a protocol client (``bench load``) matches its views
    # to its drags by it, and a stale readout says so.
    sliders = f' data-sliders="{",".join(f"{v:.4f}" for v in r.sliders)}"' if r.sliders is not None else ""
    parts = [
        f'<div id="{READOUT_ID}"{sliders} data-state="{r.state}" style="font-size:0.82em;line-height:1.5">',
        "<div>" + " &nbsp;".join(legend) + "</div>",
        '<table style="border-collapse:collapse;width:100%"><tr style="opacity:0.7">'
        "<td></td><td>distance</td><td>direction</td><td>heading</td></tr>",
        f"<tr>{_cells(r.model, 'Model', r.no_model)}</tr><tr>{_cells(r.mujoco, 'MuJoCo')}</tr></table>",
        f"<div>{gap_text} · <span data-key='state'>{state}</span></div>",
    ]
    if r.gait:
        parts.append(f"<div>{html.escape(r.gait)}</div>")
    if r.off_data:
        parts.append(
            '<div style="color:#b45309"><b>⚠ Off the data</b>: this z_B is less likely than 99% of the '
            "training records; the model extrapolates here.</div>"
        )
    if r.cluster:
        parts.append(
            f'<div data-key="cluster" style="color:#b45309"><b>⚠ Off the cluster</b>: {html.escape(r.cluster)}</div>'
        )
    if r.variations:
        parts.append(
            f'<div data-key="variations">{swatch(colors["variations"], 2)}{html.escape(r.variations)}</div>'
        )
    if r.robot:
        parts.append(f'<div style="color:#b45309"><b>⚠ Robot</b>: {html.escape(r.robot)}</div>')
    parts.append("</div>")
    return "".join(parts)


STREAM_READOUT_PERIOD_S = 1.0
"""How often a streaming replay's readout (t = x s, MuJoCo's distance so far) is sent."""


class TabReadout:
    """What a ``DesignerClient`` ``tab``'s readout says of its current gait."""

    def __init__(self, tab) -> None:
        self.tab = tab

    def _variations_line(self) -> str:
        """The variations' line for the current gait: the replays' (with how far the physics head's
        prediction was from them), or the prediction's until they are in ('' without either)."""
        from snakeloco.sim.scores.robustness import prediction_line, readout_line

        predicted = (
            self.tab.predicted[1]
            if self.tab.predicted and self.tab.predicted[0] == self.tab.version
            else None
        )
        if self.tab.variations is None or self.tab.variations[0] != self.tab.version:
            return "" if predicted is None else "predicted " + readout_line(predicted)
        line = readout_line(self.tab.variations[1])
        return line if predicted is None else f"{line}; {prediction_line(predicted, self.tab.variations[1])}"

    def _cluster_line(self, gait) -> str:
        """Where a decoded gait's z_B sits when it has left the Gait cluster its sliders move in."""
        density = self.tab.model.config.density
        lat = gait.latents
        if density is None or lat is None or lat.component is None:
            return ""
        now = int(density.component_of(np.asarray([lat.z_b]))[0])
        if now == lat.component:
            return ""
        return (
            f"the sliders move in '{density.names[lat.component]}', but this z_B sits in '{density.names[now]}' "
            "(pick that cluster to move along its axes)"
        )

    def show_readout(self, gait, state: str, body: np.ndarray | None = None, reason: str = "") -> Readout:
        """Say what ``gait`` (a ``DecodedGait``) is and where its paths went: ``state`` simulating,
        streaming, done or failed (``reason``); ``body``: MuJoCo's body series (T, 6) so far."""
        from snakeloco.app.designer.scene import BAND_COLOR, FAN_COLOR, GEN_COLOR, SIM_COLOR, VARIATION_COLOR
        from snakeloco.sim import RECORD

        if gait.member is not None:  # what is replayed and drawn; how near the decode was is the panel's
            words = f"Gait: {gait.member.describe()}"
        else:
            words = "" if gait.source == "model" else f"Gait: {gait.source}"
        self.tab.readout = Readout(
            model=PathEnd.of(gait.body_ds) if gait.body_ds is not None else None,
            mujoco=PathEnd.of(body) if body is not None and len(body) > 1 else None,
            state=state,
            t_s=0.0 if body is None else (len(body) - 1) / RECORD.sample_rate,
            duration_s=RECORD.duration,
            reason=reason,
            gait=words,
            off_data=gait.off_data,
            ring=self.tab.scene.end_spread is not None,
            sliders=gait.latents.sliders if gait.latents is not None else None,
            robot=self.tab.model.robot_warning(self.tab.session.robot) or "",
            variations=self._variations_line(),
            no_model=gait.no_model,
            cluster=self._cluster_line(gait),
        )
        colors = {
            "model": GEN_COLOR,
            "mujoco": SIM_COLOR,
            "ensemble": FAN_COLOR,
            "ring": BAND_COLOR,
            "variations": VARIATION_COLOR,
        }
        self.tab.controls.readout.content = readout_html(self.tab.readout, colors)
        return self.tab.readout
