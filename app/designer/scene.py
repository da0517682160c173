"""One tab's 3D scene: the snake, the decoded and simulated paths, the ensemble fan, the joint shapes.

Frame: the snake's initial heading frame (x forward, y left, z up; metres), the frame the body
channels are expressed in (``sim.physics.body``), so decoded and simulated paths start at the origin heading
+x. Link poses come from the simulator's kinematics (``sim.robot.kinematics.LinkPoses``); no robot geometry lives here.
"""

from __future__ import annotations

import numpy as np
import trimesh
import viser

from snakeloco.app.designer.ground import GroundView
from snakeloco.app.designer.scene_geometry import (
    SHAPE_CORNERS,
    SHAPES_AT,
    path_points,
    polyline,
    ring,
    shape_points,
)
from snakeloco.app.designer.session import DecodedGait, SimulatedGait
from snakeloco.app.designer.view import Framer, MetreGrid
from snakeloco.app.server.viser_patches import set_arrays
from snakeloco.sim import BODY_DOWNSAMPLE
from snakeloco.sim.robot.description import Robot
from snakeloco.sim.robot.kinematics import LinkPoses

GEN_COLOR = (255, 140, 0)
SIM_COLOR = (30, 100, 220)
FAN_COLOR = (150, 150, 150)
VARIATION_COLOR = (150, 90, 210)
"""The variations fan (violet): the replay on other robots (``sim.robot.variations.DEFAULT_SET``)."""
LOOP_COLOR = (20, 150, 110)
"""The closed-loop fan (teal): the steering loop's runs on the variations, each stopped at its path's end."""
PREDICTED_VARIATION_COLOR = (205, 180, 240)
"""The predicted variations fan (pale violet): where the physics head (``model.heads.physics_head``) says
the gait ends on those robots, drawn at decode time; the replays then check it."""
SNAKE_COLOR = (217, 140, 51, 255)
LAYERS = (
    "Snake",
    "Generated path",
    "Simulated path",
    "Ensemble fan",
    "Variations fan",
    "Joint shapes",
    "Metre grid",
    "Grid",
)
"""The Layers checkboxes, in the order they are shown."""
LIGHT_RENDERING = "Light rendering"
"""The Layers checkbox that draws the scene without its costly passes (``TabScene.set_light``)."""
ENVIRONMENT_MAP = "city"
"""The environment map viser's client lights an unconfigured scene with (its built-in default), which
full rendering restores."""


END_SPREAD = {"paper": 1.57}
"""Gait families whose decoded path is a mean, not a promise, and how far their replays' ends scatter:
the median RMS distance of an ensemble's final positions from its own replay's, relative to the
distance travelled, over 256 prior gaits of the shipped paper model (docs/evaluation.md). Such a
family's decoded path is drawn thin, with a ring of that radius around its end where the replay is
likely to end; a family not listed (structured: its records were kept only where physics predicts
them) is drawn as the line it is."""
BAND_COLOR = (245, 160, 60)
PATH_STEP = 2
"""The paths are drawn at every 2nd sample of the 5 Hz body series (2.5 Hz: 250 points over 100 s;
a cycle of the fastest gait is 4-5 of them), as the ensemble fan: a third of a slider move's bytes
were its paths at 5 Hz."""
FAN_STEP = PATH_STEP * BODY_DOWNSAMPLE
"""The ensemble fan's and simulated path's step in record samples (2.5 Hz)."""


class TabScene:
    """The scene nodes of one browser tab and how each is drawn. Callers serialise the calls."""

    def __init__(
        self,
        client: viser.ClientHandle,
        layers: dict[str, viser.GuiCheckboxHandle],
        robot: Robot | None = None,
    ) -> None:
        self.client = client
        self.layers = layers
        self.start = (np.zeros(3), 0.0)  # the replay's initial body position (m) and heading (rad), world
        scene = client.scene
        self.grid = scene.add_grid("/grid", 20.0, 20.0, cell_size=0.1, section_size=1.0)
        self.ground = GroundView(scene)  # the world's rough ground, steps and pegs (none on the plane)
        self.snake = None
        self.set_robot(robot)
        self.gen_path = self.band = None
        self.sim_parts: list[viser.LineSegmentsHandle] = []  # the simulated path, one node per part streamed
        self.fan: list[viser.LineSegmentsHandle] = []  # one node per batch of ensemble members
        self._fan_segments: list[np.ndarray] = []  # what those nodes draw (to merge them into one)
        self._fan_drawn = 0  # ensemble members the fan shows
        self.variation_fan: list[viser.LineSegmentsHandle] = []  # one node per batch of variations
        self.loop_fan: list[viser.LineSegmentsHandle] = []  # the closed-loop runs, one node
        self.predicted_fan: viser.LineSegmentsHandle | None = None  # the physics head's fan, one node
        self._predicted_shown = False  # whether it shows the current gait's prediction
        self._sim_drawn = 0  # replay samples the simulated path shows
        self._measured: np.ndarray | None = None  # the re-measured shape drawn
        self.end_spread: float | None = None  # END_SPREAD of the tab's family
        scene.add_label("/shapes/decoded/label", "decoded joint shape", position=(0, 0, 1.15))
        scene.add_label("/shapes/measured/label", "re-measured joint shape", position=(0, 0, 1.15))
        self.shape_frames = {
            name: scene.add_frame(f"/shapes/{name}", position=position, show_axes=True, axes_length=0.3)
            for name, position in SHAPES_AT.items()
        }
        self.clouds: dict[str, viser.PointCloudHandle] = {}
        self.metres = MetreGrid(scene)
        self._gen_points: np.ndarray | None = None  # what framing keeps in view (start frame, m)
        self._sim_points: np.ndarray | None = None
        client.camera.position = (-2.5, -3.5, 2.5)
        client.camera.look_at = (0.5, 0.0, 0.0)
        self.framer = Framer(client, self.metres)

    def set_robot(self, robot: Robot | None) -> None:
        """Draw ``robot``'s snake from now on (its links as its MJCF has them: count, radius, length);
        the tab calls it when a family of another robot is chosen."""
        self.kinematics = LinkPoses(robot)
        radius, length = self.kinematics.capsule()  # from the MJCF, as the physics has them
        self.link_radius = radius  # a path drawn before its replay sits at the lying snake's height
        capsule = trimesh.creation.capsule(height=length, radius=radius, count=[12, 12])
        capsule.visual.vertex_colors = np.array(SNAKE_COLOR, dtype=np.uint8)
        visible = True if self.snake is None else self.snake.visible
        n = self.kinematics.robot.n_links
        self.snake = self.client.scene.add_batched_meshes_trimesh(  # replaces the node of that name
            "/snake",
            capsule,
            batched_wxyzs=np.tile([1.0, 0, 0, 0], (n, 1)),
            batched_positions=np.zeros((n, 3)),
        )
        self.snake.visible = visible

    def set_light(self, light: bool) -> None:
        """Full rendering (cascaded shadows, environment lighting) or light: neither. In a browser
        without a GPU every frame is drawn on the CPU (SwiftShader) and read back, and the page
        answers input only between frames: one animating 1280x800 tab drew 5.6 frames/s, 9.6
        without shadows, 10.6 without the shaded grid, 12.4 without all three (docs/load.md).
        The grid is a layer of its own (``Tab`` turns it off with this)."""
        scene = self.client.scene
        scene.configure_default_lights(True, cast_shadow=not light)
        scene.configure_environment_map(None if light else ENVIRONMENT_MAP)

    def apply_layers(self, simulated: bool) -> None:
        """Show each node as its Layers checkbox says (simulated nodes only once there is a replay)."""
        on = {name: box.value for name, box in self.layers.items()}
        self.snake.visible = on["Snake"]
        self.grid.visible = on["Grid"]
        self.metres.visible = on["Metre grid"]
        if self.gen_path is not None:
            self.gen_path.visible = on["Generated path"]
        if self.band is not None:
            self.band.visible = on["Generated path"] and self.end_spread is not None
        for node in self.sim_parts:
            node.visible = on["Simulated path"] and simulated
        for node in self.fan:
            node.visible = on["Ensemble fan"] and simulated
        for node in self.variation_fan + self.loop_fan:
            node.visible = on["Variations fan"] and simulated
        if self.predicted_fan is not None:
            self.predicted_fan.visible = on["Variations fan"] and self._predicted_shown
        for frame in self.shape_frames.values():
            frame.visible = on["Joint shapes"]

    def _line(self, which: str, segments: np.ndarray, color, thickness: float, layer: str, z0: float):
        """A path node at height ``z0`` (its points carry the body's height relative to the start)."""
        return self.client.scene.add_line_segments(
            f"/paths/{which}",
            segments,
            color,
            thickness=thickness,
            thickness_units="screen",
            position=(0.0, 0.0, z0),
            visible=self.layers[layer].value,
        )

    def _redraw_line(
        self, node, which: str, segments: np.ndarray, color, thickness: float, layer: str, z0: float
    ):
        """``_line``, but a node drawn before (``node``) gets the new points in place: one update
        message instead of a node removed and added again (viser's add is ~0.3 ms of the server's
        drawing and the page rebuilds the node's geometry). Returns the node."""
        if node is None:
            return self._line(which, segments, color, thickness, layer, z0)
        set_arrays(node, points=segments)
        node.thickness = thickness  # sent only where it changed (a family switch)
        node.position = (0.0, 0.0, z0)
        node.visible = self.layers[layer].value
        return node

    def _cloud(self, which: str, shape: np.ndarray) -> None:
        pts, colors = shape_points(shape)
        if which in self.clouds:  # in place: see _redraw_line
            set_arrays(self.clouds[which], points=pts, colors=colors)
            return
        self.clouds[which] = self.client.scene.add_point_cloud(
            f"/shapes/{which}/points", pts, colors, point_size=0.03, point_shape="circle", precision="float32"
        )

    def draw_decoded(self, gait: DecodedGait) -> None:
        """The decoded path and joint shape; the previous replay's nodes are hidden (its fan removed)."""
        if gait.body_ds is not None:
            self._draw_generated(gait.body_ds, self.link_radius)
        else:
            for node in (self.gen_path, self.band):
                if node is not None:
                    node.visible = False
        self._sim_points = None
        for node in self.sim_parts + self.fan + self.variation_fan + self.loop_fan:
            node.remove()
        self.sim_parts, self.fan, self._fan_segments, self._fan_drawn = [], [], [], 0
        self.variation_fan, self.loop_fan = [], []
        self._sim_drawn = 0
        self._measured = None
        self._cloud("decoded", gait.shape)
        if self.predicted_fan is not None and self._predicted_shown:  # the last gait's prediction
            self.predicted_fan.visible = self._predicted_shown = False

    @property
    def sim_path(self) -> viser.LineSegmentsHandle | None:
        """The newest part of the simulated path (None before a replay)."""
        return self.sim_parts[-1] if self.sim_parts else None

    def _draw_sim_path(self, body: np.ndarray) -> None:
        """The simulated path at ``FAN_STEP``: the samples not drawn yet, as one more node that
        starts where the last one ended (a streamed replay sends each part once, not the whole path
        so far every time); nothing if ``body`` has no new sample."""
        if len(body) <= max(self._sim_drawn, 1):
            return
        first = max(self._sim_drawn - 1, 0)
        index = np.arange(first, len(body), FAN_STEP)
        if index[-1] != len(body) - 1:  # end where the replay so far ends
            index = np.append(index, len(body) - 1)
        z0 = float(self.start[0][2])
        points = path_points(body[index], 0.0)
        part = self._line(
            f"simulated/{len(self.sim_parts)}", polyline(points), SIM_COLOR, 4.0, "Simulated path", z0
        )
        self.sim_parts.append(part)
        self._sim_drawn = len(body)
        self._sim_points = (
            points if self._sim_points is None else np.concatenate([self._sim_points, points[1:]])
        )

    def draw_streaming(self, body: np.ndarray, qpos0: np.ndarray) -> None:
        """The simulated path so far (a streamed replay's first samples)."""
        self.start = self.kinematics.start_frame(qpos0)
        self.ground.place(self.start)
        self._draw_sim_path(body)

    def draw_simulated(self, gait: DecodedGait, sim: SimulatedGait, ensemble: bool) -> None:
        """The simulated path (and the ensemble fan once it ran), the re-measured joint shape, and the
        decoded path moved to the replay's starting height: only what is not drawn already (a
        streamed replay drew its path, an ensemble's batches their members). The streamed parts,
        and the fan's batches once the ensemble is done, become one node each here, so that the
        next slider move removes two nodes instead of a dozen (the decoded view waits on that)."""
        self.start = self.kinematics.start_frame(sim.qpos[0])
        self.ground.place(self.start)
        z0 = float(self.start[0][2])
        self._draw_sim_path(sim.body)
        if len(self.sim_parts) > 1 and self._sim_points is not None:
            whole = self._line(
                "simulated/whole", polyline(self._sim_points), SIM_COLOR, 4.0, "Simulated path", z0
            )
            for node in self.sim_parts:
                node.remove()
            self.sim_parts = [whole]
        if ensemble and len(sim.ensemble_body) > 1:
            self.draw_fan(sim.ensemble_body)
            if len(self.fan) > 1:
                segments = np.concatenate(self._fan_segments)
                whole = self._line("ensemble/whole", segments, FAN_COLOR, 1.0, "Ensemble fan", z0)
                for node in self.fan:
                    node.remove()
                self.fan, self._fan_segments = [whole], [segments]
        for node in (self.gen_path, self.band, self.predicted_fan):
            if node is not None:
                node.position = (0.0, 0.0, z0)
        if self._measured is not sim.shape:
            self._cloud("measured", sim.shape)
            self._measured = sim.shape

    def _draw_generated(self, body: np.ndarray, z0: float) -> None:
        """The decoded path: the line it is, or, for a family in ``END_SPREAD``, a thin mean path and
        a ring where the replay is likely to end."""
        points = path_points(body[::PATH_STEP], 0.0)
        if (len(body) - 1) % PATH_STEP:
            points = np.concatenate([points, path_points(body[-1:], 0.0)])
        self._gen_points = points
        thickness = 4.0 if self.end_spread is None else 1.5
        self.gen_path = self._redraw_line(
            self.gen_path, "generated", polyline(points), GEN_COLOR, thickness, "Generated path", z0
        )
        if self.end_spread is None:
            if self.band is not None:
                self.band.visible = False
            return
        radius = max(self.end_spread * float(np.linalg.norm(points[-1, :2] - points[0, :2])), 0.05)
        self.band = self._redraw_line(
            self.band, "band", ring(points[-1], radius), BAND_COLOR, 2.0, "Generated path", z0
        )

    def frame(self, force: bool = False) -> bool:
        """Point the camera at the snake's start and both paths (``view.Framer``: not after the
        user moved it, unless ``force``); returns whether it moved."""
        points = [SHAPE_CORNERS, *(p for p in (self._gen_points, self._sim_points) if p is not None)]
        return self.framer.frame(np.concatenate(points), force=force)

    def draw_fan(self, ensemble_body: np.ndarray) -> None:
        """The ensemble's perturbed members (K, T, 6; member 0, the replay, is the simulated path)
        that are not drawn yet, one node a batch, at ``FAN_STEP`` (drawn as the members come in)."""
        members = ensemble_body[1 + self._fan_drawn :, ::FAN_STEP]
        if len(members):
            segments = np.concatenate([polyline(path_points(b, 0.0)) for b in members])
            z0 = float(self.start[0][2])
            self.fan.append(
                self._line(f"ensemble/{len(self.fan)}", segments, FAN_COLOR, 1.0, "Ensemble fan", z0)
            )
            self._fan_segments.append(segments)
            self._fan_drawn += len(members)

    def draw_variations(self, bodies: list[np.ndarray]) -> None:
        """A batch of the replay's variations (each (T, 6)) as one node of the Variations fan."""
        if not bodies:
            return
        segments = np.concatenate([polyline(path_points(b[::FAN_STEP], 0.0)) for b in bodies])
        z0 = float(self.start[0][2])
        name = f"variations/{len(self.variation_fan)}"
        self.variation_fan.append(self._line(name, segments, VARIATION_COLOR, 1.0, "Variations fan", z0))

    def draw_closed_loop(self, paths: list[np.ndarray]) -> None:
        """The steering loop's runs (each (n, 2) forward, sideways m in the start frame, averaged over
        a wave period) as the closed-loop fan: one node in the Variations fan's layer, the last one's
        replaced."""
        for node in self.loop_fan:
            node.remove()
        self.loop_fan = []
        paths = [p[np.isfinite(p).all(axis=1)][::FAN_STEP] for p in paths]
        paths = [p for p in paths if len(p) > 1]
        if not paths:
            return
        points = [np.column_stack([p, np.zeros(len(p))]) for p in paths]
        segments = np.concatenate([polyline(q) for q in points])
        z0 = float(self.start[0][2])
        self.loop_fan.append(self._line("closed_loop", segments, LOOP_COLOR, 2.0, "Variations fan", z0))

    def draw_predicted_variations(self, bodies: np.ndarray) -> None:
        """The physics head's predicted paths of the current gait on the variations (V, 500, 6), at
        the decoded path's height, as one node of the Variations fan's layer (in place: one node)."""
        step = 2 * PATH_STEP  # 1.25 Hz: 12 paths on every decode of a drag, half the bytes of 2.5 Hz
        segments = np.concatenate([polyline(path_points(b[::step], 0.0)) for b in bodies])
        self.predicted_fan = self._redraw_line(
            self.predicted_fan,
            "variations/predicted",
            segments,
            PREDICTED_VARIATION_COLOR,
            1.0,
            "Variations fan",
            self.link_radius,
        )
        self._predicted_shown = True

    def draw_snake(self, qpos: np.ndarray, follow: bool = False) -> None:
        """Pose the snake's links as in ``qpos`` (a replay sample), in the start frame; with
        ``follow``, move the camera with the snake (the same offset from it, as the user left it).

        One frame is one message group (``atomic``): both pose arrays in a single update message,
        and the camera with them. Nothing is sent for a snake whose layer is off, unless the
        camera follows it."""
        if not (follow or self.layers["Snake"].value):
            return
        positions, wxyzs = self.kinematics.poses(qpos, self.start)
        with self.client.atomic():
            set_arrays(self.snake, batched_positions=positions, batched_wxyzs=wxyzs)
            if follow:  # viser moves look_at with position: one shift keeps the view on the snake
                camera = self.client.camera
                camera.position = tuple(
                    np.asarray(camera.position) + positions.mean(axis=0) - np.asarray(camera.look_at)
                )
                self.framer.placed()
