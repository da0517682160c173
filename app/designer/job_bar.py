"""A tab's long job on screen: a progress bar with what the job is doing and its best so far, and a
**Cancel** button, under the panel's status line (the design and fit panels each hold one).

The bar is hidden while no job runs. Updates are sent at most every ``UPDATE_PERIOD_S`` (a design
reports every replay batch; the browser needs no more), the first and the last at once.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import viser

UPDATE_PERIOD_S = 0.3
"""How often a running job's bar and line are sent to the browser."""


@dataclass
class JobControls:
    bar: viser.GuiProgressBarHandle
    cancel: viser.GuiButtonHandle


def build_job_controls(gui: viser.GuiApi, what: str) -> JobControls:
    """The bar and Cancel button of a panel's job (hidden until one runs); ``what``: the job, for the hint."""
    bar = gui.add_progress_bar(0.0, visible=False, animated=True)
    cancel = gui.add_button(
        "Cancel", visible=False, color="red", hint=f"Stop the running {what} and its replays (the gait stays)"
    )
    return JobControls(bar, cancel)


class JobBar:
    """Shows one job at a time: ``start`` it, ``show`` its progress, ``end`` it with a status line.
    ``status`` is the panel's markdown line; ``on_cancel`` runs when Cancel is pressed."""

    def __init__(
        self, controls: JobControls, status: viser.GuiMarkdownHandle, on_cancel: Callable[[], None], guard
    ) -> None:
        self.controls, self.status = controls, status
        self._lock = threading.Lock()
        self._shown = 0.0
        self.running = False
        controls.cancel.on_click(guard(lambda _e: on_cancel()))

    def start(self, line: str) -> None:
        with self._lock:
            self.running, self._shown = True, time.perf_counter()
            self.controls.bar.value = 0.0
            self.controls.bar.visible = self.controls.cancel.visible = True
            self.status.content = line

    def show(self, fraction: float, line: str, force: bool = False) -> None:
        """The running job is ``fraction`` done (0-1) and doing what ``line`` says (sent at most every
        ``UPDATE_PERIOD_S`` unless ``force``)."""
        with self._lock:
            now = time.perf_counter()
            if not self.running or (not force and now - self._shown < UPDATE_PERIOD_S):
                return
            self._shown = now
            self.controls.bar.value = round(100.0 * min(max(fraction, 0.0), 1.0), 1)
            self.status.content = line

    def end(self, line: str | None = None) -> None:
        """The job is over (finished, failed or cancelled): bar and button hidden, ``line`` said."""
        with self._lock:
            self.running = False
            self.controls.bar.visible = self.controls.cancel.visible = False
            if line is not None:
                self.status.content = line
