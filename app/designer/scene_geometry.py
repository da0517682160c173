"""The scene's geometry, apart from its nodes: joint colours, where the point clouds stand, paths and
rings as line segments (``app.designer.scene`` draws them)."""

from __future__ import annotations

import numpy as np

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
"""One colour per joint of the paper's 8-joint robot (point clouds, command plot)."""


def joint_colors(n: int) -> np.ndarray:
    """(n, 3) uint8 colours of n joints: ``JOINT_COLORS`` for up to 8, else n hues around the wheel."""
    if n <= len(JOINT_COLORS):
        return JOINT_COLORS[:n]
    import colorsys

    rgb = [colorsys.hsv_to_rgb(k / n, 0.75, 0.85) for k in range(n)]
    return (np.array(rgb) * 255).round().astype(np.uint8)


SHAPE_SCALE = 1.5
"""Point-cloud metres per radian of FFT coefficient."""
JOINT_SPACING = 0.12
"""Point-cloud height step between joints (m)."""
SHAPES_AT = {"decoded": (-1.5, 1.0, 0.0), "measured": (-1.5, -1.0, 0.0)}
"""Where the decoded and re-measured joint shapes' point clouds stand (start frame, m)."""
SHAPE_CORNERS = np.array(
    [(0.0, 0.0, 0.0)]
    + [
        (x + dx, y + dy, z)
        for x, y, _ in SHAPES_AT.values()
        for dx in (-0.6, 0.6)
        for dy in (-0.6, 0.6)
        for z in (0.0, 1.2)
    ]
)
"""What framing keeps in view beside the paths: the start and the point clouds (their typical
extent, 0.4 rad coefficients, and their labels), which a first view framed on the paths alone cut."""


def ring(center: np.ndarray, radius: float, n: int = 72) -> np.ndarray:
    """(n, 2, 3) segments of a horizontal circle."""
    a = np.linspace(0.0, 2 * np.pi, n + 1)
    points = np.stack(
        [center[0] + radius * np.cos(a), center[1] + radius * np.sin(a), np.full(n + 1, center[2])], -1
    )
    return polyline(points)


def polyline(points: np.ndarray) -> np.ndarray:
    """(N, 3) points -> (N-1, 2, 3) segments for add_line_segments."""
    return np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)


def path_points(body: np.ndarray, z0: float) -> np.ndarray:
    """Body channels (T, 6) -> (T, 3) scene points (forward, sideways, height above z0's floor)."""
    return np.stack([body[:, 1], body[:, 2], body[:, 0] + z0], axis=-1)


def shape_points(shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint shape (N, L, 2) -> points (N L, 3) = (real, imag, joint height) and per-joint colours;
    the joints span the same height whatever their count (the paper robot's 8 at ``JOINT_SPACING``)."""
    n = shape.shape[0]
    k = np.repeat(np.arange(n), shape.shape[1])
    spacing = JOINT_SPACING * len(JOINT_COLORS) / n
    pts = np.stack(
        [SHAPE_SCALE * shape[..., 0].ravel(), SHAPE_SCALE * shape[..., 1].ravel(), spacing * (k + 1)],
        -1,
    )
    return pts.astype(np.float32), joint_colors(n)[k]
