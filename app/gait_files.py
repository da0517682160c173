"""A tab's gait files: Export CSV, Import CSV and the library Baseline, and the physics job that loads
such a gait (``DesignerClient`` mixes it in: it uses the tab's current gait, its notifications, its
session and its physics worker)."""

from __future__ import annotations

import time

import numpy as np

from snakeloco.app.gait_csv import GaitCSVError, gait_comments, read_gait_csv, write_gait_csv
from snakeloco.app.session import DecodedGait, Timing
from snakeloco.sim import SimulationError, joint_shape
from snakeloco.sim.gaits import PRESETS as GAIT_PRESETS


class GaitFiles:
    """Export, import and library loading of ``DesignerClient`` (see there for the attributes used)."""

    def export_text(self) -> str:
        """The current gait as CSV text (what "Export CSV" downloads)."""
        if self.decoded is None:
            raise RuntimeError("no gait yet")
        encoded = self._shown_z if self._programmatic_z is not None else None
        comments = gait_comments(self.decoded, self.simulated, self.model.hash, encoded)
        return write_gait_csv(self.decoded.commands, comments, self.session.robot)

    def export(self) -> None:
        try:
            text = self.export_text()
        except RuntimeError as exc:
            self.client.add_notification("Export CSV", str(exc), color="yellow", auto_close_seconds=5.0)
            return
        self.client.send_file_download("snakeloco_gait.csv", text.encode(), save_immediately=True)

    def export_for_robot(self, label: str) -> tuple[str, bytes] | None:
        """Download the current gait in a robot format (``ROBOT_FORMATS[label]``); returns (file name,
        bytes), or None after a notification saying why not (no gait, a limit, no parameters)."""
        from snakeloco.app.export import ROBOT_FORMATS, ExportError, export_gait

        fmt, ext, options = ROBOT_FORMATS[label]
        try:
            body, _ = export_gait(self.export_text(), fmt, self.session.robot, source="designer", **options)
        except (RuntimeError, ExportError, GaitCSVError) as exc:
            self.client.add_notification(
                f"Export for robot: {label}", str(exc), color="yellow", auto_close_seconds=10.0
            )
            return None
        name = f"snakeloco_gait_{fmt}.{ext}"
        self.client.send_file_download(name, body.encode(), save_immediately=True)
        return name, body.encode()

    def share(self) -> tuple[str, bytes] | None:
        """Download the current replay as a page that plays with no server (``app.share``); None with
        a notification where there is no replay yet."""
        from snakeloco.app.share import record_html

        gait, sim = self.decoded, self.simulated
        if gait is None or sim is None or sim.error is not None:
            self.client.add_notification(
                "Share",
                "wait for the MuJoCo replay: the page plays it",
                color="yellow",
                auto_close_seconds=5.0,
            )
            return None
        model_body = None if gait.latents is None else gait.body_ds
        title = gait.member.describe() if getattr(gait, "member", None) is not None else gait.source
        html, _ = record_html(
            sim.body, sim.qpos, list(sim.ensemble_body[1:]), self.session.robot, model_body, title
        )
        self.client.send_file_download("snakeloco_replay.html", html.encode(), save_immediately=True)
        return "snakeloco_replay.html", html.encode()

    def import_bytes(self, name: str, data: bytes) -> int | None:
        """Validate an uploaded gait and submit it for replay; returns the request version or None."""
        try:
            table = read_gait_csv(data, self.session.robot)
        except GaitCSVError as exc:
            self.client.add_notification(
                f"Import CSV: {name} rejected",
                f"{exc}. The current gait stays.",
                color="red",
                auto_close_seconds=15.0,
            )
            return None
        self._clear_baseline()
        return self._submit(self.physics, ("load", f"import: {name}", f"Import CSV: {name}", table.commands))

    def load_baseline(self, name: str) -> int | None:
        """Make the library gait ``name`` (``sim.gaits.PRESETS``) the current gait: replayed, drawn,
        exportable, the sliders where it encodes. Returns the request version (None for "none")."""
        if name not in GAIT_PRESETS:
            return None
        robot = self.session.robot
        commands = GAIT_PRESETS[name].gait.on_robot(robot).commands(robot)
        return self._submit(self.physics, ("load", f"library: {name}", f"Baseline: {name}", commands))

    def _on_upload(self) -> None:
        f = self.controls.import_button.value
        self.import_bytes(f.name, f.content)  # read_gait_csv refuses more than MAX_BYTES

    def _load_job(self, source: str, title: str, commands: np.ndarray, timing: Timing, is_current) -> None:
        """Replay given commands (an imported CSV, a library gait) as the current gait, with the
        sliders moved to where it encodes; ``title`` heads its notifications."""
        shape = joint_shape(commands)
        gait = DecodedGait(None, shape, None, commands, 0.0, source=source)
        try:
            sim = self.session.replay(gait)
        except SimulationError as exc:
            timing.failed = str(exc)
            self.client.add_notification(
                f"{title} not loaded", f"Its replay broke: {exc}. The current gait stays.", color="red"
            )
            return
        z_b = self.session.encode_replay(sim)
        with self._draw_lock:
            if not is_current():
                return
            self.decoded, self.simulated = gait, sim
            self._draw_decoded(gait)
            self._draw_simulated(gait, sim, ensemble=False)
            with self._z_lock:
                self._programmatic_z = self._write_z(z_b)
                self._shown_z = tuple(float(v) for v in z_b)
            timing.replayed = time.perf_counter()
        sim = self.session.run_ensemble(gait, sim, seed=timing.version)
        with self._draw_lock:
            if is_current():
                self._draw_simulated(gait, sim, ensemble=True)
                timing.ensembled = time.perf_counter()
                self.client.add_notification(
                    title, "Replayed; the sliders show where it sits in z_B.", auto_close_seconds=5.0
                )
