"""A tab's "Your robot" folder: import a measured run of the current gait, draw it beside the model's and
MuJoCo's paths, fit the robot's physics to it (``sim.fit.fit_robot``) as the tab's lowest-priority physics job,
and offer the fitted robot for the tab's replays.

The fit runs on a ``LatestWorker`` of the panel's own, its progress in a bar with a Cancel button
(``job_bar``); its replays take the physics pool's last turn (``Turn.FIT``: after every tab's replays,
ensembles, variations and design) and are dropped, ending the fit, when it is cancelled, the tab's
gait changes or the tab closes. Choosing a robot in the Robot dropdown replays the current gait
on it; the readout then says that the model was trained on the nominal robot.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import viser

from snakeloco.app.designer.job_bar import JobBar, JobControls, build_job_controls
from snakeloco.app.server.workers import LatestWorker
from snakeloco.sim.fit.fit_robot import FitCancelled, FitConfig, fit_robot
from snakeloco.sim.fit.measured import MeasuredRun, MeasuredRunError, read_measured_run
from snakeloco.sim.physics.scheduler import Turn
from snakeloco.sim.robot.description import Robot

MEASURED_COLOR = (190, 30, 160)
"""The measured run's path (magenta): beside the model's orange, MuJoCo's blue and the fan's grey."""
NOMINAL = "nominal"


@dataclass
class FitControls:
    measured_button: viser.GuiUploadButtonHandle
    fit_button: viser.GuiButtonHandle
    robot: viser.GuiDropdownHandle
    status: viser.GuiMarkdownHandle
    job: JobControls


def build_fit_controls(gui: viser.GuiApi) -> FitControls:
    with gui.add_folder("Your robot", expand_by_default=False):
        measured = gui.add_upload_button(
            "Import measured run",
            mime_type=".csv,text/csv,text/plain",
            hint="A run of the current gait on your robot: time_s,x,y,yaw (m, rad) from motion capture or "
            "odometry (docs/calibration.md); drawn in magenta",
        )
        fit = gui.add_button(
            "Fit physics",
            hint="Fit floor friction along and across and servo kp so that MuJoCo's replay follows the measured "
            "run (minutes; the tab's last physics job)",
        )
        robot = gui.add_dropdown(
            "Robot",
            (NOMINAL,),
            initial_value=NOMINAL,
            hint="The robot this tab replays on: nominal or fitted",
        )
        status = gui.add_markdown("Import a measured run of the current gait, then **Fit physics**.")
        job = build_job_controls(gui, "fit")
    return FitControls(measured, fit, robot, status, job)


def fit_summary(report: dict) -> str:
    """The fit's outcome as markdown: each field with its interval, and the path error before and after."""
    rows = ["| field | fitted | interval | determined |", "|---|---|---|---|"]
    for name, p in report["params"].items():
        interval = f"{p['low']:.3g}-{p['high']:.3g}" if np.isfinite(p["high"]) else "unbounded"
        rows.append(f"| {name} | {p['fitted']:.3g} | {interval} | {'yes' if p['determined'] else 'no'} |")
    b, a = report["before"][0], report["after"][0]
    err = lambda e: "broke" if e.get("broke") else f"{e['end_m']:.2f} m"  # noqa: E731
    return (
        f"**Fitted** in {report['seconds']:.0f} s ({report['replays']} replays): end-point error "
        f"{err(b)} on the nominal robot, {err(a)} on the fitted one.\n\n" + "\n".join(rows)
    )


class FitPanel:
    """Wires a tab's ``FitControls``; ``tab`` is its ``DesignerClient``."""

    def __init__(self, tab, controls: FitControls, config: FitConfig | None = None) -> None:
        self.tab, self.controls, self.config = tab, controls, config or FitConfig()
        self.run: MeasuredRun | None = None
        self.commands: np.ndarray | None = None  # the gait the run ran (the tab's when imported)
        self.robots: dict[str, Robot] = {NOMINAL: tab.session.nominal_robot}
        self.report: dict | None = None
        self._version = 0
        self._lock = threading.Lock()
        self.line = None
        self._started: float | None = None  # the running fit's start (perf_counter)
        self.bar = JobBar(controls.job, controls.status, self.cancel, tab.guarded)
        c, g = controls, tab.guarded
        c.measured_button.on_upload(g(lambda _e: self._on_upload()))
        c.fit_button.on_click(g(lambda _e: self.request()))
        c.robot.on_update(g(lambda _e: self.choose(c.robot.value)))
        self.worker = LatestWorker(
            self._job, name=f"fit-{tab.client.client_id}", on_error=lambda exc: tab.report(f"fit: {exc}")
        )

    def _on_upload(self) -> None:
        f = self.controls.measured_button.value
        self.import_bytes(f.name, f.content)

    def import_bytes(self, name: str, data: bytes) -> MeasuredRun | None:
        """Read a measured run of the tab's current gait and draw it; None (and a notification saying
        why) for a file that is no run."""
        gait = self.tab.decoded
        if gait is None:
            return None
        try:
            run = read_measured_run(data.decode("utf-8-sig"), name, gait.commands.shape[1])
        except (MeasuredRunError, UnicodeDecodeError) as exc:
            self.tab.client.add_notification(
                f"Import measured run: {name} rejected", str(exc), color="red", auto_close_seconds=15.0
            )
            return None
        self.run, self.commands = run, gait.commands.copy()
        z0 = float(self.tab.scene.start[0][2])
        points = np.column_stack([run.xy, np.full(len(run.xy), z0)]).astype(np.float32)
        segments = np.stack([points[:-1], points[1:]], axis=1)
        self.line = self.tab.client.scene.add_line_segments(
            "/measured", segments, MEASURED_COLOR, thickness=3.0, thickness_units="screen"
        )
        self.controls.status.content = (
            f"**Measured run** {name} (magenta): {run.distance:.2f} m in {run.duration:.0f} s, paired with "
            "the current gait. **Fit physics** fits the robot to it."
        )
        return run

    def request(self) -> int | None:
        """Fit on the panel's worker (a newer request supersedes it); None without a measured run."""
        if self.run is None:
            self.controls.status.content = "Import a measured run first: the fit needs where the robot went."
            return None
        with self._lock:
            self._version += 1
            version = self._version
        self.bar.start("Fitting: the first generation of candidate robots is replaying ...")
        self.worker.submit((version, self.tab.version, self.commands, self.run))
        return version

    def cancel(self) -> None:
        """Stop the running fit: its queued replays are dropped, the robots offered stay."""
        with self._lock:
            self._version += 1
            started = self._started
        if started is not None:
            self.bar.end(
                f"**Cancelled** after {time.perf_counter() - started:.0f} s. **Fit physics** starts again."
            )

    def _job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, gait_version, commands, run = item
        current = lambda: version == self._version and not self.tab.closed.is_set()  # noqa: E731
        wanted = lambda: current() and self.tab.version == gait_version  # noqa: E731
        simulator = self.tab.session.simulator_for(Turn.FIT, wanted)
        done = [0]
        self._started = t0 = time.perf_counter()

        def progress(k: int) -> None:
            done[0] += k
            if current():
                g = self.config.generations
                self.bar.show(
                    done[0] / g, f"Fitting: generation {done[0]} of {g}, {time.perf_counter() - t0:.0f} s ..."
                )

        try:
            report = fit_robot(
                [(commands, run)], self.tab.session.nominal_robot, self.config, simulator, progress
            )
        except FitCancelled:
            if current():
                self.bar.end("The fit stopped: the gait changed. Import the run again to fit.")
            return
        except MeasuredRunError as exc:
            if current():
                self.bar.end(f"**Cannot fit**: {exc}")
            return
        finally:
            self._started = None
        if not current():
            return
        self.report = report
        label = f"fitted to {run.source}"
        self.robots[label] = report["robot"]
        with self.tab.client.atomic():
            self.bar.end(fit_summary(report))
            self.controls.robot.options = tuple(self.robots)
        self.tab.client.add_notification(
            "Fit physics", f"Choose '{label}' in Robot to replay on the fitted robot.", auto_close_seconds=8.0
        )

    def choose(self, label: str) -> int | None:
        """Replay the current gait on the robot named ``label``; its request version."""
        robot = self.robots.get(label)
        if robot is None or robot == self.tab.session.robot or self.tab.decoded is None:
            return None
        self.tab.session.set_robot(robot)
        gait = self.tab.decoded
        if gait.latents is not None:  # the model's gait: decoded again, its path kept, replayed here
            return self.tab.request_decode()
        return self.tab.submit(
            self.tab.physics, ("load", gait.source, f"Robot: {label}", gait.commands, gait.no_model)
        )

    def robot_changed(self) -> None:
        """The tab now designs for another robot (a family trained on it): the Robot dropdown offers
        its nominal robot and the fitted robots of its joints only; a measured run of the old robot's
        gait is dropped."""
        nominal = self.tab.session.nominal_robot
        keep = {
            label: r
            for label, r in self.robots.items()
            if label != NOMINAL and (r.n_joints, r.joint_pattern) == (nominal.n_joints, nominal.joint_pattern)
        }
        self.robots = {NOMINAL: nominal, **keep}
        self.controls.robot.options = tuple(self.robots)
        self.controls.robot.value = NOMINAL
        if self.commands is not None and self.commands.shape[1] != nominal.n_joints:
            self.run = self.commands = None

    def close(self) -> None:
        self.worker.close()
