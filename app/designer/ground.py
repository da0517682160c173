"""A tab's world drawn under the snake: the rough ground's heightfield as a mesh, the steps and pegs as
their shapes, built from the compiled model the replays run on (so the picture is the physics).

Frame: the scene's start frame (``scene.TabScene``); the world's geoms are in MuJoCo's world frame,
so they hang under one node placed by the replay's start pose (``GroundView.place``).
"""

from __future__ import annotations

import mujoco
import numpy as np
import trimesh
import viser

from snakeloco.sim.world.description import GROUND, WORLDS_DIR, World, load_world

DRAWN_HALF_M = 12.0
"""Half the side of the heightfield square drawn around the start (m): past any replay on rough ground
(the library undulation goes 3.6 m there), a few hundred thousand bytes at the field's own grid."""
MAX_SIDE = 241
"""At most this many heightfield vertices per side are drawn (every k-th where the grid is finer)."""
LOW, HIGH = np.array([118, 104, 84]), np.array([214, 198, 160])
"""The heightfield's colours at its lowest and highest points (a valley reads darker)."""
STEP_COLOR, PEG_COLOR = (170, 160, 140), (110, 100, 92)


def shipped_worlds() -> dict[str, World]:
    """The shipped worlds by name (``sim/worlds``), the flat plane first."""
    return {"flat": World(), **{p.stem: load_world(p) for p in sorted(WORLDS_DIR.glob("*.yaml"))}}


def _heightfield(model: mujoco.MjModel, field: int) -> trimesh.Trimesh:
    nrow, ncol = int(model.hfield_nrow[field]), int(model.hfield_ncol[field])
    rx, ry, top, _ = model.hfield_size[field]
    adr = int(model.hfield_adr[field])
    heights = model.hfield_data[adr : adr + nrow * ncol].reshape(nrow, ncol) * top
    x, y = np.linspace(-rx, rx, ncol), np.linspace(-ry, ry, nrow)
    cols, rows = np.flatnonzero(np.abs(x) <= DRAWN_HALF_M), np.flatnonzero(np.abs(y) <= DRAWN_HALF_M)
    stride = max(1, -(-max(len(cols), len(rows)) // MAX_SIDE))
    cols, rows = cols[::stride], rows[::stride]
    gx, gy = np.meshgrid(x[cols], y[rows])
    gz = heights[np.ix_(rows, cols)]
    vertices = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    n, m = len(rows), len(cols)
    corner = (np.arange(n - 1)[:, None] * m + np.arange(m - 1)[None, :]).reshape(-1)
    faces = np.concatenate(
        [np.stack([corner, corner + 1, corner + m + 1], 1), np.stack([corner, corner + m + 1, corner + m], 1)]
    )
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    shade = (gz.reshape(-1) - gz.min()) / max(float(np.ptp(gz)), 1e-9)
    colours = LOW + shade[:, None] * (HIGH - LOW)
    mesh.visual.vertex_colors = np.concatenate([colours, np.full((len(shade), 1), 255)], 1).astype(np.uint8)
    return mesh


def ground_mesh(model: mujoco.MjModel) -> trimesh.Trimesh | None:
    """The world's ground geoms (named ``ground_*``: heightfield, steps, pegs) as one coloured mesh in
    MuJoCo's world frame; None on the plane alone (the scene's grid draws that)."""
    parts = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != 0 or not model.geom(g).name.startswith(f"{GROUND}_"):
            continue
        kind, size = model.geom_type[g], model.geom_size[g]
        if kind == mujoco.mjtGeom.mjGEOM_HFIELD:
            mesh = _heightfield(model, int(model.geom_dataid[g]))
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            mesh = trimesh.creation.box(extents=2 * size)
            mesh.visual.vertex_colors = (*STEP_COLOR, 255)
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=10)
            mesh.visual.vertex_colors = (*PEG_COLOR, 255)
        else:
            continue
        transform = trimesh.transformations.quaternion_matrix(model.geom_quat[g])  # wxyz
        transform[:3, 3] = model.geom_pos[g]
        mesh.apply_transform(transform)
        parts.append(mesh)
    return trimesh.util.concatenate(parts) if parts else None


class GroundView:
    """The ground node of one tab's scene (callers serialise the calls, as ``TabScene``'s)."""

    def __init__(self, scene: viser.SceneApi) -> None:
        self.scene = scene
        self.frame = scene.add_frame("/ground", show_axes=False)
        self.mesh: viser.GlbHandle | None = None
        self.model: mujoco.MjModel | None = None

    def show(self, model: mujoco.MjModel) -> None:
        """Draw the ground of ``model`` (a simulator's compiled model) in place of the one drawn."""
        if model is self.model:
            return
        self.model = model
        if self.mesh is not None:
            self.mesh.remove()
            self.mesh = None
        mesh = ground_mesh(model)
        if mesh is not None:
            self.mesh = self.scene.add_mesh_trimesh("/ground/mesh", mesh, cast_shadow=False)

    def place(self, start: tuple[np.ndarray, float]) -> None:
        """Hang the world under the replay's start frame (``LinkPoses.start_frame``: position, heading)."""
        p0, yaw0 = start
        c, s = np.cos(-yaw0), np.sin(-yaw0)
        self.frame.position = (-(c * p0[0] - s * p0[1]), -(s * p0[0] + c * p0[1]), 0.0)
        self.frame.wxyz = (float(np.cos(-yaw0 / 2)), 0.0, 0.0, float(np.sin(-yaw0 / 2)))


class TabWorld:
    """A tab's World dropdown: the shipped worlds plus the server's (``serve --world``); choosing one
    replays the current gait there and draws its ground. And its Fan over dropdown: whether the
    Variations fan replays each gait on other robots or on other ground (``terrain_fan``)."""

    def __init__(self, tab) -> None:
        self.tab = tab
        self.terrain_fan = False
        """The Variations fan replays on the terrain set (``sim.world.sets``), not the physics variations."""
        self.worlds = shipped_worlds()
        here = tab.session.world
        self.initial = next((name for name, w in self.worlds.items() if w == here), None)
        if self.initial is None:  # a world of the user's own: offered under its name
            self.initial = here.name if here.name not in self.worlds else f"{here.name} (--world)"
            self.worlds[self.initial] = here

    def show(self) -> None:
        """Draw the ground the session's replays run on."""
        self.tab.scene.ground.show(self.tab.session.replay_model)

    def choose(self, name: str) -> int | None:
        """Replay the current gait on the world named ``name``; its request version (None: nothing to do)."""
        world = self.worlds.get(name)
        if world is None or world == self.tab.session.world:
            return None
        self.tab.session.set_world(world)
        self.show()
        return self._again(f"World: {name}")

    def choose_fan(self, label: str) -> int | None:
        """The Variations fan over other ground (``label`` "other ground") or other robots: the current
        gait replayed again, its fan over the new set; its request version (None: nothing to do)."""
        terrain = label == "other ground"
        if terrain == self.terrain_fan:
            return None
        self.terrain_fan = terrain
        return self._again(f"Fan over {label}")

    def _again(self, label: str) -> int | None:
        """Replay the current gait again, as ``label`` (the model's gait: decoded again, its path kept)."""
        gait = self.tab.decoded
        if gait is None:
            return None
        if gait.latents is not None:
            return self.tab.request_decode()
        return self.tab.submit(self.tab.physics, ("load", gait.source, label, gait.commands, gait.no_model))
