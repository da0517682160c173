"""``snakeloco serve``: the browser designer on viser.

Each browser tab gets a ``DesignerClient``: its own GUI, scene, ``GaitSession`` and two
``LatestWorker`` threads, one that decodes and one that runs physics. Slider events only *read* the
current slider values and submit them, so viser's thread pool may run callbacks in any order: the
newest submit always carries the newest values. Every request gets a version from one per-client
counter; each worker runs only the newest request it holds, and nothing is drawn unless its version
is still the newest (a stale result is never drawn over a newer one). Decoding never waits for
physics: while a replay runs, new slider values are decoded and drawn at once, and the physics
worker (at a lower OS priority) moves on to the newest gait when its current run ends.

Scene frame: the snake's initial heading frame (x forward, y left, z up; metres), the frame the body
channels are expressed in, so decoded and simulated paths start at the origin heading +x.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch
import trimesh
import viser
import viser.uplot as uplot

from app.gait_csv import MAX_BYTES, GaitCSVError, read_gait_csv, write_gait_csv
from app.session import DecodedGait, GaitSession, Latents, LatestWorker, SimulatedGait
from model.api import GaitModel, load_pretrained
from sim import LINK_RADIUS, SimulationError, joint_shape, load_model
from sim.physics import Simulator

HELP_PATH = Path(__file__).resolve().parent / "help.md"
"""The Help panel's text; package data, so a non-editable install shows it too."""
SLIDER_RANGE = 3.0
"""Sliders span +/- 3 prior standard deviations of z_B ~ N(0, I)."""
JOINT_COLORS = np.array(
    [
        [228, 26, 28],
        [55, 126, 184],
        [77, 175, 74],
        [152, 78, 163],
        [255, 127, 0],
        [166, 86, 40],
        [247, 129, 191],
        [90, 90, 90],
    ],
    dtype=np.uint8,
)
GEN_COLOR = (255, 140, 0)
SIM_COLOR = (30, 100, 220)
FAN_COLOR = (150, 150, 150)
SHAPE_SCALE = 1.5
"""Point-cloud metres per radian of FFT coefficient."""
JOINT_SPACING = 0.12
"""Point-cloud height step between joints (m)."""
FPS = 20.0
DECODE_THREADS = 1
"""torch intra-op threads of a designer server process. Four threads decoding at once on 2 cores:
p50 21-23 ms per decode with 1 intra-op thread, 21-31 ms with 2 (two runs each)."""
SWITCH_INTERVAL_S = 0.001
"""Python's GIL switch interval in a designer server (default 0.005 s)."""
PHYSICS_NICE = 15
"""Nice increment of the native threads that run a tab's rollouts (its Python threads stay at the
server's priority, so a niced thread never holds the GIL that slider decoding waits for)."""


def _help_text() -> str:
    return HELP_PATH.read_text(encoding="utf-8")


def _polyline(points: np.ndarray) -> np.ndarray:
    """(N, 3) points -> (N-1, 2, 3) segments for add_line_segments."""
    return np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)


def _path_points(body: np.ndarray, z0: float) -> np.ndarray:
    """Body channels (T, 6) -> (T, 3) scene points (forward, sideways, height)."""
    return np.stack([body[:, 1], body[:, 2], body[:, 0] + z0], axis=-1)


def _shape_points(shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint shape (8, L, 2) -> points (8 L, 3) = (real, imag, joint height) and per-joint colours."""
    k = np.repeat(np.arange(shape.shape[0]), shape.shape[1])
    pts = np.stack(
        [SHAPE_SCALE * shape[..., 0].ravel(), SHAPE_SCALE * shape[..., 1].ravel(), JOINT_SPACING * (k + 1)],
        -1,
    )
    return pts.astype(np.float32), JOINT_COLORS[k]


def _spread_text(std: float, relative: float) -> str:
    """An ensemble's spread of one statistic for the panel: its std in the statistic's units and,
    where the ensemble's mean is a meaningful scale (larger than the spread), relative to it. A net
    roll that goes either way across the ensemble has a mean near 0: its relative spread (e.g. ±15 rad
    about a mean of 1.9, 789%) says nothing the std does not."""
    text = f"±{std:.2g}"
    return text + (f" ({100 * relative:.1f}%)" if relative < 1.0 else "")


@dataclass
class Timing:
    """When each stage of one request finished (perf_counter seconds), for ``bench app``."""

    version: int
    submitted: float
    started: float = float("nan")  # the decode worker picked the request up
    decoded: float = float("nan")
    replayed: float = float("nan")
    ensembled: float = float("nan")
    decode_ms: float = float("nan")
    replay_ms: float = float("nan")
    ensemble_ms: float = float("nan")
    failed: str | None = None


class DesignerClient:
    """One browser tab: GUI, scene, session, a decode worker and a physics worker."""

    def __init__(
        self,
        client: viser.ClientHandle,
        model: GaitModel,
        ensemble: int = 8,
        workers: int | None = None,
        on_error: Callable[[str], None] | None = None,
        simulator: Simulator | None = None,
    ):
        self.client = client
        self._on_error = on_error
        self.model = model
        self.session = GaitSession(
            model, ensemble=ensemble, workers=workers, physics_nice=PHYSICS_NICE, simulator=simulator
        )
        self.decoded: DecodedGait | None = None
        self.simulated: SimulatedGait | None = None
        self.timings: deque[Timing] = deque(maxlen=2000)
        self._timing_by_version: dict[int, Timing] = {}
        self._draw_lock = threading.RLock()
        self._programmatic_z: tuple[float, ...] | None = None
        self._z_lock = threading.RLock()
        self._setting_z = False
        self._kin_model = load_model()
        self._kin_data = mujoco.MjData(self._kin_model)
        self._link_geoms = [self._kin_model.geom(f"link{i}").id for i in range(1, 10)]
        self._origin = (np.zeros(3), 0.0)  # replay's initial body position and yaw (world)
        self._frame = 0
        self._position = 0.0
        self._playing = True
        self._closed = threading.Event()
        self._version = 0
        self._version_lock = threading.Lock()
        self._build_gui()
        self._build_scene()
        report = lambda exc: self._report(f"{type(exc).__name__}: {exc}")  # noqa: E731
        self.decoder = LatestWorker(self._decode_job, name=f"decode-{client.client_id}", on_error=report)
        self.physics = LatestWorker(self._physics_job, name=f"physics-{client.client_id}", on_error=report)
        self._animator = threading.Thread(
            target=self._animate, name=f"animate-{client.client_id}", daemon=True
        )
        self._animator.start()
        self.request_decode()

    # --- GUI -------------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.client.gui
        with gui.add_folder("Body latent z_B"):
            self.sliders = [
                gui.add_slider(
                    f"z_B {i + 1}",
                    -SLIDER_RANGE,
                    SLIDER_RANGE,
                    0.01,
                    0.0,
                    hint=f"Body latent dimension {i + 1}",
                )
                for i in range(self.model.z_b_dim)
            ]
            self.reset_button = gui.add_button("Reset z_B", hint="All z_B to 0 (the prior mean)")
            self.random_button = gui.add_button("Random z_B", hint="Draw z_B from its N(0, I) prior")
        with gui.add_folder("Joint latents z_k"):
            self.zk_mode = gui.add_dropdown("z_k mode", ("zero", "sampled"), initial_value="zero")
            self.zk_seed = gui.add_number("z_k seed", 0, min=0, step=1)
            self.zk_temperature = gui.add_slider("Temperature", 0.0, 2.0, 0.05, 1.0)
            self.resample_button = gui.add_button(
                "Resample z_k", hint="New seed for the sampled joint latents"
            )
        with gui.add_folder("Playback"):
            self.play_button = gui.add_button("Pause")
            self.speed = gui.add_slider("Speed", 0.25, 8.0, 0.25, 1.0, hint="Playback speed (x real time)")
            self.scrubber = gui.add_slider("Time (s)", 0.0, 99.95, 0.05, 0.0)
        with gui.add_folder("Layers"):
            self.layers = {
                name: gui.add_checkbox(name, True)
                for name in (
                    "Snake",
                    "Generated path",
                    "Simulated path",
                    "Ensemble fan",
                    "Joint shapes",
                    "Grid",
                )
            }
        with gui.add_folder("Gait file"):
            self.export_button = gui.add_button(
                "Export CSV", hint="Download the current gait (2000 rows, 20 Hz, rad)"
            )
            self.import_button = gui.add_upload_button("Import CSV", mime_type=".csv,text/csv,text/plain")
        with gui.add_folder("Consistency"):
            self.panel = gui.add_markdown("Decoding...")
        with gui.add_folder("Plots", expand_by_default=False):
            no_time = {"x": {"time": False}}
            t = np.arange(500) / 5.0
            nan = np.full(500, np.nan)
            self.plots = {}
            for name in ("forward (m)", "sideways (m)", "yaw (rad)"):
                self.plots[name] = gui.add_uplot(
                    data=(t, nan, nan),
                    series=(
                        uplot.Series(label="t (s)"),
                        uplot.Series(label="generated", stroke="darkorange", width=2),
                        uplot.Series(label="simulated", stroke="royalblue", width=2),
                    ),
                    scales=no_time,
                    title=name,
                    aspect=2.0,
                )
            t20 = np.arange(2000) / 20.0
            self.plots["commands"] = gui.add_uplot(
                data=(t20, *[np.zeros(2000)] * 8),
                series=(
                    uplot.Series(label="t (s)"),
                    *[
                        uplot.Series(
                            label=f"joint {k + 1}",
                            stroke="#{:02x}{:02x}{:02x}".format(*tuple(JOINT_COLORS[k])),
                            width=1,
                        )
                        for k in range(8)
                    ],
                ),
                scales=no_time,
                title="joint commands (rad)",
                aspect=1.5,
            )
        with gui.add_folder("Help", expand_by_default=False):
            gui.add_markdown(_help_text())

        g = self._guarded
        for s in self.sliders:
            s.on_update(g(lambda _e: self._on_latents_changed()))
        self.zk_mode.on_update(g(lambda _e: self.request_decode()))
        self.zk_seed.on_update(g(lambda _e: self.request_decode()))
        self.zk_temperature.on_update(
            g(lambda _e: self.request_decode() if self.zk_mode.value == "sampled" else None)
        )
        self.resample_button.on_click(g(lambda _e: self._resample()))
        self.reset_button.on_click(g(lambda _e: self._set_z(np.zeros(self.model.z_b_dim))))
        self.random_button.on_click(
            g(lambda _e: self._set_z(np.random.default_rng().standard_normal(self.model.z_b_dim)))
        )
        self.play_button.on_click(g(lambda _e: self._toggle_play()))
        self.scrubber.on_update(g(self._on_scrub))
        for layer in self.layers.values():
            layer.on_update(g(lambda _e: self._apply_layers()))
        self.export_button.on_click(g(lambda _e: self.export()))
        self.import_button.on_upload(g(lambda _e: self._on_upload()))

    def _report(self, message: str) -> None:
        if self._on_error is not None:
            self._on_error(f"client {self.client.client_id}: {message}")

    def _guarded(self, fn: Callable) -> Callable:
        """A GUI callback that reports instead of raising: one tab's error never reaches viser."""

        def run(event) -> None:
            try:
                fn(event)
            except Exception as exc:
                if self._closed.is_set():
                    return  # the tab went away mid-callback
                traceback.print_exc()
                self._report(f"{type(exc).__name__}: {exc}")

        return run

    def _build_scene(self) -> None:
        scene = self.client.scene
        self.grid = scene.add_grid("/grid", 20.0, 20.0, cell_size=0.1, section_size=1.0)
        capsule = trimesh.creation.capsule(height=0.1, radius=LINK_RADIUS, count=[12, 12])
        capsule.visual.vertex_colors = np.array([217, 140, 51, 255], dtype=np.uint8)
        self.snake = scene.add_batched_meshes_trimesh(
            "/snake",
            capsule,
            batched_wxyzs=np.tile([1.0, 0, 0, 0], (9, 1)),
            batched_positions=np.zeros((9, 3)),
        )
        self.gen_path = None
        self.sim_path = None
        self.fan = None
        scene.add_label("/shapes/decoded/label", "decoded joint shape", position=(0, 0, 1.15))
        scene.add_label("/shapes/measured/label", "re-measured joint shape", position=(0, 0, 1.15))
        self.shape_frames = {
            "decoded": scene.add_frame(
                "/shapes/decoded", position=(-1.5, 1.0, 0.0), show_axes=True, axes_length=0.3
            ),
            "measured": scene.add_frame(
                "/shapes/measured", position=(-1.5, -1.0, 0.0), show_axes=True, axes_length=0.3
            ),
        }
        self.clouds: dict[str, viser.PointCloudHandle] = {}
        self.client.camera.position = (-2.5, -3.5, 2.5)
        self.client.camera.look_at = (0.5, 0.0, 0.0)

    # --- requests --------------------------------------------------------------------------------

    def current_latents(self) -> Latents:
        """Latents as the GUI shows them now."""
        return Latents(
            z_b=tuple(float(s.value) for s in self.sliders),
            zk_mode=self.zk_mode.value,
            seed=int(self.zk_seed.value),
            temperature=float(self.zk_temperature.value),
        )

    def request_decode(self) -> int:
        """Submit the GUI's current latents (latest wins); returns the request version."""
        return self._submit(self.decoder, self.current_latents())

    def _submit(self, worker: LatestWorker, request: object) -> int:
        # Versions are taken and submitted under one lock, so workers always hold the newest request.
        with self._version_lock:
            self._version += 1
            self._record(self._version)
            worker.submit((self._version, request))
            return self._version

    def is_current(self, version: int) -> bool:
        """Whether ``version`` is still this tab's newest request (only then may it be drawn)."""
        return version == self._version and not self._closed.is_set()

    def idle(self) -> bool:
        return self.decoder.idle() and self.physics.idle()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until neither worker has work (for tests and benchmarks)."""
        deadline = time.monotonic() + timeout
        while True:
            for w in (self.decoder, self.physics):
                if not w.wait_idle(max(deadline - time.monotonic(), 0.0)):
                    return False
            if self.idle():
                return True

    def _record(self, version: int) -> None:
        timing = Timing(version=version, submitted=time.perf_counter())
        self._timing_by_version[version] = timing
        self.timings.append(timing)
        if len(self._timing_by_version) > 4000:
            for v in sorted(self._timing_by_version)[:2000]:
                del self._timing_by_version[v]

    def _on_latents_changed(self) -> None:
        # Reading under the lock that _write_sliders holds: a callback never sees half-set sliders.
        with self._z_lock:
            if self._setting_z:
                return
            z = tuple(float(s.value) for s in self.sliders)
            if self._programmatic_z is not None and np.allclose(z, self._programmatic_z, atol=1e-9):
                return  # the sliders show an imported gait's encoding: keep that gait
            self._programmatic_z = None
        self.request_decode()

    def _write_sliders(self, z: np.ndarray) -> tuple[float, ...]:
        values = tuple(float(v) for v in np.clip(np.round(z, 2), -SLIDER_RANGE, SLIDER_RANGE))
        with self._z_lock:
            self._setting_z = True
            try:
                with self.client.atomic():
                    for s, v in zip(self.sliders, values, strict=True):
                        s.value = v
            finally:
                self._setting_z = False
        return values

    def _set_z(self, z: np.ndarray) -> None:
        """Move all sliders at once (Reset, Random) and decode once."""
        with self._z_lock:
            self._programmatic_z = None
            self._write_sliders(z)
        self.request_decode()

    def _resample(self) -> None:
        self.zk_mode.value = "sampled"
        self.zk_seed.value = int(self.zk_seed.value) + 1

    def _toggle_play(self) -> None:
        self._playing = not self._playing
        self.play_button.label = "Pause" if self._playing else "Play"

    def _on_scrub(self, event) -> None:
        if event.client is None:
            return  # our own playback position updates
        self._frame = round(self.scrubber.value * FPS) % 2000
        self._position = float(self._frame)
        self._draw_snake()

    def _apply_layers(self) -> None:
        with self._draw_lock, self.client.atomic():
            self.snake.visible = self.layers["Snake"].value
            self.grid.visible = self.layers["Grid"].value
            if self.gen_path is not None:
                self.gen_path.visible = self.layers["Generated path"].value
            if self.sim_path is not None:
                self.sim_path.visible = self.layers["Simulated path"].value and self.simulated is not None
            if self.fan is not None:
                self.fan.visible = self.layers["Ensemble fan"].value and self.simulated is not None
            for frame in self.shape_frames.values():
                frame.visible = self.layers["Joint shapes"].value

    # --- the jobs: decode -> draw | replay -> draw -> ensemble -> draw ----------------------------

    def _timing(self, version: int) -> Timing:
        return self._timing_by_version.get(version) or Timing(version, time.perf_counter())

    def _decode_job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, latents = item
        if not self.is_current(version):
            return
        timing = self._timing(version)
        timing.started = time.perf_counter()
        decoded = self.session.decode(latents)
        timing.decode_ms = decoded.decode_ms
        with self._draw_lock:
            if not self.is_current(version):
                return
            self.decoded, self.simulated = decoded, None
            self._draw_decoded(decoded)
            timing.decoded = time.perf_counter()
            self.physics.submit((version, ("gait", decoded)))

    def _physics_job(self, _worker_version: int, item: tuple, _is_newest) -> None:
        version, (kind, *payload) = item
        if not self.is_current(version):
            return
        timing = self._timing(version)
        is_current = lambda: self.is_current(version)  # noqa: E731
        if kind == "import":
            self._import_job(*payload, timing, is_current)
        else:
            self._simulate(payload[0], timing, is_current)

    def _simulate(self, decoded: DecodedGait, timing: Timing, is_current) -> SimulatedGait | None:
        try:
            sim = self.session.replay(decoded)
        except SimulationError as exc:
            timing.failed = str(exc)
            with self._draw_lock:
                if is_current():
                    hint = ""
                    if decoded.latents is not None and decoded.latents.zk_mode == "sampled":
                        # Measured on the shipped model (implicit integrator): 3.3% of 512 sampled gaits
                        # at T = 1 broke, 2.1% at T = 0.5, none with z_k = 0 (calibration replays).
                        hint = (
                            "\n\nAbout 1 in 30 sampled-z_k gaits throws the simulated snake or breaks "
                            "the simulation: **Resample z_k** or lower the temperature."
                        )
                    self.panel.content = (
                        f"**Replay failed**: {exc}\n\nThe decoded gait is shown; physics could not replay it."
                        + hint
                    )
                    self.client.add_notification(
                        "Replay failed", str(exc), color="red", auto_close_seconds=8.0
                    )
            return None
        timing.replay_ms = sim.replay_ms
        with self._draw_lock:
            if not is_current():
                return None
            self.simulated = sim
            self._draw_simulated(decoded, sim, ensemble=False)
            timing.replayed = time.perf_counter()
        sim = self.session.run_ensemble(decoded, sim, seed=timing.version)
        timing.ensemble_ms = sim.ensemble_ms
        with self._draw_lock:
            if not is_current():
                return None
            self._draw_simulated(decoded, sim, ensemble=True)
            timing.ensembled = time.perf_counter()
        return sim

    def _import_job(self, name: str, commands: np.ndarray, timing: Timing, is_current) -> None:
        shape = joint_shape(commands)
        gait = DecodedGait(None, shape, None, commands, 0.0, source=f"import: {name}")
        try:
            sim = self.session.replay(gait)
        except SimulationError as exc:
            timing.failed = str(exc)
            self.client.add_notification(
                f"Import CSV: {name} not loaded",
                f"Its replay broke: {exc}. The current gait stays.",
                color="red",
            )
            return
        z_b = self.session.encode_replay(sim)
        with self._draw_lock:
            if not is_current():
                return
            self.decoded, self.simulated = gait, sim
            self._draw_decoded(gait)
            self._draw_simulated(gait, sim, ensemble=False)
            with self._z_lock:
                self._programmatic_z = self._write_sliders(z_b)
            timing.replayed = time.perf_counter()
        sim = self.session.run_ensemble(gait, sim, seed=timing.version)
        with self._draw_lock:
            if is_current():
                self._draw_simulated(gait, sim, ensemble=True)
                timing.ensembled = time.perf_counter()
                self.client.add_notification(
                    "Import CSV",
                    f"Replaying {name}; the sliders show where it sits in z_B.",
                    auto_close_seconds=5.0,
                )

    # --- drawing ---------------------------------------------------------------------------------

    def _draw_decoded(self, gait: DecodedGait) -> None:
        with self.client.atomic():
            if gait.body_ds is not None:
                self.gen_path = self._draw_line(
                    "generated",
                    _polyline(_path_points(gait.body_ds, LINK_RADIUS)),
                    GEN_COLOR,
                    4.0,
                    "Generated path",
                )
            elif self.gen_path is not None:
                self.gen_path.visible = False
            if self.sim_path is not None:
                self.sim_path.visible = False
            if self.fan is not None:
                self.fan.visible = False
            self._draw_cloud("decoded", gait.shape)
            self._update_plots(gait, None)
            self.plots["commands"].data = (np.arange(2000) / 20.0, *gait.commands.T)
            src = "model decode" if gait.source == "model" else gait.source
            self.panel.content = f"Decoded in {gait.decode_ms:.1f} ms ({src}); simulating..."

    def _draw_line(self, which: str, segments: np.ndarray, color, thickness: float, layer: str):
        return self.client.scene.add_line_segments(
            f"/paths/{which}",
            segments,
            color,
            thickness=thickness,
            thickness_units="screen",
            visible=self.layers[layer].value,
        )

    def _update_plots(self, gait: DecodedGait, sim_body_ds: np.ndarray | None) -> None:
        """Generated vs simulated (500, 6) body channels; a missing series is drawn as NaN (no line)."""
        t = np.arange(500) / 5.0
        missing = np.full(500, np.nan)
        for name, ch in {"forward (m)": 1, "sideways (m)": 2, "yaw (rad)": 5}.items():
            gen = gait.body_ds[:, ch] if gait.body_ds is not None else missing
            self.plots[name].data = (t, gen, sim_body_ds[:, ch] if sim_body_ds is not None else missing)

    def _draw_cloud(self, which: str, shape: np.ndarray) -> None:
        pts, colors = _shape_points(shape)
        self.clouds[which] = self.client.scene.add_point_cloud(
            f"/shapes/{which}/points", pts, colors, point_size=0.03, point_shape="circle", precision="float32"
        )

    def _draw_simulated(self, gait: DecodedGait, sim: SimulatedGait, ensemble: bool) -> None:
        # World pose of the body frame at t = 0 defines the scene frame (as the body channels do).
        self._set_origin(sim.qpos[0])
        z0 = self._origin[0][2]
        with self.client.atomic():
            self.sim_path = self._draw_line(
                "simulated", _polyline(_path_points(sim.body, z0)), SIM_COLOR, 4.0, "Simulated path"
            )
            if ensemble and len(sim.ensemble_body) > 1:
                segs = np.concatenate([_polyline(_path_points(b[::4], z0)) for b in sim.ensemble_body[1:]])
                self.fan = self._draw_line("ensemble", segs, FAN_COLOR, 1.0, "Ensemble fan")
            elif self.fan is not None:
                self.fan.visible = False
            if self.gen_path is not None and gait.body_ds is not None:
                self.gen_path = self._draw_line(
                    "generated", _polyline(_path_points(gait.body_ds, z0)), GEN_COLOR, 4.0, "Generated path"
                )
            self._draw_cloud("measured", sim.shape)
            self._update_plots(gait, sim.body[::4])
            self.panel.content = self._panel_text(gait, sim, ensemble)
        self._draw_snake()

    def _panel_text(self, gait: DecodedGait, sim: SimulatedGait, ensemble: bool) -> str:
        lines = [
            f"decode {gait.decode_ms:.1f} ms · replay {sim.replay_ms:.0f} ms"
            + (
                f" · ensemble of {len(sim.ensemble_body)} {sim.ensemble_ms:.0f} ms"
                if ensemble
                else " · ensemble running..."
            ),
        ]
        f = sim.figures
        if ensemble and f:
            lines.append(
                f"**Predictability** (ensemble final-position spread / distance travelled): **{f['final_spread']:.2f}**"
            )
            if gait.body_ds is not None:
                table = [
                    "| | model | simulated | error | physics spread (± std) |",
                    "|---|---|---|---|---|",
                    *[
                        f"| {label} | {unit * f[key + '_decoded']:.3g} | {unit * f[key + '_simulated']:.3g} | "
                        f"{100 * f[key + '_err']:.0f}% | "
                        f"{_spread_text(unit * f[key + '_std'], f[key + '_spread'])} |"
                        for key, label, unit in (
                            ("path_length", "path length (m)", 1.0),
                            ("median_speed", "speed (m/s)", 1.0),
                            ("vertical_std", "vertical osc. (mm)", 1000.0),
                            ("net_roll", "net roll (rad)", 1.0),
                        )
                    ],
                ]
                lines += [
                    "\n".join(table),
                    f"xy-path R²: {f['xy_r2']:.2f} · decoded final position "
                    + ("**inside**" if f["final_inside"] else "**outside**")
                    + f" the ensemble spread ({f['final_z']:.1f}× RMS)",
                ]
            if f.get("ensemble_broken"):
                lines.append(f"{int(f['ensemble_broken'])} ensemble member(s) broke and were left out.")
        # Paragraphs apart: a line right after a markdown table would be drawn as one more table row.
        return "\n\n".join(lines)

    def _set_origin(self, qpos0: np.ndarray) -> None:
        m, d = self._kin_model, self._kin_data
        d.qpos[:] = qpos0
        mujoco.mj_kinematics(m, d)
        site = m.site("body_frame").id
        xmat = d.site_xmat[site].reshape(3, 3)
        self._origin = (d.site_xpos[site].copy(), float(np.arctan2(xmat[1, 0], xmat[0, 0])))

    def _draw_snake(self) -> None:
        sim = self.simulated
        if sim is None:
            return
        m, d = self._kin_model, self._kin_data
        with self._draw_lock:
            d.qpos[:] = sim.qpos[self._frame % len(sim.qpos)]
            mujoco.mj_kinematics(m, d)
            p0, yaw0 = self._origin
            c, s = np.cos(-yaw0), np.sin(-yaw0)
            undo = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            pos = (d.geom_xpos[self._link_geoms] - [p0[0], p0[1], 0.0]) @ undo.T
            mats = undo @ d.geom_xmat[self._link_geoms].reshape(-1, 3, 3)
            quats = np.empty((9, 4))
            for i in range(9):
                mujoco.mju_mat2Quat(quats[i], mats[i].ravel())
            self.snake.batched_positions = pos.astype(np.float32)
            self.snake.batched_wxyzs = quats.astype(np.float32)

    def _animate(self) -> None:
        last_slider = 0.0
        while not self._closed.wait(1.0 / FPS):
            if not self._playing or self.simulated is None:
                continue
            try:
                # One record sample per tick at speed 1 (FPS = 20 Hz, the record's rate).
                self._position = (self._position + float(self.speed.value)) % 2000.0
                self._frame = int(self._position)
                self._draw_snake()
                now = time.monotonic()
                if now - last_slider > 0.5:
                    self.scrubber.value = round(self._frame / FPS, 2)
                    last_slider = now
            except Exception:  # the tab went away mid-update; the disconnect handler cleans up
                if self._closed.is_set():
                    return

    # --- files -----------------------------------------------------------------------------------

    def export_text(self) -> str:
        """The current gait as CSV text (what "Export CSV" downloads)."""
        gait, sim = self.decoded, self.simulated
        if gait is None:
            raise RuntimeError("no gait yet")
        comments = {"snakeloco gait": "commands (rad) at 20 Hz, replay with `snakeloco` or sim.replay"}
        if gait.latents is not None:
            lat = gait.latents
            comments["z_B"] = "[" + ", ".join(f"{v:.4f}" for v in lat.z_b) + "]"
            comments["z_k mode"] = lat.zk_mode + (
                f" (seed {lat.seed}, temperature {lat.temperature})" if lat.zk_mode == "sampled" else ""
            )
        else:
            comments["source"] = gait.source
            if self._programmatic_z is not None:
                comments["z_B (encoded)"] = "[" + ", ".join(f"{v:.4f}" for v in self._programmatic_z) + "]"
        comments["checkpoint sha256"] = self.model.hash
        if sim is not None and sim.figures:
            f = sim.figures
            comments["consistency"] = ", ".join(
                f"{k} {f[k]:.4g}"
                for k in (
                    "final_spread",
                    "path_length_err",
                    "median_speed_err",
                    "vertical_std_err",
                    "net_roll_err",
                    "xy_r2",
                )
                if k in f
            )
        return write_gait_csv(gait.commands, comments)

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
        return self._submit(self.physics, ("import", name, table.commands))

    def _on_upload(self) -> None:
        f = self.import_button.value
        self.import_bytes(f.name, f.content)  # read_gait_csv refuses more than MAX_BYTES

    def close(self) -> None:
        self._closed.set()
        self.decoder.close()
        self.physics.close()
        self.session.close()
        self._animator.join(timeout=5)


def return_freed_buffers_to_the_os(threshold: int = 1 << 20) -> bool:
    """glibc: serve every allocation of ``threshold`` bytes or more with its own mmap, unmapped
    when freed. Returns whether the setting took (False elsewhere).

    By default glibc raises that threshold (up to 32 MB) after the first large free; from then on
    each replay's 6-10 MB state and sensor arrays come from heap arenas, whose pages are kept after
    the arrays die, and a server's RSS creeps up with every tab's replays.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold)))
    except (OSError, AttributeError):  # not glibc
        return False


_M_MMAP_THRESHOLD = -3  # glibc malloc.h


def check_bindable(host: str) -> None:
    """An OSError naming ``host`` unless a TCP server can bind to it on this machine.

    Why: viser (1.1) binds in a background thread and, on any OSError, tries the next port, forever
    when the host itself is wrong (a typo, another machine's address), while its constructor waits
    for that thread: ``serve --host 999.1.1.1`` hung without a word.
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise OSError(f"--host {host}: not a host name or address ({exc.strerror})") from None
    try:
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise OSError(f"--host {host}: cannot serve on it here ({exc.strerror})") from None


class DesignerServer:
    """The viser server with one ``DesignerClient`` per connected tab."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        checkpoint: str | Path | None = None,
        ensemble: int = 8,
        workers: int | None = None,
        verbose: bool = True,
    ) -> None:
        check_bindable(host)
        self.model = load_pretrained(checkpoint)
        # One decode is a small, GIL-bound graph (~5 ms): intra-op threads do not speed it up, and
        # with several tabs decoding at once their OpenMP teams only compete for the cores.
        torch.set_num_threads(DECODE_THREADS)
        return_freed_buffers_to_the_os()
        # A thread that waits for the GIL forces the holder to let go after this long: with many
        # busy threads (tabs drawing, the websocket loop) a decode's every numpy/torch call would
        # otherwise wait up to the default 5 ms to get it back.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        self.ensemble = ensemble
        self.workers = workers
        # Every tab's replays and ensembles take turns on one pool of physics threads, at nice +15.
        self.simulator = Simulator(workers=workers or os.cpu_count() or 1, nice=PHYSICS_NICE)
        self.clients: dict[int, DesignerClient] = {}
        self.errors: list[str] = []
        """Every exception a tab's callbacks or workers raised (each also printed); bench load counts them."""
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=host, port=port, label="snakeloco", verbose=verbose)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._bound_uploads()

    def _bound_uploads(self) -> None:
        """Refuse an upload larger than ``MAX_BYTES`` when it starts, before any of it is buffered.

        viser (1.0-1.1) buffers a whole upload in memory before ``on_upload`` fires; its start message
        declares the size, so an oversized file is refused there and its parts are then dropped
        unbuffered (viser ignores parts of a transfer it does not know). Should viser's internals
        differ, the size is still checked in ``on_upload``.
        """
        from viser import _messages

        gui = self.server.gui
        interface = getattr(gui, "_websock_interface", None)
        original = getattr(gui, "_handle_file_transfer_start", None)
        if interface is None or original is None:
            return

        def bounded(client_id, message) -> None:
            if message.size_bytes > MAX_BYTES:
                client = self.server.get_clients().get(client_id)
                if client is not None:
                    client.add_notification(
                        f"Import CSV: {message.filename[:80]} rejected",
                        f"file is {message.size_bytes / 2**20:.1f} MiB; a gait CSV is at most "
                        f"{MAX_BYTES // 2**20} MiB. The current gait stays.",
                        color="red",
                        auto_close_seconds=15.0,
                    )
                return
            original(client_id, message)

        try:
            interface.unregister_handler(_messages.FileTransferStartUpload, original)
        except (AssertionError, ValueError):
            return
        interface.register_handler(_messages.FileTransferStartUpload, bounded)

    @property
    def port(self) -> int:
        return self.server.get_port()

    def _error(self, message: str) -> None:
        with self._lock:
            self.errors.append(message)
            del self.errors[:-1000]

    def _connect(self, client: viser.ClientHandle) -> None:
        try:
            designer = DesignerClient(
                client,
                self.model,
                self.ensemble,
                self.workers,
                on_error=self._error,
                simulator=self.simulator,
            )
        except Exception as exc:  # a tab that could not be set up must not take the server down
            traceback.print_exc()
            self._error(f"client {client.client_id}: setup failed: {type(exc).__name__}: {exc}")
            return
        with self._lock:
            self.clients[client.client_id] = designer

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            designer = self.clients.pop(client.client_id, None)
        if designer is not None:
            designer.close()

    def stop(self) -> None:
        with self._lock:
            designers = list(self.clients.values())
            self.clients.clear()
        for d in designers:
            d.close()
        self.simulator.close()
        self.server.stop()


def serve(
    host: str = "127.0.0.1", port: int = 8080, checkpoint: str | Path | None = None, ensemble: int = 8
) -> None:
    """Run the designer until Ctrl-C or SIGTERM; then stop cleanly (port freed, threads joined)."""
    app = DesignerServer(host, port, checkpoint, ensemble)
    stop = threading.Event()

    def _stop(signum, _frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    warning = app.model.robot_warning()
    if warning:
        print(f"snakeloco: warning: {warning}", file=sys.stderr)
    print(f"snakeloco designer on http://{host}:{app.port} (no authentication: keep it on a trusted network)")
    try:
        stop.wait()
    finally:
        app.stop()


__all__ = ["DesignerClient", "DesignerServer", "Timing", "asdict", "serve"]
