"""What makes a tab's scene readable at a glance: a metre grid that light rendering keeps, distance
rings around the start, and a camera that frames the snake and both paths. Frame: the start frame of
``scene.py`` (x forward, y left, z up; metres).

The metre grid is a flat mesh of thin quads (about 1,700 triangles), not line segments: three.js's
screen-space lines extrude a segment that passes behind the camera across the whole window, which
painted wide grey bands over a software-WebGL page when the rings were lines. Its line widths follow
the framing (``MetreGrid.fit``), so they stay one to three pixels wide whether the paths span 2 m or
30 m."""

from __future__ import annotations

import numpy as np
import viser

VIEW_DIRECTION = np.array([-3.0, -3.5, 2.5]) / np.linalg.norm([-3.0, -3.5, 2.5])
"""From where the camera looks at what it frames (unit vector from the target, start frame): behind
the start, to the right and above, as the tab's first view."""
FRAME_MARGIN = 1.2
"""The framed points' bounding circle fills 1 / this of the narrower field of view."""
MOVED_TOLERANCE_M = 0.02
"""A camera this far from where the tab last put it was moved by the user: framing leaves it alone."""
FRAME_STILL = 0.01
"""A framing whose camera position and target both lie within this share of the camera's distance
of where they are is not sent: the view moves by a few pixels at most, and most slider moves of a
drag frame within it (a camera move is two messages and 1.5 ms of a decoded view's 3-4 ms of the
server's drawing, cProfile of one tab). The margin (``FRAME_MARGIN``) keeps what is framed in view."""
PANEL_PX = 350
"""Pixels of the canvas's right side under viser's control panel (its 320 px and margins, measured
at 1500 px): what is framed goes in the rest, or a path's end can sit behind the readout."""
GRID_HALF_M = 40
"""The metre grid spans +/- this many metres around the start (the fastest gaits go ~33 m in 100 s)."""
RINGS_M = (1.0, 2.0, 5.0, 10.0, 20.0, 30.0)
"""Distance rings around the start (m), each labelled: 1 m and 10 m read differently at any zoom."""
GRID_WIDTHS = {"minor": 0.001, "major": 0.002, "rings": 0.002}
"""Line width (m) per metre of camera distance: about 1, 2 and 2 px where the camera looks, at 950 px
and viser's 50 deg field of view (nearer lines are wider: perspective)."""
GRID_COLORS = {"minor": (200, 200, 200), "major": (150, 150, 150), "rings": (110, 110, 110)}
GRID_LIFT_M = 0.002
"""The grid's height above the ground, so that viser's shaded grid (at 0) does not fight it."""


def ground_quads(segments: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground segments (n, 2, 2) xy -> a mesh of one thin quad each, ``width`` wide: vertices
    (4 n, 3) at ``GRID_LIFT_M`` and faces (2 n, 3), facing up."""
    a, b = segments[:, 0], segments[:, 1]
    d = b - a
    normal = np.stack([-d[:, 1], d[:, 0]], -1) / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    off = 0.5 * width * normal
    xy = np.stack([a - off, b - off, b + off, a + off], 1).reshape(-1, 2)
    vertices = np.concatenate([xy, np.full((len(xy), 1), GRID_LIFT_M)], 1).astype(np.float32)
    k = 4 * np.arange(len(segments))[:, None]
    faces = np.concatenate([k + np.array([0, 1, 2]), k + np.array([0, 2, 3])]).astype(np.uint32)
    return vertices, faces


def grid_lines(step: int, skip: int | None = None, half: int = GRID_HALF_M) -> np.ndarray:
    """(n, 2, 2) segments of the lines x = k step and y = k step (|k step| <= half); lines at
    multiples of ``skip`` are left out (another node draws them)."""
    ks = np.arange(-half, half + 1, step, dtype=np.float64)
    if skip is not None:
        ks = ks[ks % skip != 0]
    lo, hi = np.full_like(ks, -half), np.full_like(ks, half)
    xs = np.stack([np.stack([ks, lo], -1), np.stack([ks, hi], -1)], 1)
    ys = np.stack([np.stack([lo, ks], -1), np.stack([hi, ks], -1)], 1)
    return np.concatenate([xs, ys])


def ring_strips(width: float, radii=RINGS_M, n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Rings around the start as closed strips ``width`` wide: vertices (2 len(radii) (n + 1), 3)
    (inner and outer edge, shared by neighbouring quads) and faces (2 len(radii) n, 3), facing up."""
    a = np.linspace(0.0, 2 * np.pi, n + 1)
    vertices, faces = [], []
    for i, r in enumerate(radii):
        inner = np.stack([(r - width / 2) * np.cos(a), (r - width / 2) * np.sin(a)], -1)
        outer = np.stack([(r + width / 2) * np.cos(a), (r + width / 2) * np.sin(a)], -1)
        vertices.append(np.concatenate([inner, outer]))
        k = 2 * (n + 1) * i + np.arange(n)[:, None]  # quad k: inner k, k+1 and outer k, k+1
        o = n + 1
        faces += [k + np.array([0, o, o + 1]), k + np.array([0, o + 1, 1])]
    xy = np.concatenate(vertices)
    lifted = np.concatenate([xy, np.full((len(xy), 1), GRID_LIFT_M)], 1)
    return lifted.astype(np.float32), np.concatenate(faces).astype(np.uint32)


def width_scale(distance: float) -> float:
    """The camera distance the grid's line widths are made for: ``distance`` rounded to a power of
    2, so that framing a similar view again sends nothing (a redraw is ~25 kB)."""
    return float(2.0 ** np.round(np.log2(max(distance, 0.25))))


class MetreGrid:
    """The metre grid (1 m lines, every 5 m darker), the labelled distance rings and the start
    marker of one tab. One set of meshes per width scale (``width_scale``), made the first time a
    framing needs it and shown or hidden after that: going back and forth between a decode's and a
    replay's framing sends two visibility flags, not 28 kB of mesh."""

    def __init__(self, scene: viser.SceneApi) -> None:
        self.scene = scene
        self._lines = {"minor": grid_lines(1, skip=5), "major": grid_lines(5)}
        self.sets: dict[float, list[viser.MeshHandle]] = {}
        self.distance = 0.0  # the width scale shown
        self.labels = [scene.add_label("/metres/start", "start", position=(0.0, 0.0, 0.02))] + [
            # Where the rings cross the start's right rear (where paths rarely run).
            scene.add_label(f"/metres/ring_{r:g}", f"{r:g} m", position=(-r * 0.7071, -r * 0.7071, 0.02))
            for r in RINGS_M
        ]
        self._visible = True
        self.fit(float(np.linalg.norm([-2.5, -3.5, 2.5])))  # the tab's first view

    def _make(self, scale: float) -> list[viser.MeshHandle]:
        meshes = {name: ground_quads(lines, GRID_WIDTHS[name] * scale) for name, lines in self._lines.items()}
        meshes["rings"] = ring_strips(GRID_WIDTHS["rings"] * scale)
        return [
            self.scene.add_mesh_simple(
                f"/metres/{scale:g}/{name}",
                vertices,
                faces,
                color=GRID_COLORS[name],
                cast_shadow=False,
                receive_shadow=False,
                visible=self._visible,
            )
            for name, (vertices, faces) in meshes.items()
        ]

    def fit(self, distance: float) -> None:
        """Show the line widths for a camera ``distance`` m from what it looks at."""
        scale = width_scale(distance)
        if scale == self.distance:
            return
        for node in self.sets.get(self.distance, []):
            node.visible = False
        self.distance = scale
        if scale in self.sets:
            for node in self.sets[scale]:
                node.visible = self._visible
        else:
            self.sets[scale] = self._make(scale)

    @property
    def meshes(self) -> list[viser.MeshHandle]:
        """The meshes shown (at the current width scale)."""
        return self.sets[self.distance]

    @property
    def visible(self) -> bool:
        return self._visible

    @visible.setter
    def visible(self, on: bool) -> None:
        self._visible = on
        for node in [*self.meshes, *self.labels]:
            node.visible = on


def framing(
    points: np.ndarray, fov: float, aspect: float, covered: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Camera position and look-at (start frame, m) that show ``points`` (n, 3) whole from
    ``VIEW_DIRECTION``: their bounding circle (at least 1 m across) fits the narrower of the vertical
    field of view ``fov`` (rad) and the horizontal one that ``aspect`` (width / height) gives, in the
    part of the image left of the ``covered`` share of its width (the control panel): the camera
    moves right by as much, so that the circle's centre lands in the middle of what is seen."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    centre = (p.min(axis=0) + p.max(axis=0)) / 2
    radius = max(float(np.linalg.norm(p - centre, axis=1).max()), 0.5)
    seen = 1.0 - float(np.clip(covered, 0.0, 0.6))
    half = min(fov / 2, np.arctan(np.tan(fov / 2) * max(aspect * seen, 1e-3)))
    distance = FRAME_MARGIN * radius / np.sin(half)
    right = np.cross(-VIEW_DIRECTION, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    shift = right * (1.0 - seen) * distance * np.tan(fov / 2) * aspect
    return centre + VIEW_DIRECTION * distance + shift, centre + shift


def in_view(points: np.ndarray, position, look_at, fov: float, aspect: float) -> np.ndarray:
    """Whether each point (n, 3) projects inside a pinhole camera's image (z up): (n,) bool."""
    pos = np.asarray(position, np.float64)
    f = np.asarray(look_at, np.float64) - pos
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    v = np.asarray(points, np.float64).reshape(-1, 3) - pos
    depth = v @ f
    tan_v = np.tan(fov / 2)
    x, y = (v @ right) / np.maximum(depth, 1e-9), (v @ up) / np.maximum(depth, 1e-9)
    return (depth > 0) & (np.abs(x) <= tan_v * aspect) & (np.abs(y) <= tan_v)


class Framer:
    """Frames a tab's camera on what it shows, unless the user moved the camera since the tab last
    placed it (then only "Frame paths" does)."""

    def __init__(self, client: viser.ClientHandle, grid: MetreGrid | None = None) -> None:
        self.client = client
        self.grid = grid
        self._placed: np.ndarray | None = np.asarray(client.camera.position, np.float64)

    def placed(self) -> None:
        """The tab moved the camera itself (first view, follow): remember where."""
        self._placed = np.asarray(self.client.camera.position, np.float64)

    def user_moved(self) -> bool:
        here = np.asarray(self.client.camera.position, np.float64)
        return self._placed is None or float(np.linalg.norm(here - self._placed)) > MOVED_TOLERANCE_M

    def frame(self, points: np.ndarray, force: bool = False) -> bool:
        """Frame ``points`` (n, 3); returns whether the camera moved."""
        if not force and self.user_moved():
            return False
        camera = self.client.camera
        aspect = camera.aspect if camera.image_height > 0 else 1.5
        width = camera.image_width
        covered = PANEL_PX / width if width >= 3 * PANEL_PX else 0.0  # a narrow page: the panel floats
        position, look_at = framing(points, camera.fov, aspect, covered)
        still = FRAME_STILL * float(np.linalg.norm(position - look_at))
        here, target = np.asarray(camera.position, np.float64), np.asarray(camera.look_at, np.float64)
        if np.linalg.norm(position - here) < still and np.linalg.norm(look_at - target) < still:
            return False
        with self.client.atomic():  # position first: viser moves look_at with it, then sets it
            camera.position = tuple(position)
            camera.look_at = tuple(look_at)
        self._placed = np.asarray(position, np.float64)
        if self.grid is not None:
            self.grid.fit(float(np.linalg.norm(position - look_at)))
        return True
