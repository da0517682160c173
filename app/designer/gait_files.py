"""A tab's gait files: Export CSV, Import CSV and the library Baseline, and the physics job that loads
such a gait: a part ``DesignerClient`` holds (``tab.files``), reading the tab's current gait and
session and submitting to its physics worker."""

from __future__ import annotations

import time

import numpy as np

from snakeloco.app.designer.session import DecodedGait, Latents, Timing, decode_latents
from snakeloco.app.export.gait_csv import (
    STEERING_KEY,
    GaitCSVError,
    gait_comments,
    read_gait_csv,
    write_gait_csv,
)
from snakeloco.sim import SimulationError, joint_shape
from snakeloco.sim.gaits.library import PRESETS as GAIT_PRESETS


class GaitFiles:
    """Export, import and library loading of a ``DesignerClient`` ``tab``."""

    def __init__(self, tab) -> None:
        self.tab = tab

    def export_text(self) -> str:
        """The current gait as CSV text (what "Export CSV" downloads)."""
        if self.tab.decoded is None:
            raise RuntimeError("no gait yet")
        encoded = self.tab.shown_z if self.tab.programmatic_z is not None else None
        comments = gait_comments(self.tab.decoded, self.tab.simulated, self.tab.model.hash, encoded)
        if (
            steering := self.tab.loop.steering_for(self.tab.version)
        ) is not None:  # found for this gait: kept with it
            comments[STEERING_KEY] = steering.model_dump_json()
        return write_gait_csv(self.tab.decoded.commands, comments, self.tab.session.robot)

    def export(self) -> None:
        try:
            text = self.export_text()
        except RuntimeError as exc:
            self.tab.client.add_notification("Export CSV", str(exc), color="yellow", auto_close_seconds=5.0)
            return
        self.tab.client.send_file_download("snakeloco_gait.csv", text.encode(), save_immediately=True)

    def export_for_robot(self, label: str) -> tuple[str, bytes] | None:
        """Download the current gait in a robot format (``ROBOT_FORMATS[label]``); returns (file name,
        bytes), or None after a notification saying why not (no gait, a limit, no parameters)."""
        from snakeloco.app.export.formats import ROBOT_FORMATS, ExportError, export_gait

        fmt, ext, options = ROBOT_FORMATS[label]
        try:
            body, _ = export_gait(
                self.export_text(), fmt, self.tab.session.robot, source="designer", **options
            )
        except (RuntimeError, ExportError, GaitCSVError) as exc:
            self.tab.client.add_notification(
                f"Export for robot: {label}", str(exc), color="yellow", auto_close_seconds=10.0
            )
            return None
        name = f"snakeloco_gait_{fmt}.{ext}"
        self.tab.client.send_file_download(name, body.encode(), save_immediately=True)
        return name, body.encode()

    def share(self) -> tuple[str, bytes] | None:
        """Download the current replay as a page that plays with no server (``app.export.share``); None with
        a notification where there is no replay yet."""
        from snakeloco.app.export.share import record_html

        gait, sim = self.tab.decoded, self.tab.simulated
        if gait is None or sim is None or sim.error is not None:
            self.tab.client.add_notification(
                "Share",
                "wait for the MuJoCo replay: the page plays it",
                color="yellow",
                auto_close_seconds=5.0,
            )
            return None
        model_body = None if gait.latents is None else gait.body_ds
        title = gait.member.describe() if getattr(gait, "member", None) is not None else gait.source
        html, _ = record_html(
            sim.body, sim.qpos, list(sim.ensemble_body[1:]), self.tab.session.robot, model_body, title
        )
        self.tab.client.send_file_download("snakeloco_replay.html", html.encode(), save_immediately=True)
        return "snakeloco_replay.html", html.encode()

    def import_bytes(self, name: str, data: bytes) -> int | None:
        """Validate an uploaded gait and submit it for replay; returns the request version or None."""
        try:
            table = read_gait_csv(data, self.tab.session.robot)
        except GaitCSVError as exc:
            self.tab.client.add_notification(
                f"Import CSV: {name} rejected",
                f"{exc}. The current gait stays.",
                color="red",
                auto_close_seconds=15.0,
            )
            return None
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
        restored, why = self._restore_export(text, table.commands)
        if restored is not None:
            self.tab.client.add_notification(
                f"Import CSV: {name}",
                "Restored as exported: its z_B (the sliders), the model's path and the readout.",
                auto_close_seconds=5.0,
            )
            return restored
        self.tab.clear_baseline()
        no_model = f"none: {why}; its commands are replayed as written"
        return self.tab.submit(
            self.tab.physics, ("load", f"import: {name}", f"Import CSV: {name}", table.commands, no_model)
        )

    def _restore_export(self, text: str, commands: np.ndarray) -> tuple[int | None, str]:
        """Show a file Export CSV wrote from this tab's checkpoint as the gait it was: its z_B and z_k
        decoded again, where that gives the file's very commands (the request version); else None and
        why the file has no model path."""
        from snakeloco.app.export.gait_csv import exported_latents

        found, why = exported_latents(text)
        if found is None:
            return None, why
        if found["checkpoint"] != self.tab.model.hash:
            return None, (
                f"exported from another checkpoint (sha256 {str(found['checkpoint'])[:12]}; this family's is "
                f"{self.tab.model.hash[:12]})"
            )
        if len(found["z_b"]) != self.tab.model.z_b_dim:
            return None, f"its z_B has {len(found['z_b'])} values, this family's {self.tab.model.z_b_dim}"
        z_b = np.asarray(found["z_b"])
        latents = Latents(
            found["z_b"], found["zk_mode"], found["seed"], found["temperature"], *self.tab.moves.axes_of(z_b)
        )
        if not np.array_equal(decode_latents(self.tab.model, latents).commands, commands):
            return None, "its commands are not what this checkpoint decodes at its z_B (edited after export?)"
        return self.tab.moves.show_latents(z_b, found["zk_mode"], found["seed"], found["temperature"]), ""

    def load_baseline(self, name: str) -> int | None:
        """Make the library gait ``name`` (``sim.gaits.library.PRESETS``) the current gait: replayed, drawn,
        exportable, the sliders where it encodes. Returns the request version (None for "none")."""
        if name not in GAIT_PRESETS:
            return None
        robot = self.tab.session.robot
        commands = GAIT_PRESETS[name].gait.on_robot(robot).commands(robot)
        no_model = "none: a library gait (gait-equation parameters), not the model's"
        return self.tab.submit(
            self.tab.physics, ("load", f"library: {name}", f"Baseline: {name}", commands, no_model)
        )

    def on_upload(self) -> None:
        f = self.tab.controls.import_button.value
        self.import_bytes(f.name, f.content)  # read_gait_csv refuses more than MAX_BYTES

    def load_job(
        self, source: str, title: str, commands: np.ndarray, no_model: str, timing: Timing, is_current
    ) -> None:
        """Replay given commands (an imported CSV, a library gait) as the current gait, with the
        sliders moved to where it encodes; ``title`` heads its notifications, ``no_model`` says why
        it has no model path."""
        shape = joint_shape(commands)
        gait = DecodedGait(None, shape, None, commands, 0.0, source=source, no_model=no_model)
        try:
            sim = self.tab.session.replay(gait)
        except SimulationError as exc:
            timing.failed = str(exc)
            self.tab.client.add_notification(
                f"{title} not loaded", f"Its replay broke: {exc}. The current gait stays.", color="red"
            )
            return
        z_b = self.tab.session.encode_replay(sim)
        with self.tab.draw_lock:
            if not is_current():
                return
            self.tab.decoded, self.tab.simulated = gait, sim
            self.tab.draw_decoded(gait)
            self.tab.draw_simulated(gait, sim, ensemble=False)
            with self.tab.z_lock:
                self.tab.programmatic_z = self.tab.moves.write_z(z_b)
                self.tab.shown_z = tuple(float(v) for v in z_b)
            timing.replayed = time.perf_counter()
            self.tab.loop.request(timing.version, gait, sim)
        sim = self.tab.session.run_ensemble(gait, sim, seed=timing.version)
        with self.tab.draw_lock:
            if is_current():
                self.tab.draw_simulated(gait, sim, ensemble=True)
                timing.ensembled = time.perf_counter()
                self.tab.client.add_notification(
                    title, "Replayed; the sliders show where it sits in z_B.", auto_close_seconds=5.0
                )
