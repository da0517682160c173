"""A real browser (Debian chromium via Playwright) loads the designer, moves a slider, exports and imports.

Skipped with a reason where chromium or Playwright is missing; CI installs both so it runs there.
"""

from __future__ import annotations

import threading

import numpy as np

from snakeloco.app.bench.users.load_driver import CHROMIUM_ARGS, wait_until
from snakeloco.app.export.gait_csv import read_gait_csv
from snakeloco.sim.robot.description import DEFAULT_ROBOT

from helpers import BROWSER, designer_page

ARGS = CHROMIUM_ARGS
pytestmark = BROWSER


def test_browser_designs_exports_and_imports_a_gait(checkpoint, tmp_path):
    with designer_page(checkpoint, accept_downloads=True) as (sync_api, srv, page, d):
        assert d.wait_idle(90)
        # This Chromium renders WebGL in software (SwiftShader): the page ticks Light rendering.
        assert wait_until(lambda: d.controls.light.value is True, 30), "the page kept full rendering"
        assert d.controls.layers["Grid"].value is False
        box = page.get_by_role("checkbox", name="Light rendering")
        box.uncheck()  # a user who wants shadows back gets them, and the page leaves it so
        assert wait_until(lambda: d.controls.light.value is False and d.controls.layers["Grid"].value)
        page.wait_for_timeout(1500)
        assert d.controls.light.value is False and not box.is_checked()
        # Move the first z_B slider with the keyboard, as a person would.
        slider = page.get_by_role("slider").first
        slider.focus()
        for _ in range(25):
            slider.press("ArrowRight")
        assert wait_until(lambda: d.sliders[0].value > 0.2), "the slider move never reached the server"
        assert wait_until(lambda: d.idle() and d.decoded.latents.z_b[0] == d.sliders[0].value, 90)
        assert d.simulated is not None
        with page.expect_download(timeout=30000) as info:
            page.get_by_role("button", name="Export CSV").click()
        path = tmp_path / "gait.csv"
        info.value.save_as(path)
        text = path.read_text()
        z = d.decoded.latents.z_b
        assert f"# z_B: [{float(z[0])!r}" in text  # exactly, so that the import restores it
        table = read_gait_csv(text.encode(), robot=DEFAULT_ROBOT)
        np.testing.assert_array_equal(table.commands, d.decoded.commands)
        # Import it back through the upload button: the gait it was, its z_B decoded again.
        before = d.version
        page.locator("input[type=file]").first.set_input_files(str(path))
        assert wait_until(lambda: d.version > before and d.idle(), 90)
        assert d.decoded.source == "model" and d.decoded.latents.z_b == z
        np.testing.assert_array_equal(d.decoded.commands, table.commands)
        # An oversized upload is refused when it starts (nothing buffered) with a visible message,
        # and a malformed one after parsing; the imported gait stays in both cases.
        # (90 s: a busy 2-core machine with a software-rendered page behind was seen to take over 30 s)
        big = tmp_path / "big.csv"
        big.write_bytes(b"0" * (5 * 2**20))
        page.locator("input[type=file]").first.set_input_files(str(big))
        sync_api.expect(page.get_by_text("Import CSV: big.csv rejected")).to_be_visible(timeout=90000)
        assert not srv.server.gui._current_file_upload_states
        bad = tmp_path / "bad.csv"
        bad.write_text(path.read_text().replace("joint_8", "joint_9"))
        page.locator("input[type=file]").first.set_input_files(str(bad))
        sync_api.expect(page.get_by_text("Import CSV: bad.csv rejected")).to_be_visible(timeout=90000)
        assert d.idle() and d.decoded.source == "model" and d.decoded.latents.z_b == z
        np.testing.assert_array_equal(d.decoded.commands, table.commands)
        page.wait_for_timeout(1500)
        screenshot = tmp_path / "designer.png"  # under the test's own folder: nothing goes into the repo
        page.screenshot(path=str(screenshot))
        assert screenshot.read_bytes()[:4] == b"\x89PNG" and screenshot.stat().st_size > 10_000


def _set_hidden(page, hidden: bool) -> None:
    """What a browser does when its tab goes to the background (or comes back)."""
    state = "hidden" if hidden else "visible"
    page.evaluate(
        f"""() => {{
            Object.defineProperty(document, "hidden", {{value: {str(hidden).lower()}, configurable: true}});
            Object.defineProperty(document, "visibilityState", {{value: "{state}", configurable: true}});
            document.dispatchEvent(new Event("visibilitychange"));
        }}"""
    )


def _pause_then_hide_and_show(page, d, settle_ms: int) -> None:
    """The user presses Pause, the tab goes to the background for 0.3 s and comes back: still paused."""
    page.get_by_role("button", name="Pause").click()
    assert wait_until(lambda: not d.playback.playing, 30)
    _set_hidden(page, True)
    page.wait_for_timeout(300)
    _set_hidden(page, False)
    page.wait_for_timeout(settle_ms)
    assert not d.playback.playing, "hiding and showing the tab undid the user's pause"


def test_a_hidden_tab_pauses_its_animation_and_resumes_when_shown(checkpoint, monkeypatch):
    with designer_page(checkpoint) as (_sync_api, _srv, page, d):
        assert d.wait_idle(90) and d.playback.playing
        page.get_by_role("button", name="Pause").wait_for(timeout=30000)
        _set_hidden(page, True)
        assert wait_until(lambda: not d.playback.playing, 30), "hiding the tab did not pause it"
        frame = d.playback.frame
        page.wait_for_timeout(500)
        assert d.playback.frame == frame  # no poses while hidden
        _set_hidden(page, False)
        assert wait_until(lambda: d.playback.playing, 30), "showing the tab did not resume it"
        # A user's own pause survives hiding and showing the tab.
        _pause_then_hide_and_show(page, d, settle_ms=1000)
        # ... even when the tab is hidden before the button's new label has come back from the
        # server (a busy server or a slow network: here the label is sent 0.8 s late).
        page.get_by_role("button", name="Play").click()
        assert wait_until(lambda: d.playback.playing, 30)
        page.wait_for_timeout(300)
        playback = d.playback

        def toggle_with_late_label():
            playback.playing = not playback.playing
            label = "Pause" if playback.playing else "Play"
            threading.Timer(0.8, setattr, (playback.controls.play_button, "label", label)).start()

        monkeypatch.setattr(playback, "toggle", toggle_with_late_label)
        _pause_then_hide_and_show(page, d, settle_ms=2000)
        # A tab shown again before the hiding's Pause label arrived still resumes.
        page.get_by_role("button", name="Play").click()
        assert wait_until(lambda: d.playback.playing, 30)
        page.get_by_role("button", name="Pause").wait_for(timeout=30000)
        _set_hidden(page, True)
        assert wait_until(lambda: not d.playback.playing, 30)
        _set_hidden(page, False)
        assert wait_until(lambda: d.playback.playing, 30), "showing the tab did not resume it"
        page.wait_for_timeout(1000)  # the last late label is sent


def test_a_design_beside_the_ensemble_leaves_the_page_answering_and_cancels(checkpoint, tmp_path):
    """Issue 71: Design pressed while the ensemble runs; the page shows the bar, a slider move is
    drawn, Export CSV downloads and Cancel stops it, each within ANSWER_S on 2 cores. Screenshots of
    the bar, the cancelled line and a finished design's verdict go to $SNAKELOCO_SCREENSHOTS (else
    the test's own folder)."""
    import os
    from pathlib import Path

    from test_jobs import ANSWER_S, LONG

    from snakeloco.model.design.config import DesignConfig

    shots = Path(os.environ.get("SNAKELOCO_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    with designer_page(checkpoint, accept_downloads=True, server={"ensemble": 4}) as (sync_api, srv, page, d):
        d.design.config = LONG
        d.controls.design.forward.value, d.controls.design.sideways.value = 0.6, 0.2  # within reach
        page.get_by_text("Design for target").first.click()  # open the folder
        slider = page.get_by_role("slider").first
        slider.focus()
        for _ in range(5):
            slider.press("ArrowRight")
        assert wait_until(lambda: d.ensembles._busy, 60), "no ensemble ran"
        page.get_by_role("button", name="Design", exact=True).click()
        sync_api.expect(page.locator(".mantine-Progress-root")).to_be_visible(timeout=ANSWER_S * 1000)
        assert d.design.progress is not None
        page.wait_for_timeout(3000)
        page.screenshot(path=str(shots / "design-in-progress.png"))
        drawn = d.views_drawn
        slider.focus()
        for _ in range(3):
            slider.press("ArrowRight")
        assert wait_until(lambda: d.views_drawn > drawn, ANSWER_S), "the slider move went unanswered"
        with page.expect_download(timeout=ANSWER_S * 1000):
            page.get_by_role("button", name="Export CSV").click()
        page.get_by_role("button", name="Cancel").click()
        assert d.design.worker.wait_idle(ANSWER_S), "the design went on after Cancel"
        sync_api.expect(page.get_by_text("Cancelled after")).to_be_visible(timeout=ANSWER_S * 1000)
        sync_api.expect(page.locator(".mantine-Progress-root")).to_be_hidden(timeout=ANSWER_S * 1000)
        page.screenshot(path=str(shots / "design-cancelled.png"))
        d.design.config = DesignConfig(
            candidates=2, screen=32, starts=1, generations=4, population=6, rounds=2
        )
        page.get_by_role("button", name="Design", exact=True).click()
        assert d.design.worker.wait_idle(120) and d.design.result is not None
        sync_api.expect(page.get_by_text("rounds, search")).to_be_visible(timeout=ANSWER_S * 1000)
        page.wait_for_timeout(1000)
        page.screenshot(path=str(shots / "design-verdict.png"))
        assert srv.errors == []


def test_the_designer_draws_each_world_under_the_snake(checkpoint, tmp_path):
    """Issue 70: the page offers the World dropdown and draws rough ground, steps and pegs; screenshots
    of each go to $SNAKELOCO_SCREENSHOTS (else the test's own folder)."""
    import os
    from pathlib import Path

    from helpers import apply

    shots = Path(os.environ.get("SNAKELOCO_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    with designer_page(checkpoint) as (sync_api, _srv, page, d):
        sync_api.expect(page.locator("label").filter(has_text="World")).to_be_visible(timeout=30_000)
        for name in ("rough", "steps", "pegs"):
            assert apply(d, d.controls.world, name, 120), name
            assert d.scene.ground.mesh is not None and d.session.world.name == name
            d.scene.frame(force=True)
            page.wait_for_timeout(4000)  # software WebGL: a few frames
            page.screenshot(path=str(shots / f"world-{name}.png"))
            assert (shots / f"world-{name}.png").stat().st_size > 10_000
