"""A camera that frames the snake and both paths. Frame: the start frame of ``scene.py`` (x forward,
y left, z up; metres)."""

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


def framing(points: np.ndarray, fov: float, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera position and look-at (start frame, m) that show ``points`` (n, 3) whole from
    ``VIEW_DIRECTION``: their bounding circle (at least 1 m across) fits the narrower of the vertical
    field of view ``fov`` (rad) and the horizontal one that ``aspect`` (width / height) gives."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    centre = (p.min(axis=0) + p.max(axis=0)) / 2
    radius = max(float(np.linalg.norm(p - centre, axis=1).max()), 0.5)
    half = min(fov / 2, np.arctan(np.tan(fov / 2) * max(aspect, 1e-3)))
    distance = FRAME_MARGIN * radius / np.sin(half)
    return centre + VIEW_DIRECTION * distance, centre


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

    def __init__(self, client: viser.ClientHandle) -> None:
        self.client = client
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
        position, look_at = framing(points, camera.fov, aspect)
        with self.client.atomic():  # position first: viser moves look_at with it, then sets it
            camera.position = tuple(position)
            camera.look_at = tuple(look_at)
        self._placed = np.asarray(position, np.float64)
        return True
