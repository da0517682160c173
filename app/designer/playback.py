"""A tab's snake animation: the replay played back at the record's rate on a thread of its own, with
Play/Pause, a playback speed and a time scrubber."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

from snakeloco.app.designer.gui import Controls
from snakeloco.app.designer.scene import LIGHT_RENDERING
from snakeloco.sim import RECORD

FRAME_HZ = 20.0
"""Snake poses sent per second while playing (the record's rate: one sample a frame at speed 1; 10 did
not make 3 tabs rendering in one software-WebGL Chromium answer key presses sooner, docs/load.md)."""
SCRUBBER_PERIOD_S = 0.5
"""How often the playing animation moves the time scrubber (the snake itself moves every frame)."""
PAUSED_WAIT_S = 1.0
"""A paused animation thread sleeps until played again, waking this often only to see whether its tab
has closed (docs/load.md, "PAUSED_WAIT_S")."""

PAUSE_WHEN_HIDDEN_JS = """
(() => {
  if (window.__snakelocoPauseWhenHidden) return;
  window.__snakelocoPauseWhenHidden = true;
  const button = (label) =>
    Array.from(document.querySelectorAll("button")).find((b) => b.textContent.trim() === label);
  let pausedByHiding = false;
  let pausedByUser = false;
  // The user's own Play/Pause clicks (trusted events; this script's clicks are not), seen before
  // the server's new label arrives: a Pause still shown a moment after the user pressed it must
  // not be pressed again by hiding the tab (that would toggle the animation back on).
  document.addEventListener("click", (event) => {
    if (!event.isTrusted) return;
    const b = event.target.closest && event.target.closest("button");
    const label = b ? b.textContent.trim() : "";
    if (label === "Pause") pausedByUser = true;
    else if (label === "Play") pausedByUser = false;
  }, true);
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) {
      const pause = button("Pause");
      if (pause && !pausedByUser && !pausedByHiding) { pause.click(); pausedByHiding = true; }
    } else if (pausedByHiding) {
      pausedByHiding = false;
      // The Play label may still be on its way from the server: look for it for up to 3 s.
      const resume = (left) => {
        if (document.hidden || pausedByUser) return;
        const play = button("Play");
        if (play) play.click();
        else if (left > 0) setTimeout(() => resume(left - 1), 100);
      };
      resume(30);
    }
  });
})();
"""
"""Sent to each page: while the tab is hidden (another browser tab in front, a minimised window)
the page presses Pause, and Play again when it is shown, so a hidden tab receives no poses. A
user's own Pause stays (the page only undoes the pause it made, and never presses Pause after the
user did, even while the button still shows the old label)."""

SOFTWARE_RENDERING_JS = """
(() => {
  if (window.__snakelocoLightChecked) return;
  window.__snakelocoLightChecked = true;
  let renderer = "";
  try {
    const gl = document.createElement("canvas").getContext("webgl");
    const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
    renderer = gl ? String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER)) : "";
    const lose = gl && gl.getExtension("WEBGL_lose_context");
    if (lose) lose.loseContext();
  } catch (e) { return; }
  if (!/swiftshader|llvmpipe|softpipe|software/i.test(renderer)) return;
  const label = __LABEL__;
  const tryCheck = (left) => {
    const box = Array.from(document.querySelectorAll("input[type=checkbox]")).find((input) => {
      for (let node = input.parentElement; node; node = node.parentElement) {
        if (node.textContent && node.textContent.trim() === label) return true;
        if (node.querySelectorAll("input[type=checkbox]").length > 1) return false;
      }
      return false;
    });
    if (box) { if (!box.checked) box.click(); }
    else if (left > 0) setTimeout(() => tryCheck(left - 1), 500);
  };
  tryCheck(120);
})();
""".replace("__LABEL__", json.dumps(LIGHT_RENDERING))
"""Sent to each page: where the page's WebGL renders in software (SwiftShader, llvmpipe: a
browser without a GPU, a remote desktop) it ticks "Light rendering" once, as soon as the control is
laid out (tried every 0.5 s for a minute). The user can untick it; the page never ticks it again."""


class Playback:
    """Which record sample the snake shows, advanced one sample per frame at speed 1 (20 Hz).

    ``draw(frame)`` poses the snake at a record sample; ``ready()`` says whether there is a replay to
    play, and a page to play it to. The thread stops when ``closed`` is set (``join`` waits for it).
    """

    def __init__(
        self,
        controls: Controls,
        draw: Callable[[int], None],
        ready: Callable[[], bool],
        closed: threading.Event,
        name: str,
    ) -> None:
        self.controls = controls
        self.frame = 0
        self._playing = True
        self._wake = threading.Event()  # set to wake a paused thread (played again, or closing)
        self._position = 0.0
        self._draw, self._ready, self.closed = draw, ready, closed
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def playing(self) -> bool:
        return self._playing

    @playing.setter
    def playing(self, value: bool) -> None:
        self._playing = bool(value)
        if value:
            self._wake.set()

    def toggle(self) -> None:
        """Play or pause."""
        self.playing = not self.playing
        self.controls.play_button.label = "Pause" if self.playing else "Play"

    def restart(self) -> None:
        """Back to t = 0 (a new replay starts streaming in)."""
        self.frame = 0
        self._position = 0.0

    def on_scrub(self, event) -> None:
        """Jump to the scrubber's time (a user's move; the animation's own updates are ignored)."""
        if event.client is None:
            return  # our own playback position updates
        self.frame = round(self.controls.scrubber.value * RECORD.sample_rate) % RECORD.n_samples
        self._position = float(self.frame)
        self._draw(self.frame)

    def _run(self) -> None:
        last_scrub = 0.0
        step = RECORD.sample_rate / FRAME_HZ  # record samples per frame at speed 1
        while not self.closed.is_set():
            if not self._playing:
                self._wake.wait(PAUSED_WAIT_S)
                self._wake.clear()  # then reads ``_playing`` again, which is set before the wake
                continue
            if self.closed.wait(1.0 / FRAME_HZ):
                return
            if not self.playing or not self._ready():
                continue
            try:
                self._position = (self._position + step * float(self.controls.speed.value)) % RECORD.n_samples
                self.frame = int(self._position)
                self._draw(self.frame)
                now = time.monotonic()
                if now - last_scrub > SCRUBBER_PERIOD_S:
                    self.controls.scrubber.value = round(self.frame / RECORD.sample_rate, 2)
                    last_scrub = now
            except Exception:  # the tab went away mid-update; the disconnect handler cleans up
                if self.closed.is_set():
                    return

    def join(self, timeout: float = 5.0) -> None:
        """Wait for the thread to end (after ``closed`` is set: a paused one is woken to see it)."""
        self._wake.set()
        self._thread.join(timeout=timeout)
