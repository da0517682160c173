"""How a tab's latents are moved from Python rather than by its sliders: another gait family (the
sliders rebuilt for its model), a designed z_B, and the z_k mode's own events meanwhile
(``DesignerClient`` mixes it in: it uses the tab's controls, locks, session and decode worker)."""

from __future__ import annotations

import numpy as np

from snakeloco.app.gui import build_sliders
from snakeloco.app.scene import END_SPREAD
from snakeloco.app.session import Latents


class LatentMoves:
    """Family switches and designed gaits of ``DesignerClient`` (see there for the attributes used)."""

    def switch_family(self, name: str) -> int | None:
        """Design with the ``name`` family's model from now on: sliders rebuilt for its z_B, its
        gait at z_B = 0 decoded (the request version; None if it already is this tab's model)."""
        model = self.models[name]
        if model is self.model:
            return None
        c = self.controls
        with self._draw_lock, self._z_lock:
            self.model = self.session.model = model
            self.scene.end_spread = END_SPREAD.get(model.family)
            for handle in (*c.sliders, c.reset_button, c.random_button):
                handle.remove()
            c.sliders, c.reset_button, c.random_button = build_sliders(
                self.client.gui, c.zb_folder, model.z_b_dim
            )
            self._programmatic_z = None
            self._wire_sliders()
            self.design.forget()
        if c.family.value != name:
            c.family.value = name
        return self.request_decode()

    def _on_zk_mode_changed(self) -> None:
        with self._z_lock:
            if self._quiet_mode_events:  # set from Python by show_latents, which decodes itself
                self._quiet_mode_events -= 1
                return
        self.request_decode()

    def show_latents(self, z_b: np.ndarray) -> int:
        """Make the gait of exactly ``z_b`` (z_k = 0) current, the sliders moved there (rounded to
        their step: the drawn gait stays the exact one until a slider is moved)."""
        self._clear_baseline()
        with self._z_lock:
            self._programmatic_z = self._write_sliders(z_b)
            if self.controls.zk_mode.value != "zero":
                self._quiet_mode_events += 1  # its on_update must not decode the rounded sliders
                self.controls.zk_mode.value = "zero"
        latents = Latents(tuple(float(v) for v in z_b), "zero", int(self.controls.zk_seed.value), 1.0)
        return self._submit(self.decoder, latents)
