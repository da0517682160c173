"""A newcomer's path through the designer (issue 59) in one Chromium page at 1500x950: first load, a
slider drag, the family switch, a cluster change, an import of the exported gait and a finished
design, each a screenshot (JPEG) with whether both paths' ends are on the canvas, in OUT/report.json.

    python -m snakeloco.app.bench.newcomer_screens static/screens/newcomer

The same path on an older main (the "before" of docs/first-screen.md: the first load on that main's
default family, the switch to the other one), run as a file so that ``snakeloco`` is that tree:

    git worktree add /tmp/old fe669c1 && mkdir -p /tmp/oldpath && ln -s /tmp/old /tmp/oldpath/snakeloco
    PYTHONPATH=/tmp/oldpath python app/bench/newcomer_screens.py static/screens/newcomer-before

With a checkpoint (a build's ``runs/NAME/model``), the designer of that robot instead: its first
load and a replay after z_B 1 moved to 2 (``robot_screens``):

    python -m snakeloco.app.bench.newcomer_screens static/screens/twelve runs/twelve/model
"""

from __future__ import annotations

import io
import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image

from snakeloco.app.bench.users.load_driver import CHROMIUM, CHROMIUM_ARGS, wait_until
from snakeloco.app.designer.view import in_view
from snakeloco.app.server.lifecycle import DesignerServer

try:
    from snakeloco.app.designer.scene_geometry import path_points
except ImportError:  # a main before the scene's geometry had a module of its own
    from snakeloco.app.designer.scene import path_points

W, H = 1500, 950


def ends_seen(d) -> tuple[bool, int]:
    """Whether the model's and MuJoCo's path ends are both inside the camera's image, and how many."""
    cam = d.client.camera
    pts = []
    if d.decoded is not None and d.decoded.body_ds is not None:
        pts.append(path_points(d.decoded.body_ds, 0.0)[-1])
    if d.simulated is not None:
        pts.append(path_points(d.simulated.body, 0.0)[-1])
    inside = in_view(np.array(pts), cam.position, cam.look_at, cam.fov, cam.aspect)
    return bool(inside.all()), len(pts)


def _shot(page, d, out: Path, name: str, report: dict) -> None:
    """Screenshot ``page`` into OUT/NAME.jpg and note whether both paths' ends are on its canvas."""
    time.sleep(2.5)  # the camera's move and the last frames drawn
    Image.open(io.BytesIO(page.screenshot())).convert("RGB").save(out / f"{name}.jpg", quality=80)
    inside, n = ends_seen(d)
    report[name] = {"path_ends_in_canvas": inside, "paths": n, "family": d.model.family}
    print(name, report[name], flush=True)


@contextmanager
def designer_page(srv, idle_s: float):
    """One Chromium page at W x H on ``srv`` and its tab once idle (within ``idle_s``); stops ``srv``."""
    from playwright.sync_api import sync_playwright

    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = b.new_page(viewport={"width": W, "height": H})
            page.goto(f"http://127.0.0.1:{srv.port}")
            assert wait_until(lambda: len(srv.clients) == 1, 60)
            d = next(iter(srv.clients.values()))
            assert d.wait_idle(idle_s)
            yield page, d
    finally:
        srv.stop()


def robot_screens(out: Path, checkpoint: Path) -> dict:
    """The designer on ``checkpoint``'s robot: first load, then z_B 1 at 2 replayed (ensemble in)."""
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    srv = DesignerServer(port=0, checkpoint=checkpoint, ensemble=8, workers=2, verbose=False)
    with designer_page(srv, 400) as (page, d):  # 400 s: replay, ensemble and the Variations fan
        _shot(page, d, out, "1-first-load", report)
        report["first_load"] = {"gait": d.readout.gait, "gap_m": d.readout.gap_m}
        d.sliders[0].value = 2.0
        assert wait_until(
            lambda: d.idle() and d.decoded.latents is not None and d.decoded.latents.axes[0] == 2.0, 400
        )
        _shot(page, d, out, "2-replayed", report)
        report["robot"] = d.session.robot.model_dump(mode="json")
        r = d.readout
        report["readout"] = {
            "model": r.model.__dict__ if r.model else None,
            "mujoco": r.mujoco.__dict__ if r.mujoco else None,
            "gap_m": r.gap_m,
            "gait": r.gait,
        }
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return report


def main(out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {}

    def shot(page, d, name: str) -> None:
        _shot(page, d, out, name, report)

    import inspect

    # (a main before the Variations fan has no such option, and no fan)
    fan = {"variations": False} if "variations" in inspect.signature(DesignerServer).parameters else {}
    srv = DesignerServer(port=0, ensemble=2, workers=2, verbose=False, **fan)
    with designer_page(srv, 120) as (page, d):
        shot(page, d, "1-first-load")
        d.sliders[0].value = 2.0
        assert wait_until(
            lambda: d.idle() and d.decoded.latents is not None and d.decoded.latents.axes[0] == 2.0, 120
        )
        shot(page, d, "2-drag")
        exported = d.files.export_text()
        first = d.model.family  # the default family; the newcomer tries the other one, then back
        other = "paper" if first == "structured" else "structured"
        d.controls.family.value = other
        assert wait_until(lambda: d.model.family == other and d.idle() and d.simulated is not None, 120)
        shot(page, d, f"3-family-{other}")
        d.controls.family.value = "structured"
        assert wait_until(lambda: d.model.family == "structured" and d.idle(), 120)
        d.controls.component.value = d.model.config.density.names[4]
        time.sleep(1)
        assert wait_until(lambda: d.idle() and d.simulated is not None, 120)
        shot(page, d, "4-cluster")
        d.files.import_bytes("exported.csv", exported.encode())
        time.sleep(1)
        assert wait_until(lambda: d.idle() and d.simulated is not None, 120)
        shot(page, d, "5-import")
        dc = d.controls.design
        dc.forward.value, dc.sideways.value = 3.0, 2.0
        time.sleep(0.5)
        d.design.request()
        assert d.design.worker.wait_idle(400) and wait_until(lambda: d.idle(), 120)
        shot(page, d, "6-design-finished")
        report["design_status"] = dc.status.content
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    robot_screens(Path(sys.argv[1]), Path(sys.argv[2])) if len(sys.argv) > 2 else main(Path(sys.argv[1]))
