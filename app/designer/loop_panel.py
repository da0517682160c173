"""A tab's "Closed loop" folder: the current gait played with its steering loop on the default variation
set, drawn as the closed-loop fan (teal) beside the open-loop Variations fan (violet), with a line of
what it did and a plot of the steering input (docs/closed-loop.md).

After each replay (on by default) the panel's worker finds the gait's steering input (the probes
alone, 20 s each: the fan is the closed-loop check), takes the path the designer shows for it (a
member's predicted path; else its nominal replay, averaged over a wave period) and plays it closed
loop (*arrive*) on the nominal robot and each variation, on the physics pool's closed-loop turn
(after every tab's replays, ensembles and variations). A new gait drops it. A gait no input steers
says so and keeps its open-loop fan.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np
import viser
import viser.uplot as uplot

from snakeloco.app.designer.job_bar import JobBar, JobControls, build_job_controls
from snakeloco.app.server.viser_patches import set_plot_data
from snakeloco.app.server.workers import LatestWorker
from snakeloco.sim import BODY_TIMES
from snakeloco.sim.control.closed_loop import nominal_path, trailing_mean
from snakeloco.sim.control.find import find_steering
from snakeloco.sim.physics.results import Dropped, SimulationError
from snakeloco.sim.physics.scheduler import Turn
from snakeloco.sim.robot.variations import DEFAULT_SET
from snakeloco.sim.scores.closed_loop import closed_loop_robustness

PROBE_SECONDS = 20.0
"""Open-loop seconds of each steering probe in the designer (the command line's: 30 s and a closed-loop check)."""
PLOT_STEP = 4
"""Steering samples per plotted point (5 Hz)."""


@dataclass
class LoopControls:
    enabled: viser.GuiCheckboxHandle
    status: viser.GuiMarkdownHandle
    plot: viser.GuiUplotHandle
    job: JobControls


def build_loop_controls(gui: viser.GuiApi) -> LoopControls:
    with gui.add_folder("Closed loop", expand_by_default=False):
        enabled = gui.add_checkbox(
            "Closed loop",
            initial_value=True,
            hint="After each replay, play the gait with its steering loop on the 12 physics variations: "
            "the teal fan, each run stopped at the path's end (docs/closed-loop.md)",
        )
        status = gui.add_markdown("The steering loop plays each replayed gait on other robots.")
        job = build_job_controls(gui, "closed-loop replays of this gait")
        t = np.array([0.0, 1.0])
        plot = gui.add_uplot(
            data=(t, np.full(2, np.nan)),
            series=(uplot.Series(label="t (s)"), uplot.Series(label="steering", stroke="#14966e", width=2)),
            scales={"x": {"time": False}},
            title="steering input, nominal robot",
            aspect=2.0,
        )
    return LoopControls(enabled, status, plot, job)


def loop_summary(report: dict, open_line: str | None) -> str:
    """The folder's text: the input, where the runs ended, when they arrived, the open loop beside."""
    rows = [r for r in report["variations"] if r["failure"] is None]
    arrived = [r["arrival_s"] for r in rows if r["arrived"]]
    lines = [
        f"**{report['steering_line']}**; path {report['distance_m']:.1f} m.",
        f"**closed loop on other robots**: ends within {report['worst_end_error_m']:.2f} m "
        f"({100 * report['worst_rel']:.1f}%) of the path's end; worst: {report['worst']}."
        if report["worst_end_error_m"] is not None
        else "**closed loop**: every variation broke the simulation.",
        f"arrived {len(arrived)} of {len(report['variations'])}"
        + (f" in {min(arrived):.0f}-{max(arrived):.0f} s" if arrived else "")
        + (f"; late (not there by the 200 s cap): {', '.join(report['late'])}" if report["late"] else "")
        + (f"; broke: {', '.join(report['broken'])}" if report["broken"] else ""),
    ]
    if open_line:
        lines.append(f"open loop, for comparison: {open_line}")
    return "\n\n".join(lines)


class LoopPanel:
    """Wires a tab's ``LoopControls``; ``tab`` is its ``DesignerClient``."""

    def __init__(self, tab, controls: LoopControls, enabled: bool = True) -> None:
        self.tab, self.controls = tab, controls
        controls.enabled.value = enabled  # before the callback: setting it from here requests nothing
        self.report: dict | None = None
        self.version = 0  # the gait version the last request was for
        self.found: tuple[int, object] | None = None  # (gait version, its Steering) once found
        self.seconds: float | None = None  # request to fan drawn, the last time
        self._asked = 0.0
        self.done = threading.Event()  # set when the last request's fan is drawn (or it said why not)
        self._cancelled = -1  # the gait version whose closed loop was cancelled
        self.bar = JobBar(controls.job, controls.status, self.cancel, tab.guarded)
        c, g = controls, tab.guarded
        c.enabled.on_update(g(lambda _e: self._toggled()))
        self.worker = LatestWorker(
            self._job,
            name=f"loop-{tab.client.client_id}",
            on_error=lambda exc: tab.report(f"closed loop: {exc}"),
        )

    @property
    def enabled(self) -> bool:
        return bool(self.controls.enabled.value)

    def steering_for(self, version: int):
        """The steering input found for gait ``version`` (``Steering``), or None if not (yet)."""
        found = self.found
        return found[1] if found is not None and found[0] == version else None

    def request(self, version: int, decoded, sim) -> None:
        """Play the replayed gait ``decoded`` closed loop (its open-loop replay ``sim``) if enabled."""
        self.version, self.report, self.seconds = version, None, None
        self._asked = time.perf_counter()
        self.done.clear()
        if not self.enabled:
            self.done.set()
            return
        self.bar.start("Finding the gait's steering input ...")
        self.worker.submit((version, decoded, sim))

    def cancel(self) -> None:
        """Stop this gait's closed-loop replays (the next gait's run as usual)."""
        self._cancelled = self.version
        self.bar.end(
            f"**Cancelled** after {time.perf_counter() - self._asked:.0f} s: this gait plays open loop here. "
            "The next gait is played closed loop again."
        )
        self.done.set()

    def _toggled(self) -> None:
        if self.enabled and self.tab.decoded is not None and self.tab.simulated is not None:
            self.request(self.tab.version, self.tab.decoded, self.tab.simulated)
        elif not self.enabled:
            self.tab.scene.draw_closed_loop([])
            self.bar.end("Closed loop is off: gaits play open loop.")

    def _job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, decoded, _sim = item
        tab = self.tab
        wanted = lambda: (  # noqa: E731
            tab.version == version and self.enabled and self._cancelled != version and not tab.closed.is_set()
        )
        simulator = tab.session.simulator_for(Turn.CLOSED_LOOP, wanted)
        try:
            steering = find_steering(decoded.commands, simulator, seconds=PROBE_SECONDS, check=False)
            if wanted():
                self.found = (version, steering)
            if not steering.steers:
                if wanted():
                    self.bar.end(f"**{steering.line()}**: this gait plays open loop.")
                    self.done.set()
                return
            if wanted():
                self.bar.show(
                    0.3, f"**{steering.line()}**; replaying it closed loop on 12 robots ...", force=True
                )
            reference, record = nominal_path(decoded.commands, simulator, steering.period)
            shown = self._shown_path(decoded, record, steering.period, simulator.excitation.sample_rate)
            if shown is not None:
                reference = shown
            report = closed_loop_robustness(decoded.commands, DEFAULT_SET, simulator, steering, reference)
        except Dropped:
            return
        except SimulationError as exc:
            if wanted():
                self.bar.end(f"**Closed loop failed**: {exc}")
                self.done.set()
            return
        if not wanted():
            return
        runs = report.pop("runs")
        p0, yaw0 = record[:2], float(record[2])
        c, s = math.cos(yaw0), math.sin(yaw0)
        to_start = np.array([[c, -s], [s, c]])  # rest frame -> the record's start frame (row vectors)
        paths = [(r.averaged - p0) @ to_start for r in runs]
        open_line = None
        if tab.variations is not None and tab.variations[0] == version:
            from snakeloco.sim.scores.robustness import readout_line

            open_line = readout_line(tab.variations[1]).removeprefix("on other robots: ")
        nominal = runs[0]
        times = nominal.times[::PLOT_STEP] - simulator.config.lead_in / simulator.excitation.sample_rate
        with tab.draw_lock:
            if not wanted():
                return
            self.report = report
            tab.scene.draw_closed_loop(paths)
            self.bar.end(loop_summary(report, open_line))
            set_plot_data(self.controls.plot, (times, nominal.steering[::PLOT_STEP]))
            self.seconds = time.perf_counter() - self._asked
        self.done.set()

    @staticmethod
    def _shown_path(decoded, record: np.ndarray, period: float, rate: float) -> np.ndarray | None:
        """The member's predicted path (the orange one) in the follower's frame, averaged over a wave
        period as the follower averages its pose; None for a gait without one."""
        if decoded.member is None or decoded.body_ds is None:
            return None
        body = np.asarray(decoded.body_ds, np.float64)  # (500, 6) at 5 Hz, the record's start frame
        t_ds = BODY_TIMES[: len(body)]
        t = np.arange(round(t_ds[-1] * rate) + 1) / rate
        xy = np.column_stack([np.interp(t, t_ds, body[:, 1]), np.interp(t, t_ds, body[:, 2])])
        yaw0 = float(record[2])
        c, s = math.cos(yaw0), math.sin(yaw0)
        rest = record[:2] + xy @ np.array([[c, s], [-s, c]])  # start frame -> rest frame
        w = max(1, round(period * rate))
        return trailing_mean(rest, w)[w - 1 :]

    def close(self) -> None:
        self.worker.close()
