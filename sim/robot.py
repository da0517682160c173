"""The snake robot: MJCF file, model loading and the constants every other module shares.

Units: metres, kilograms, seconds, radians. The MJCF (``sim/snake.xml``) documents each physical
number and the reason for it. Importing this module does not import MuJoCo (``load_model`` does):
the model package reads the constants and the MJCF hash without the simulator.
"""

from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mujoco

MJCF_PATH = Path(__file__).with_name("snake.xml")

N_JOINTS = 8
"""Actuated hinge joints: odd joints pitch, even joints yaw (1-based, as in the MJCF names)."""
N_LINKS = N_JOINTS + 1
LINK_LENGTH = 0.10
"""Joint-to-joint distance along a link (m); the capsule runs from 0 to LINK_LENGTH on the link's x axis."""
LINK_RADIUS = 0.025
"""Capsule radius (m)."""
BODY_LENGTH = N_LINKS * LINK_LENGTH + 2 * LINK_RADIUS
"""Overall length of the straight snake (m), used to express speeds in body lengths per second."""
JOINT_RANGE = 2.3
"""Joint stops at +/- this angle (rad)."""
COMMAND_LIMIT = 2.2
"""Every joint command is clipped to +/- this angle (rad), inside the joint range."""
LINK_GEOMS = tuple(f"link{i}" for i in range(1, N_LINKS + 1))
"""MJCF names of the link capsules, head (link 1) to tail."""
BODY_SITE = "body_frame"
"""Site at the middle link's (link 5) centre whose pose is the measured body state."""


@cache
def mjcf_sha256() -> str:
    """Hash of the MJCF file, stored with datasets and checkpoints to catch a changed robot."""
    return hashlib.sha256(MJCF_PATH.read_bytes()).hexdigest()


def load_model() -> mujoco.MjModel:
    """Compile a fresh MjModel of the snake (each caller gets its own, so threads never share one)."""
    import mujoco

    return mujoco.MjModel.from_xml_path(str(MJCF_PATH))
