"""How a tab's latents are moved from Python rather than by its sliders: another gait family (the
sliders rebuilt for its model), a designed z_B, and the z_k mode's own events meanwhile
(a part ``DesignerClient`` holds, ``tab.moves``: through the tab's controls, locks and decode worker)."""

from __future__ import annotations

import numpy as np

from snakeloco.app.designer.gui import build_sliders
from snakeloco.app.designer.scene import END_SPREAD
from snakeloco.app.designer.session import Latents


class LatentMoves:
    """Family switches and designed gaits of a ``DesignerClient`` ``tab``: its latents moved from Python."""

    def __init__(self, tab) -> None:
        self.tab = tab

    def switch_family(self, name: str) -> int | None:
        """Design with the ``name`` family's model from now on: sliders rebuilt for its z_B, its
        gait at z_B = 0 decoded (the request version; None if it already is this tab's model)."""
        model = self.tab.models[name]
        if model is self.tab.model:
            return None
        c = self.tab.controls
        with self.tab.draw_lock, self.tab.z_lock:
            self.tab.model = model
            if self.tab.session.use_model(model):  # a family of another robot: its snake, its joints
                self.tab.scene.set_robot(self.tab.session.robot)
                c.set_joint_count(self.tab.client.gui, self.tab.session.robot.n_joints)
                self.tab.fit.robot_changed()
            self.tab.scene.end_spread = END_SPREAD.get(model.family)
            for handle in (*c.sliders, c.reset_button, c.random_button, c.component):
                if handle is not None:
                    handle.remove()
            c.component, c.sliders, c.reset_button, c.random_button = build_sliders(
                self.tab.client.gui, c.zb_folder, model.z_b_dim, self.component_names(model)
            )
            self.tab.programmatic_z = None
            self.tab.wire_sliders()
            self.tab.design.forget()
        if c.family.value != name:
            c.family.value = name
        return self.tab.request_decode()

    @staticmethod
    def component_names(model) -> list[str] | None:
        """The Gait cluster dropdown's entries: the names of the model's density components."""
        density = model.config.density
        return list(density.names) if density is not None else None

    def on_component_changed(self) -> None:
        """Another cluster picked: the sliders to its centre (unless set from Python, which decodes)."""
        with self.tab.z_lock:
            if self.tab.quiet_component_events:
                self.tab.quiet_component_events -= 1
                return
        self.tab.set_z(np.zeros(self.tab.model.z_b_dim))

    def _show_component(self, component: int) -> None:
        """Pick a cluster in the dropdown without its own decode (the caller decodes)."""
        c, density = self.tab.controls, self.tab.model.config.density
        if c.component is not None and c.component.value != density.names[component]:
            self.tab.quiet_component_events += 1
            c.component.value = density.names[component]

    def write_z(self, z_b: np.ndarray) -> tuple[float, ...]:
        """Move the sliders (and the cluster) to where ``z_b`` (Db,) sits; returns the slider values
        written (rounded to the slider step and clipped to its range)."""
        density = self.tab.model.config.density
        z_b = np.asarray(z_b, np.float64)
        if density is None or self.tab.controls.component is None:
            return self.tab.write_sliders(z_b)
        component = int(density.component_of(z_b[None])[0])
        self._show_component(component)
        return self.tab.write_sliders(density.to_axes(component, z_b))

    def random_z(self) -> None:
        """Random z_B: drawn from the density (its cluster picked, the sliders moved there), or from
        the N(0, I) prior where the model has none; decoded once."""
        rng = np.random.default_rng()
        density = self.tab.model.config.density
        if density is None or self.tab.controls.component is None:
            self.tab.set_z(rng.standard_normal(self.tab.model.z_b_dim))
            return
        z, comp = density.sample(1, seed=int(rng.integers(2**31)))
        with self.tab.z_lock:
            self._show_component(int(comp[0]))
        self.tab.set_z(density.to_axes(int(comp[0]), z[0]))

    def on_zk_changed(self, control: str) -> None:
        with self.tab.z_lock:
            if self.tab.quiet_zk[control]:  # set from Python by show_latents, which decodes itself
                self.tab.quiet_zk[control] -= 1
                return
        self.tab.request_decode()

    def _set_zk_quietly(self, mode: str, seed: int, temperature: float) -> None:
        """The z_k controls to a gait's, their callbacks told not to decode (the caller does)."""
        c = self.tab.controls
        for control, handle, value in (
            ("mode", c.zk_mode, mode),
            ("seed", c.zk_seed, int(seed)),
            ("temperature", c.zk_temperature, float(temperature)),
        ):
            if handle.value != value and (control == "mode" or mode == "sampled"):
                self.tab.quiet_zk[control] += 1
                handle.value = value

    def show_latents(
        self, z_b: np.ndarray, zk_mode: str = "zero", seed: int | None = None, temperature: float = 1.0
    ) -> int:
        """Make the gait of exactly ``z_b`` (z_k = 0, or sampled with ``seed`` and ``temperature``)
        current, the sliders moved there (rounded to their step: the drawn gait stays the exact one
        until a slider is moved)."""
        self.tab.clear_baseline()
        seed = int(self.tab.controls.zk_seed.value) if seed is None else seed
        with self.tab.z_lock:
            self.tab.programmatic_z = self.write_z(z_b)
            self.tab.shown_z = tuple(float(v) for v in z_b)
            self._set_zk_quietly(
                zk_mode, seed, temperature
            )  # their on_update must not decode the rounded sliders
        latents = Latents(
            tuple(float(v) for v in z_b),
            zk_mode,
            seed,
            temperature if zk_mode == "sampled" else 1.0,
            *self.axes_of(z_b),
        )
        return self.tab.submit(self.tab.decoder, latents)

    def axes_of(self, z_b: np.ndarray) -> tuple[int | None, tuple[float, ...] | None]:
        """The cluster and exact (unrounded) axis positions of ``z_b``, or (None, None) without a density."""
        density = self.tab.model.config.density
        if density is None or self.tab.controls.component is None:
            return None, None
        component = int(density.component_of(np.asarray(z_b, np.float64)[None])[0])
        return component, tuple(float(v) for v in density.to_axes(component, z_b))
