"""One browser tab of the designer: its state, its jobs (decode, replay, ensemble) and its callbacks.

Each tab gets a ``DesignerClient``: its own GUI (``gui``), scene (``scene``), ``GaitSession`` and two
``LatestWorker`` threads, one that decodes and one that runs physics. Slider events only *read* the
current slider values and submit them, so viser's thread pool may run callbacks in any order: the
newest submit always carries the newest values. Every request gets a version from one per-tab
counter; each worker runs only the newest request it holds, and nothing is drawn unless its version
is still the newest (a stale result is never drawn over a newer one). Decoding never waits for
physics: while a replay runs, new slider values are decoded and drawn at once, and the physics
worker moves on to the newest gait when its current run ends.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from collections.abc import Callable

import numpy as np
import viser

from snakeloco.app.designer import panel
from snakeloco.app.designer.design_panel import DesignPanel
from snakeloco.app.designer.fit_panel import FitPanel
from snakeloco.app.designer.gait_files import GaitFiles
from snakeloco.app.designer.ground import TabWorld
from snakeloco.app.designer.gui import NO_BASELINE, SLIDER_RANGE, WIDE_PX, build_controls
from snakeloco.app.designer.jobs import TabJobs
from snakeloco.app.designer.latent_moves import LatentMoves
from snakeloco.app.designer.loop_panel import LoopPanel
from snakeloco.app.designer.playback import PAUSE_WHEN_HIDDEN_JS, SOFTWARE_RENDERING_JS, Playback
from snakeloco.app.designer.readout import Readout, TabReadout
from snakeloco.app.designer.scene import END_SPREAD, TabScene
from snakeloco.app.designer.session import DecodedGait, GaitSession, Latents, SimulatedGait, Timing
from snakeloco.app.server.decode_process import DecodePool
from snakeloco.app.server.viser_patches import connection_closed, run_javascript
from snakeloco.app.server.workers import LatestWorker
from snakeloco.model.api import GaitModel
from snakeloco.sim import BODY_DOWNSAMPLE
from snakeloco.sim.physics.scheduler import FairPhysics
from snakeloco.sim.physics.simulator import Simulator
from snakeloco.sim.scores.consistency import ENSEMBLE_SIZE

PHYSICS_NICE = 10
"""Nice increment of the physics threads (``sim.physics.scheduler.FairPhysics``): below the server's own
threads, so decoding and drawing for every tab come first (docs/load.md, "PHYSICS_NICE")."""

FIRST_MOTION_THREADS_PER_CORE = 1
"""The server's first-motion threads (``FairPhysics(first_threads=...)``) per physics thread: held
first motions run alone there, not behind a replay's chunk (docs/load.md, "FIRST_MOTION_THREADS_PER_CORE")."""

FIRST_MOTION_NICE = 5
"""Nice increment of the first-motion threads: above the replays and ensembles, below decoding and
drawing (docs/load.md, "FIRST_MOTION_NICE")."""

TIMINGS_KEPT = 1000
"""Request timings a tab keeps (its newest; ``DesignerClient.timings``) for the benchmarks: more than
a drag phase sends (docs/load.md, "TIMINGS_KEPT")."""


class DesignerClient:
    """One browser tab: GUI, scene, session, its workers, and the parts it is composed of: ``jobs``
    (what the workers run), ``files`` (export, import, library), ``moves`` (latents moved from
    Python) and ``says`` (the readout), each holding the tab."""

    def __init__(
        self,
        client: viser.ClientHandle,
        model: GaitModel,
        ensemble: int = ENSEMBLE_SIZE,
        workers: int | None = None,
        on_error: Callable[[str], None] | None = None,
        simulator: Simulator | None = None,
        models: dict[str, GaitModel] | None = None,
        physics: FairPhysics | None = None,
        decoding: DecodePool | None = None,
        variations: bool = True,
        closed_loop: bool = True,
    ):
        self.client = client
        self.show_variations = variations
        """Replay each gait on the default physics variations after its ensemble (the Variations fan)."""
        self.decoding = decoding or DecodePool([], 0, processes=0)
        """The server's decode stage, shared by its tabs (``app.server.decode_process``): each decode takes a
        turn, in the order the tabs' values came, each tab's newest value when its turn comes, and
        runs in one of the server's decode processes, away from the server's GIL (else in this tab's
        decode worker, one at a time). A decode is a few milliseconds of Python and small torch calls
        that hand the GIL back and forth: 2-4 tabs decoding at once in the server's threads on 2
        cores took 31-49 ms each (p95, 8 tabs dragging) where one alone takes 8-10 (docs/load.md)."""
        self._on_error = on_error
        self.model = model
        self.models = models or {model.family: model}
        """The gait families this tab can switch between (the Gait family dropdown), by name."""
        family = next(name for name, m in self.models.items() if m is model)
        self.session = GaitSession(
            model,
            ensemble=ensemble,
            workers=workers,
            physics_nice=PHYSICS_NICE,
            simulator=simulator,
            physics=physics,
            tab=client.client_id,
        )
        self.decoded: DecodedGait | None = None
        self.simulated: SimulatedGait | None = None
        self.streaming = None  # the current gait's streamed replay so far (sim.StreamedReplay)
        self.readout: Readout | None = None  # what the readout says now (``TabReadout.show_readout``)
        self.variations: tuple[int, dict] | None = None  # (request version, its variations' report)
        self.predicted: tuple[int, dict] | None = None  # (request version, the physics head's report)
        self.jobs, self.files = TabJobs(self), GaitFiles(self)
        self.moves, self.says, self.world = LatentMoves(self), TabReadout(self), TabWorld(self)
        self.timings: deque[Timing] = deque(maxlen=TIMINGS_KEPT)
        self.values_received = 0  # slider values since the tab joined (all, not only those timed)
        self.views_drawn = 0  # decoded views drawn since the tab joined
        self.timing_by_version: dict[int, Timing] = {}
        self.draw_lock = threading.RLock()
        self.programmatic_z: tuple[float, ...] | None = None  # slider values set from Python
        self.shown_z: tuple[float, ...] | None = None  # the exact z_B they stand for
        self.z_lock = threading.RLock()
        self._setting_z = False
        self.quiet_zk = {"mode": 0, "seed": 0, "temperature": 0}  # z_k controls set by show_latents
        self.quiet_component_events = 0
        self.closed = threading.Event()
        self._version = 0
        self._version_lock = threading.Lock()
        self.controls = build_controls(
            client.gui,
            model.z_b_dim,
            tuple(self.models),
            family,
            self.moves.component_names(model),
            wide=client.camera.image_width >= WIDE_PX,
            n_joints=self.session.robot.n_joints,
            worlds=tuple(self.world.worlds),
            world=self.world.initial,
        )
        self.scene = TabScene(client, self.controls.layers, self.session.robot)
        self.world.show()
        self.scene.end_spread = END_SPREAD.get(model.family)
        self._wire()
        self.design = DesignPanel(self, self.controls.design)
        self.fit = FitPanel(self, self.controls.fit)
        self.loop = LoopPanel(self, self.controls.loop, enabled=closed_loop)
        report = lambda exc: self.report(f"{type(exc).__name__}: {exc}")  # noqa: E731
        self.decoder = LatestWorker(self.jobs.decode_job, name=f"decode-{client.client_id}", on_error=report)
        self.physics = LatestWorker(
            self.jobs.physics_job, name=f"physics-{client.client_id}", on_error=report
        )
        # Ensembles on a worker of their own: a new gait's replay starts at once instead of waiting
        # for the previous gait's ensemble batch (and the batches of other tabs queued before it).
        self.ensembles = LatestWorker(
            self.jobs.ensemble_job, name=f"ensemble-{client.client_id}", on_error=report
        )
        self.playback = Playback(
            self.controls,
            self.draw_snake,
            lambda: (self.simulated is not None or self.streaming is not None) and not self.page_left,
            self.closed,
            name=f"animate-{client.client_id}",
        )
        run_javascript(client, PAUSE_WHEN_HIDDEN_JS)
        run_javascript(client, SOFTWARE_RENDERING_JS)
        self.request_decode()

    @property
    def sliders(self) -> list[viser.GuiSliderHandle]:
        """The z_B sliders, one per latent dimension."""
        return self.controls.sliders

    def wire_sliders(self) -> None:
        c, g = self.controls, self.guarded
        for s in c.sliders:
            s.on_update(g(lambda _e: self._on_latents_changed()))
        if c.component is not None:
            c.component.on_update(g(lambda _e: self.moves.on_component_changed()))
        c.reset_button.on_click(g(lambda _e: self.set_z(np.zeros(self.model.z_b_dim))))
        c.random_button.on_click(g(lambda _e: self.moves.random_z()))

    def _wire(self) -> None:
        c, g = self.controls, self.guarded
        self.wire_sliders()
        c.family.on_update(g(lambda _e: self.moves.switch_family(c.family.value)))
        c.world.on_update(g(lambda _e: self.world.choose(c.world.value)))
        c.fan.on_update(g(lambda _e: self.world.choose_fan(c.fan.value)))
        c.zk_mode.on_update(g(lambda _e: self.moves.on_zk_changed("mode")))
        c.zk_seed.on_update(g(lambda _e: self.moves.on_zk_changed("seed")))
        c.zk_temperature.on_update(
            g(lambda _e: self.moves.on_zk_changed("temperature") if c.zk_mode.value == "sampled" else None)
        )
        c.resample_button.on_click(g(lambda _e: self._resample()))
        c.play_button.on_click(g(lambda _e: self.playback.toggle()))
        c.frame_button.on_click(g(lambda _e: self._frame(force=True)))
        c.scrubber.on_update(g(lambda event: self.playback.on_scrub(event)))
        for layer in c.layers.values():
            layer.on_update(g(lambda _e: self._apply_layers()))
        c.light.on_update(g(lambda _e: self._on_light_changed()))
        c.export_button.on_click(g(lambda _e: self.files.export()))
        c.robot_export_button.on_click(g(lambda _e: self.files.export_for_robot(c.robot_format.value)))
        c.share_button.on_click(g(lambda _e: self.files.share()))
        c.baseline.on_update(g(lambda _e: self.files.load_baseline(c.baseline.value)))
        c.import_button.on_upload(g(lambda _e: self.files.on_upload()))

    def report(self, message: str) -> None:
        if self._on_error is not None and not self.closed.is_set():  # not a gone tab's
            self._on_error(f"client {self.client.client_id}: {message}")

    def guarded(self, fn: Callable) -> Callable:
        """A GUI callback that reports instead of raising: one tab's error never reaches viser."""

        def run(event) -> None:
            try:
                fn(event)
            except Exception as exc:
                if self.closed.is_set():
                    return  # the tab went away mid-callback
                traceback.print_exc()
                self.report(f"{type(exc).__name__}: {exc}")

        return run

    # --- requests --------------------------------------------------------------------------------

    def current_latents(self) -> Latents:
        """Latents as the GUI shows them now: the sliders are z_B itself, or positions along the
        chosen cluster's axes (``model.heads.density``) that give z_B."""
        c = self.controls
        values = tuple(float(s.value) for s in c.sliders)
        z_b, component, axes = values, None, None
        density = self.model.config.density
        if density is not None and c.component is not None and c.component.value in density.names:
            component, axes = density.names.index(c.component.value), values
            z_b = tuple(float(v) for v in density.to_z(component, np.asarray(values)))
        return Latents(
            z_b=z_b,
            zk_mode=c.zk_mode.value,
            seed=int(c.zk_seed.value),
            temperature=float(c.zk_temperature.value),
            component=component,
            axes=axes,
        )

    def request_decode(self) -> int:
        """Submit the GUI's current latents (latest wins); returns the request version."""
        self.clear_baseline()
        return self.submit(self.decoder, self.current_latents())

    def clear_baseline(self) -> None:
        """The Baseline dropdown back to "none" once another gait replaces a library one, so that
        picking the library gait again loads it again (a dropdown fires only on a change)."""
        if self.controls.baseline.value != NO_BASELINE:
            self.controls.baseline.value = NO_BASELINE

    def submit(self, worker: LatestWorker, request: object) -> int:
        # Versions are taken and submitted under one lock, so workers always hold the newest request.
        with self._version_lock:
            self._version += 1
            self._record(self._version)
            worker.submit((self._version, request))
            return self._version

    @property
    def version(self) -> int:
        """This tab's newest request (a decode, a load); tests and benchmarks wait on it."""
        return self._version

    def is_current(self, version: int) -> bool:
        """Whether ``version`` is still this tab's newest request (only then may it be drawn)."""
        return version == self._version and not self.page_left

    @property
    def page_left(self) -> bool:
        """Whether this tab is closed or its page's connection is (viser closes the tab a moment after
        its connection): then nothing is drawn, as nothing would be delivered."""
        return self.closed.is_set() or connection_closed(self.client)

    def idle(self) -> bool:
        return self.decoder.idle() and self.physics.idle() and self.ensembles.idle()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until neither worker has work (for tests and benchmarks)."""
        deadline = time.monotonic() + timeout
        while True:
            for w in (self.decoder, self.physics, self.ensembles):
                if not w.wait_idle(max(deadline - time.monotonic(), 0.0)):
                    return False
            if self.idle():
                return True

    def _record(self, version: int) -> None:
        timing = Timing(version=version, submitted=time.perf_counter())
        self.values_received += 1
        if len(self.timings) == self.timings.maxlen:  # versions rise: the oldest leaves both
            self.timing_by_version.pop(self.timings[0].version, None)
        self.timing_by_version[version] = timing
        self.timings.append(timing)

    def _on_latents_changed(self) -> None:
        # Reading under the lock that _write_sliders holds: a callback never sees half-set sliders.
        with self.z_lock:
            if self._setting_z:
                return
            z = tuple(float(s.value) for s in self.sliders)
            if self.programmatic_z is not None and np.allclose(z, self.programmatic_z, atol=1e-9):
                return  # the sliders show an imported gait's encoding: keep that gait
            self.programmatic_z = None
        self.request_decode()

    def write_sliders(self, z: np.ndarray) -> tuple[float, ...]:
        values = tuple(float(v) for v in np.clip(np.round(z, 2), -SLIDER_RANGE, SLIDER_RANGE))
        with self.z_lock:
            self._setting_z = True
            try:
                with self.client.atomic():
                    for s, v in zip(self.sliders, values, strict=True):
                        s.value = v
            finally:
                self._setting_z = False
        return values

    def set_z(self, z: np.ndarray) -> None:
        """Move all sliders at once (Reset, Random) and decode once."""
        with self.z_lock:
            self.programmatic_z = None
            self.write_sliders(z)
        self.request_decode()

    def _resample(self) -> None:
        self.controls.zk_mode.value = "sampled"
        self.controls.zk_seed.value = int(self.controls.zk_seed.value) + 1

    def _apply_layers(self) -> None:
        with self.draw_lock, self.client.atomic():
            self.scene.apply_layers(simulated=self.simulated is not None)
        self.draw_snake()  # a snake whose layer was off was not posed meanwhile

    def _on_light_changed(self) -> None:
        """Light or full rendering; the shaded grid goes with it (off when light, back when full)."""
        light = bool(self.controls.light.value)
        with self.draw_lock, self.client.atomic():
            self.scene.set_light(light)
        self.controls.layers["Grid"].value = not light  # its own on_update applies the layers

    # --- drawing ---------------------------------------------------------------------------------

    def _frame(self, force: bool = False) -> None:
        with self.draw_lock:
            self.scene.frame(force=force)

    def draw_decoded(self, gait: DecodedGait) -> None:
        with self.client.atomic():
            self.scene.draw_decoded(gait)
            self.controls.show_paths(gait.body_ds, None)
            self.controls.show_commands(gait.commands)
            self.controls.panel.content = panel.decoded_text(gait)
            self.says.show_readout(gait, "simulating")
            if gait.body_ds is not None:
                self.scene.frame()
        self.client.flush()  # now, not at the end of viser's next 1/60 s window

    def draw_simulated(self, gait: DecodedGait, sim: SimulatedGait, ensemble: bool) -> None:
        with self.client.atomic():
            self.scene.draw_simulated(gait, sim, ensemble)
            if not ensemble:  # the ensemble's draw follows the replay's: the same two series
                self.controls.show_paths(gait.body_ds, sim.body[::BODY_DOWNSAMPLE])
                self.says.show_readout(gait, "done", sim.body)
                self.scene.frame()
            self.controls.panel.content = panel.simulated_text(gait, sim, ensemble)
        self.draw_snake()
        self.client.flush()

    def draw_snake(self, frame: int | None = None) -> None:
        """Pose the snake at record sample ``frame`` (default: the playback's) of the current replay
        (nothing once the page has left)."""
        motion = self.simulated if self.simulated is not None else self.streaming
        if motion is None or self.page_left:
            return
        frame = self.playback.frame if frame is None else frame
        qpos = motion.qpos
        if motion is self.streaming:  # physics is still filling in: hold the newest pose there is
            frame = min(frame, len(qpos) - 1)
        with self.draw_lock, self.client.atomic():
            self.scene.draw_snake(qpos[frame % len(qpos)], follow=self.controls.follow.value)

    def close(self) -> None:
        self.closed.set()
        self.design.close()
        self.fit.close()
        self.loop.close()
        self.decoder.close()
        self.physics.close()
        self.ensembles.close()
        self.session.close()
        self.playback.join()
