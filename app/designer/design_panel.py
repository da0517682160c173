"""A tab's "Design for target" panel: the target (number inputs, or a click on the ground), a marker
in the scene, the search on the tab's own design worker, and the verified candidates to pick from.

The search and its MuJoCo verification (``model.design.search``) run on a ``LatestWorker`` of the tab's own,
so the tab's sliders (decode worker) and other tabs stay responsive meanwhile. Its progress shows in a
bar (``job_bar``) with a Cancel button; a cancel, a new Design request or the tab's closing stops it:
the search at its next CMA-ES generation, its replays dropped from the physics pool row by row. Verification replays on the
tab's physics simulator (shared by a server's tabs, taking turns). Picking a candidate makes it the
current gait: decoded from its exact z_B (z_k = 0), the sliders moved there.
"""

from __future__ import annotations

import threading

import numpy as np

from snakeloco.app.designer.gui import NO_CANDIDATE, DesignControls
from snakeloco.app.designer.job_bar import JobBar
from snakeloco.app.server.workers import LatestWorker
from snakeloco.model.design.config import DesignConfig, Target
from snakeloco.model.design.robust import robust_design
from snakeloco.model.design.search import Candidate, design
from snakeloco.model.design.targets import DesignProgress
from snakeloco.sim.physics.backend import LocalBackend
from snakeloco.sim.physics.results import Dropped
from snakeloco.sim.physics.scheduler import Turn

MARKER_COLOR = (220, 30, 60)


def ground_point(origin, direction) -> tuple[float, float] | None:
    """Where a click's ray meets the ground plane z = 0 (the start frame's x, y), or None."""
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    if d[2] >= -1e-9:
        return None  # pointing at or above the horizon
    t = -o[2] / d[2]
    return float(o[0] + t * d[0]), float(o[1] + t * d[1])


def candidate_label(rank: int, c: Candidate) -> str:
    if c.simulated is None:
        return f"{rank}: replay broke"
    return f"{rank}: {c.error_m:.2f} m off (spread {c.spread_m:.2f} m)"


def robust_line(result) -> str:
    """What a robust design adds to its verdict: where candidate 1 ends on the other robots."""
    robust = result.extra.get("robust")
    if not robust:
        return ""
    r = robust[0]
    return (
        f"\n\n**On other robots** candidate 1 ends at most {r['worst_m']:.2f} m from the target (worst: "
        f"{r['worst_variation']}; p90 {r['p90_m']:.2f} m over {r['replayed']} variations, each replayed)."
    )


class DesignPanel:
    """Wires a tab's ``DesignControls``; ``tab`` is its ``DesignerClient``."""

    def __init__(self, tab, controls: DesignControls, config: DesignConfig | None = None) -> None:
        self.tab = tab
        self.controls = controls
        self.config = config or DesignConfig()
        self.candidates: list[Candidate] = []
        self.result = None
        self._version = 0
        self._shown: str | None = None  # the candidate the search's end made the gait (not re-picked)
        self._lock = threading.Lock()
        self.progress: DesignProgress | None = None  # the running design's
        self.bar = JobBar(controls.job, controls.status, self.cancel, tab.guarded)
        client = tab.client
        self.marker = client.scene.add_icosphere(
            "/design/target", radius=0.08, color=MARKER_COLOR, position=self._marker_position(), visible=False
        )
        c, g = controls, tab.guarded
        c.button.on_click(g(lambda _e: self.request()))
        for handle in (c.forward, c.sideways):
            handle.on_update(g(lambda _e: self._move_marker()))
        c.candidate.on_update(g(lambda _e: self.pick(c.candidate.value)))
        client.scene.on_click()(g(lambda event: self._on_click(event)))
        self.worker = LatestWorker(
            self._job, name=f"design-{client.client_id}", on_error=lambda exc: tab.report(f"design: {exc}")
        )

    # --- target ----------------------------------------------------------------------------------

    def target(self) -> Target:
        c = self.controls
        heading = float(c.heading.value) if c.use_heading.value else None
        return Target(forward=float(c.forward.value), sideways=float(c.sideways.value), heading=heading)

    def _marker_position(self) -> tuple[float, float, float]:
        return float(self.controls.forward.value), float(self.controls.sideways.value), 0.02

    def _move_marker(self) -> None:
        self.marker.position = self._marker_position()
        self.marker.visible = True

    def _on_click(self, event) -> None:
        point = ground_point(event.ray_origin, event.ray_direction)
        if point is None:
            return
        with self.tab.client.atomic():
            self.controls.forward.value = round(point[0], 2)
            self.controls.sideways.value = round(point[1], 2)
        self._move_marker()

    # --- the search ------------------------------------------------------------------------------

    def request(self) -> int:
        """Design for the current target on the design worker (a newer request supersedes it)."""
        try:
            target = self.target()
        except ValueError as exc:  # a NaN typed in
            self.controls.status.content = f"**Not a target**: {exc}"
            return self._version
        with self._lock:
            self._version += 1
            version = self._version
        self._move_marker()
        self.bar.start(
            f"Searching z_B for ({target.forward:.2f}, {target.sideways:.2f}) m"
            + (f", heading {target.heading:.0f} deg" if target.heading is not None else "")
            + " ..."
        )
        self.worker.submit((version, target))
        return version

    def cancel(self) -> None:
        """Stop the running design: its search at the next generation, its queued replays dropped."""
        with self._lock:
            self._version += 1
            running = self.progress
        if running is None:
            return
        self.bar.end(
            f"**Cancelled** after {running.seconds:.0f} s ({running.replays} replays run); the gait stays. "
            "Press **Design** to search again."
        )

    def _current(self, version: int) -> bool:
        return version == self._version and not self.tab.closed.is_set()

    def _job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, target = item
        if not self._current(version):
            return
        stopped = lambda: not self._current(version)  # noqa: E731

        def show(p: DesignProgress) -> None:
            if not stopped():
                self.bar.show(p.fraction, p.line())

        self.progress = progress = DesignProgress(show)
        # Each replay row is dropped (``Dropped`` raised) once the design is cancelled, superseded
        # or its tab closed: nothing of it keeps the physics pool busy.
        simulator = self.tab.session.simulator_for(Turn.DESIGN, lambda: not stopped(), raises=True)
        runner = LocalBackend.on(simulator)
        search = robust_design if self.controls.robust.value else design
        try:
            result = search(
                self.tab.model, target, self.config, runner=runner, cancelled=stopped, progress=progress
            )
        except Dropped:
            return  # cancel() or the newer request has said so
        finally:
            if self.progress is progress:
                self.progress = None
        if stopped():
            return
        if not result.candidates:
            self.bar.end("**Not met**: no candidate could be verified")
            return
        self.result, self.candidates = result, result.candidates
        labels = tuple(candidate_label(i + 1, c) for i, c in enumerate(self.candidates))
        best = self.candidates[0]
        if (far := result.extra.get("beyond_reach")) is not None and best.simulated is not None:
            verdict = (
                f"**Beyond reach**: the target is {far['distance_m']:.3g} m away; this family's gaits end at most "
                f"{far['reach_m']:.1f} m from the start. Its nearest gait ends at ({best.simulated[0]:.2f}, "
                f"{best.simulated[1]:.2f}) m"
            )
        else:  # the criterion that decided it first: "**Not met on other robots**: worst ..."
            head, _, rest = result.verdict().partition(": ")
            verdict = f"**{head[0].upper()}{head[1:]}**: {rest}"
        with self.tab.client.atomic():
            self.bar.end(
                f"{verdict} ({result.rounds} rounds, search "
                f"{result.search_s:.1f} s, physics {result.physics_s:.1f} s for {result.replays} replays). "
                "Spread: where physics itself scatters the end." + robust_line(result)
            )
            self.controls.candidate.options = (NO_CANDIDATE, *labels)
        # The best candidate becomes the current gait at once (the others stay in the dropdown): a
        # finished design left the scene on the old gait and the dropdown at "none yet".
        if self._current(version) and best.simulated is not None:
            self.pick(labels[0], shown=True)
            self.controls.candidate.value = labels[0]  # its callback finds it picked already

    def pick(self, label: str, shown: bool = False) -> int | None:
        """Make the candidate named by ``label`` (the dropdown's) the current gait; its request version
        (None where it is no candidate, or the one the search's end has just shown: ``shown``)."""
        labels = [candidate_label(i + 1, c) for i, c in enumerate(self.candidates)]
        if label not in labels or (not shown and label == self._shown):
            return None
        self._shown = label if shown else None
        return self.tab.moves.show_latents(self.candidates[labels.index(label)].z_b)

    def forget(self) -> None:
        """Drop the candidates (of a model the tab has just left) and stop a running search."""
        with self._lock:
            self._version += 1
        self.candidates, self.result = [], None
        with self.tab.client.atomic():
            self.controls.candidate.options = (NO_CANDIDATE,)
            self.bar.end("Set a target (or click the ground), then press **Design**.")

    def close(self) -> None:
        self.worker.close()
