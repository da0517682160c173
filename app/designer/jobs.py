"""A tab's jobs, a part ``DesignerClient`` holds (``tab.jobs``): decode -> draw | replay -> draw -> ensemble -> draw ->
variations -> draw.

Each job runs on its own ``LatestWorker`` thread with the version of the request it serves, and
draws only while that version is still the tab's newest (``is_current``), under the tab's draw lock.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator

import numpy as np

from snakeloco.app.designer import panel
from snakeloco.app.designer.readout import STREAM_READOUT_PERIOD_S
from snakeloco.app.designer.session import DecodedGait, SimulatedGait, Timing
from snakeloco.sim import SimulationError
from snakeloco.sim.physics.scheduler import Turn
from snakeloco.sim.robot.variations import DEFAULT_SET
from snakeloco.sim.scores.robustness import summarise
from snakeloco.sim.scores.terrain import WorldRow
from snakeloco.sim.world.sets import TERRAIN_SET

SETTLED_S = 0.5
"""A slider value the tab has held this long (no newer one) is one the user has let go of."""
HELD_S = 0.06
"""A slider value held this long (a dragged slider sends one every 50 ms) gets its first motion
before other tabs' settled replays; a younger one's after them (``sim.physics.scheduler.LANES``;
docs/load.md, "HELD_S")."""
STREAM_PATH_PERIOD_S = 0.25
"""How often a streaming replay's growing path is sent to the browser (the whole path is sent again
each time; the snake's pose goes every animation frame)."""


class TabJobs:
    """The jobs of a ``DesignerClient`` ``tab``: its decode, physics and ensemble workers run these."""

    def __init__(self, tab) -> None:
        self.tab = tab
        self._varied_robots: tuple | None = None  # (the session's robot, its variations of the default set)
        self._path_drawn = 0.0  # when a streaming replay's path was last sent
        self._readout_drawn = 0.0  # and its readout

    def _timing(self, version: int) -> Timing:
        return self.tab.timing_by_version.get(version) or Timing(version, time.perf_counter())

    def decode_job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, latents = item
        density = self.tab.model.config.density
        if (
            not self.tab.is_current(version)
            or len(latents.z_b) != self.tab.model.z_b_dim
            or (
                latents.component is not None and (density is None or latents.component >= len(density.names))
            )
        ):
            return  # superseded (or sliders of a family this tab has just left)
        with self.tab.decoding.turns:  # in the order the tabs' values came
            if not self.tab.is_current(version):
                return  # superseded while other tabs decoded: this worker has the newer value
            timing = self._timing(version)
            timing.started = time.perf_counter()
            decoded = self.tab.decoding.decode(self.tab.session.model.path, latents, self.tab.session.decode)
            decoded = self._on_session_robot(decoded)
            timing.decode_ms = decoded.decode_ms
        with self.tab.draw_lock:
            if not self.tab.is_current(version):
                return
            self.tab.decoded, self.tab.simulated, self.tab.streaming = decoded, None, None
            self.tab.draw_decoded(decoded)
            timing.decoded = time.perf_counter()
            self.tab.views_drawn += 1
            self.tab.physics.submit((version, ("gait", decoded)))
        self._predict_variations(version, decoded)

    def _on_session_robot(self, decoded: DecodedGait) -> DecodedGait:
        """A member's path on the robot the tab replays on, where that is not the checkpoint's and
        its physics head covers it (a fitted robot: ``serve --robot``); else ``decoded`` as it is."""
        robot = self.tab.session.robot
        if decoded.member is None or robot.mjcf_sha256 == self.tab.model.robot.mjcf_sha256:
            return decoded
        if not self.tab.model.members.covers(robot):
            return decoded
        body = self.tab.model.members.predict_variation_paths(decoded.member, [robot])[0]
        return dataclasses.replace(decoded, body_ds=body)

    def _predict_variations(self, version: int, decoded: DecodedGait) -> None:
        """Draw the physics head's predicted Variations fan and say its line (a checkpoint with a
        physics head, a gait that is a family member); the replays check it (``_variations``)."""
        if (
            not self.tab.show_variations
            or self.tab.world.terrain_fan  # the physics head predicts other robots, not other ground
            or decoded.member is None
            or self.tab.model.physics_head is None
        ):
            return
        robot = self.tab.session.robot
        if self._varied_robots is None or self._varied_robots[0] != robot:
            self._varied_robots = (robot, [v.apply(robot) for v in DEFAULT_SET])
        bodies = self.tab.model.members.predict_variation_paths(decoded.member, self._varied_robots[1])
        report = summarise(decoded.body_ds, DEFAULT_SET, list(bodies), [None] * len(bodies))
        with self.tab.draw_lock:
            if not self.tab.is_current(version):
                return
            self.tab.predicted = (version, report)
            with self.tab.client.atomic():
                self.tab.scene.draw_predicted_variations(bodies)
                if self.tab.simulated is None:  # a finished replay's readout says it when it is drawn
                    if self.tab.streaming is not None:
                        self.tab.says.show_readout(decoded, "streaming", self.tab.streaming.body)
                    else:
                        self.tab.says.show_readout(decoded, "simulating")

    def physics_job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, (kind, *payload) = item
        if not self.tab.is_current(version):
            return
        timing = self._timing(version)
        is_current = lambda: self.tab.is_current(version)  # noqa: E731
        if kind == "load":
            self.tab.files.load_job(*payload, timing, is_current)
        else:
            self._simulate(payload[0], timing, is_current)

    def _draw_part(self, part, timing: Timing, is_current) -> bool:
        """Draw a streamed replay's first samples: the snake moves from t = 0 at once, the simulated
        path grows. Returns whether the replay is still wanted (else it stops at this chunk)."""
        if not np.isfinite(timing.first_chunk):
            timing.first_chunk = time.perf_counter()
        with self.tab.draw_lock:
            if not is_current():
                return False
            first = self.tab.streaming is None
            self.tab.streaming = part
            now = time.perf_counter()
            if first or now - self._path_drawn > STREAM_PATH_PERIOD_S:  # the snake moves every frame
                self._path_drawn = now
                with self.tab.client.atomic():
                    self.tab.scene.draw_streaming(part.body, part.qpos[0])
            if (
                first or now - self._readout_drawn > STREAM_READOUT_PERIOD_S
            ) and self.tab.decoded is not None:
                self._readout_drawn = now
                self.tab.says.show_readout(self.tab.decoded, "streaming", part.body)
            if first:
                self.tab.playback.restart()
                self.tab.draw_snake(0)
                self.tab.client.flush()
                timing.first_motion = time.perf_counter()
        return True

    def _simulate(self, decoded: DecodedGait, timing: Timing, is_current) -> SimulatedGait | None:
        try:
            sim = self.tab.session.replay_streamed(
                decoded,
                lambda part: self._draw_part(part, timing, is_current),
                settled=lambda: time.perf_counter() - timing.submitted >= SETTLED_S,
                wanted=is_current,
                held_at=timing.submitted + HELD_S,
            )
        except SimulationError as exc:
            timing.failed = str(exc)
            with self.tab.draw_lock:
                if is_current():
                    self.tab.controls.panel.content = panel.failed_text(decoded, str(exc))
                    self.tab.says.show_readout(decoded, "failed", reason=str(exc))
                    self.tab.client.add_notification(
                        "Replay failed", str(exc), color="red", auto_close_seconds=8.0
                    )
            return None
        if sim is None:
            return None  # superseded mid-stream
        timing.replay_ms = sim.replay_ms
        with self.tab.draw_lock:
            if not is_current():
                return None
            self.tab.simulated, self.tab.streaming = sim, None
            self.tab.draw_simulated(decoded, sim, ensemble=False)
            timing.replayed = time.perf_counter()
            self.tab.ensembles.submit((timing.version, decoded, sim))
            self.tab.loop.request(timing.version, decoded, sim)
        return sim

    def ensemble_job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, decoded, sim = item
        if not self.tab.is_current(version):
            return
        timing = self._timing(version)
        is_current = lambda: self.tab.is_current(version)  # noqa: E731
        sim = self.tab.session.run_ensemble(
            decoded, sim, version, lambda b: self._draw_members(b, is_current), wanted=is_current
        )
        if sim is None:
            return  # superseded between batches, or while a batch waited for other tabs' batches
        timing.ensemble_ms = sim.ensemble_ms
        with self.tab.draw_lock:
            if not is_current():
                return
            self.tab.draw_simulated(decoded, sim, ensemble=True)
            timing.ensembled = time.perf_counter()
        if self.tab.show_variations:
            self._variations(version, decoded, sim, is_current)

    def _variations(self, version: int, decoded: DecodedGait, sim: SimulatedGait, is_current) -> dict | None:
        """Replay the gait on the default variation set (``sim.robot.variations``; or, with the fan over
        other ground, on each world of the terrain set, ``sim.world.sets``), a batch a physics thread at
        a time on the pool's variations turn (after every tab's replays and ensembles), drawing each
        batch as it comes (the Variations fan) and, at the end, the readout's line. Dropped unrun
        once the gait changes."""
        t0, terrain = time.perf_counter(), self.tab.world.terrain_fan
        rows, batches = self._fan(decoded, is_current, terrain)
        bodies, failures = [], []
        for result in batches:
            if result is None:
                return None
            bodies += list(result.body)
            failures += result.failures
            with self.tab.draw_lock:
                if not is_current():
                    return None
                with self.tab.client.atomic():
                    self.tab.scene.draw_variations(
                        [b for b, f in zip(result.body, result.failures, strict=True) if f is None]
                    )
        report = summarise(sim.body, rows, bodies, failures)
        report["seconds"] = time.perf_counter() - t0
        if terrain:
            report["set"] = "terrain"  # the readout says "on other ground"
        with self.tab.draw_lock:
            if not is_current():
                return None
            self.tab.variations = (version, report)
            self.tab.says.show_readout(decoded, "done", sim.body)
        return report

    def _fan(self, decoded: DecodedGait, is_current, terrain: bool) -> tuple[list, Iterator]:
        """The fan's rows (the physics variations, or with ``terrain`` the worlds) and its batches'
        results, simulated as they are read."""
        session, commands = self.tab.session, decoded.commands[None]
        if terrain:
            on = (session.simulator_on(w, Turn.VARIATIONS, is_current) for w in TERRAIN_SET)
            return [WorldRow(w) for w in TERRAIN_SET], (s.simulate(commands) for s in on)
        robots = [v.apply(session.robot) for v in DEFAULT_SET]
        simulator = session.simulator_for(Turn.VARIATIONS, is_current)
        parts = (robots[i : i + simulator.workers] for i in range(0, len(robots), simulator.workers))
        return list(DEFAULT_SET), (
            simulator.simulate(np.repeat(commands, len(p), 0), robots=p) for p in parts
        )

    def _draw_members(self, bodies: np.ndarray, is_current) -> bool:
        """Draw the ensemble members in so far; whether the ensemble is still wanted."""
        with self.tab.draw_lock:
            if not is_current():
                return False
            with self.tab.client.atomic():
                self.tab.scene.draw_fan(bodies)
        return True
