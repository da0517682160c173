"""Screenshots of the designer's first screen as a new user sees it: ``python -m
snakeloco.app.bench.screens OUT_DIR`` (Debian chromium, 1500x950, software WebGL).

For each shipped gait family: the first load, after a slider drag, after the replay finished, and
with a failed replay (a decoded gait whose commands are swapped for a square wave that throws the
snake, as the failed-replay test does). Files: ``OUT_DIR/{family}-{state}.jpg``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from snakeloco.app.bench.users.load_driver import CHROMIUM, CHROMIUM_ARGS, wait_until
from snakeloco.app.server.lifecycle import DesignerServer
from snakeloco.sim import RECORD

VIEWPORT = {"width": 1500, "height": 950}
STATES = ("load", "drag", "replayed", "failed")


def square_wave() -> np.ndarray:
    """Commands (2000, 8) rad that throw the snake into the air: every joint +/-2.2 rad at 2 Hz."""
    t = RECORD.times[:, None]
    return 2.2 * np.sign(np.sin(2 * np.pi * 2.0 * t + np.arange(8)))


def shoot_family(family: str, out: Path, timeout: float = 600.0) -> list[Path]:
    """The four screenshots of one gait family's tab; returns their paths."""
    from playwright.sync_api import sync_playwright

    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    srv = DesignerServer(port=0, checkpoint=family, verbose=False)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(f"http://127.0.0.1:{srv.port}")
            assert wait_until(lambda: len(srv.clients) == 1, 60), "the page never connected"
            d = next(iter(srv.clients.values()))

            def snap(state: str) -> None:
                page.wait_for_timeout(2500)  # let the page draw what arrived
                path = out / f"{family}-{state}.jpg"
                page.screenshot(path=str(path), type="jpeg", quality=80)
                paths.append(path)

            assert d.wait_idle(timeout)
            snap("load")
            slider = page.get_by_role("slider").first
            slider.focus()
            for _ in range(150):  # a drag to the slider's right half, a key press at a time
                slider.press("ArrowRight")
            assert wait_until(lambda: d.sliders[0].value >= 1.0, 60)
            time.sleep(0.3)
            snap("drag")
            assert d.wait_idle(timeout)
            snap("replayed")
            decode = d.session.decode

            def decode_to_wild(latents):
                gait = decode(latents)
                gait.commands = square_wave()
                return gait

            d.session.decode = decode_to_wild
            d.sliders[1].value = 0.5
            time.sleep(0.3)
            assert d.wait_idle(timeout)
            snap("failed")
            browser.close()
    finally:
        srv.stop()
    return paths


def shoot(out: Path, families: tuple[str, ...] = ("structured", "paper")) -> list[Path]:
    """The screenshots of every family in ``families``."""
    return [path for family in families for path in shoot_family(family, out)]


if __name__ == "__main__":
    for p in shoot(Path(sys.argv[1] if len(sys.argv) > 1 else "static/screens")):
        print(p)
