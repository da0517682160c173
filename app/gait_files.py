"""A tab's gait files: Export CSV, Import CSV and the library Baseline (``DesignerClient`` mixes it in:
it uses the tab's current gait, its notifications and its physics worker)."""

from __future__ import annotations

from snakeloco.app.gait_csv import GaitCSVError, gait_comments, read_gait_csv, write_gait_csv
from snakeloco.sim.gaits import PRESETS as GAIT_PRESETS


class GaitFiles:
    """Export, import and library loading of ``DesignerClient`` (see there for the attributes used)."""

    def export_text(self) -> str:
        """The current gait as CSV text (what "Export CSV" downloads)."""
        if self.decoded is None:
            raise RuntimeError("no gait yet")
        comments = gait_comments(self.decoded, self.simulated, self.model.hash, self._programmatic_z)
        return write_gait_csv(self.decoded.commands, comments)

    def export(self) -> None:
        try:
            text = self.export_text()
        except RuntimeError as exc:
            self.client.add_notification("Export CSV", str(exc), color="yellow", auto_close_seconds=5.0)
            return
        self.client.send_file_download("snakeloco_gait.csv", text.encode(), save_immediately=True)

    def import_bytes(self, name: str, data: bytes) -> int | None:
        """Validate an uploaded gait and submit it for replay; returns the request version or None."""
        try:
            table = read_gait_csv(data)
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
        commands = GAIT_PRESETS[name].gait.commands()
        return self._submit(self.physics, ("load", f"library: {name}", f"Baseline: {name}", commands))

    def _on_upload(self) -> None:
        f = self.controls.import_button.value
        self.import_bytes(f.name, f.content)  # read_gait_csv refuses more than MAX_BYTES
