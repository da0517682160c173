"""One tab's GUI controls (viser), built in the order they are shown; ``tab.py`` wires them up."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser
import viser.uplot as uplot

from snakeloco.app.designer.fit_panel import FitControls, build_fit_controls
from snakeloco.app.designer.job_bar import JobControls, build_job_controls
from snakeloco.app.designer.loop_panel import LoopControls, build_loop_controls
from snakeloco.app.designer.scene import GEN_COLOR, LAYERS, LIGHT_RENDERING, SIM_COLOR
from snakeloco.app.designer.scene_geometry import joint_colors
from snakeloco.app.export.formats import ROBOT_FORMATS
from snakeloco.app.server.viser_patches import set_plot_data
from snakeloco.sim import BODY_TIMES, RECORD
from snakeloco.sim.gaits.library import PRESETS as GAIT_PRESETS

HELP_PATH = Path(__file__).resolve().parent / "help.md"
"""The Help panel's text; package data, so a non-editable install shows it too."""
SLIDER_RANGE = 3.0
"""Sliders span +/- 3 standard deviations: of z_B ~ N(0, I), or along a density component's axes."""
NO_BASELINE = "none"
"""The Baseline dropdown's entry for "no library gait"."""
PATH_PLOTS = {"forward (m)": 1, "sideways (m)": 2, "heading (deg)": 5}
"""Path plots and their body channel; the heading in degrees, as the readout says it (the body
series holds radians)."""
PLOT_SCALE = {"heading (deg)": 180.0 / np.pi}
"""Generated-vs-simulated plots: title -> body channel (``sim.BODY_CHANNELS``)."""
PATH_PLOT_BUCKET = 4
"""The path plots draw each 4 samples (0.8 s) of the 5 Hz body series as their lowest and highest
value, in the order they came, at the bucket's first and last time (``path_plot_values``): 250
points over 100 s in a plot a few hundred pixels wide. Every 2nd sample, the same bytes, lost the
peaks of yaw's ~0.5 Hz wiggle unevenly (its band's edge drawn ragged); an envelope keeps them."""
PATH_PLOT_TIMES = BODY_TIMES.reshape(-1, PATH_PLOT_BUCKET)[:, [0, -1]].ravel()
PLOT_DTYPE = np.float32
"""What the plots' series are sent as (``viser_patches.set_plot_data``): float32 is a screen's
resolution many times over and half of viser's float64."""
COMMAND_PLOT_STEP = 2
"""The commands plot shows every 2nd sample (10 Hz): above twice the highest excited frequency
(3 Hz), so no wave is lost."""
COMMAND_PLOT_SECONDS = 20.0
"""The commands plot shows the first 20 s: one period of the slowest excited frequency (0.05 Hz),
so every wave of the gait is in it, and as much as a plot a few hundred pixels wide can show of a
3 Hz wave (100 s of it was 300 cycles in 400 px, and a tenth of a slider move's bytes)."""
COMMAND_PLOT_TIMES = RECORD.times[: int(COMMAND_PLOT_SECONDS * RECORD.sample_rate) : COMMAND_PLOT_STEP]
WIDE_PX = 1200
"""A window at least this wide has room for the plots below the readout: they open by default."""

FAN_SETS = ("other robots", "other ground")
"""The Variations fan's choices (``Fan over``): the default physics variations or the terrain set."""


def hex_color(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def help_text() -> str:
    return HELP_PATH.read_text(encoding="utf-8")


NO_CANDIDATE = "none yet"
"""The Candidate dropdown before a design has verified anything."""


@dataclass
class DesignControls:
    """The handles of a tab's "Design for target" folder (``design_panel.py`` wires them up)."""

    forward: viser.GuiNumberHandle
    sideways: viser.GuiNumberHandle
    use_heading: viser.GuiCheckboxHandle
    heading: viser.GuiNumberHandle
    button: viser.GuiButtonHandle
    status: viser.GuiMarkdownHandle
    candidate: viser.GuiDropdownHandle
    robust: viser.GuiCheckboxHandle
    job: JobControls


def build_design_controls(gui: viser.GuiApi) -> DesignControls:
    with gui.add_folder("Design for target", expand_by_default=False):
        forward = gui.add_number("Forward (m)", 5.0, step=0.1, hint="Final forward displacement in 100 s")
        sideways = gui.add_number("Sideways (m)", 0.0, step=0.1, hint="Final sideways displacement (left +)")
        use_heading = gui.add_checkbox("Match heading", False, hint="Also ask for a heading change")
        heading = gui.add_number("Heading (deg)", 0.0, step=5.0, hint="Heading change in 100 s (left +)")
        robust = gui.add_checkbox(
            "Robust to other robots",
            False,
            hint="Rank the verified candidates by their worst end over the 12 physics variations (friction, "
            "anisotropy, masses, servo gains, slope, latency), each candidate replayed on every one: "
            "about 12 times the physics of a design; with a physics head the search also minimises "
            "the predicted worst end (docs/variations.md)",
        )
        button = gui.add_button("Design", hint="Search z_B for gaits that end there, verify each in MuJoCo")
        status = gui.add_markdown("Set a target (or click the ground), then press **Design**.")
        job = build_job_controls(gui, "design")
        candidate = gui.add_dropdown(
            "Candidate",
            (NO_CANDIDATE,),
            initial_value=NO_CANDIDATE,
            hint="Make a verified candidate the current gait",
        )
    return DesignControls(forward, sideways, use_heading, heading, button, status, candidate, robust, job)


@dataclass
class Controls:
    """The handles of one tab's GUI."""

    readout: viser.GuiHtmlHandle
    family: viser.GuiDropdownHandle
    world: viser.GuiDropdownHandle
    fan: viser.GuiDropdownHandle
    zb_folder: viser.GuiFolderHandle
    component: viser.GuiDropdownHandle | None
    sliders: list[viser.GuiSliderHandle]
    reset_button: viser.GuiButtonHandle
    random_button: viser.GuiButtonHandle
    zk_mode: viser.GuiDropdownHandle
    zk_seed: viser.GuiNumberHandle
    zk_temperature: viser.GuiSliderHandle
    resample_button: viser.GuiButtonHandle
    play_button: viser.GuiButtonHandle
    speed: viser.GuiSliderHandle
    scrubber: viser.GuiSliderHandle
    follow: viser.GuiCheckboxHandle
    frame_button: viser.GuiButtonHandle
    layers: dict[str, viser.GuiCheckboxHandle]
    light: viser.GuiCheckboxHandle
    baseline: viser.GuiDropdownHandle
    design: DesignControls
    export_button: viser.GuiButtonHandle
    robot_format: viser.GuiDropdownHandle
    robot_export_button: viser.GuiButtonHandle
    share_button: viser.GuiButtonHandle
    import_button: viser.GuiUploadButtonHandle
    fit: FitControls
    loop: LoopControls
    panel: viser.GuiMarkdownHandle
    plots: dict[str, viser.GuiUplotHandle]
    plots_folder: viser.GuiFolderHandle

    def show_paths(self, generated: np.ndarray | None, simulated: np.ndarray | None) -> None:
        """Generated vs simulated body series (500, 6) in the plots; a missing one is drawn as NaN."""
        missing = np.full(len(PATH_PLOT_TIMES), np.nan)
        for name, ch in PATH_PLOTS.items():
            k = PLOT_SCALE.get(name, 1.0)
            gen = path_plot_values(k * generated[:, ch]) if generated is not None else missing
            sim = path_plot_values(k * simulated[:, ch]) if simulated is not None else missing
            set_plot_data(self.plots[name], plot_series(PATH_PLOT_TIMES, gen, sim))

    def set_joint_count(self, gui: viser.GuiApi, n_joints: int) -> None:
        """A commands plot of ``n_joints`` series (a family of another robot chosen), in its place."""
        old = self.plots["commands"]
        if len(old.series) == n_joints + 1:
            return
        with self.plots_folder:
            self.plots["commands"] = add_commands_plot(gui, n_joints, order=old.order)
        old.remove()

    def show_commands(self, commands: np.ndarray) -> None:
        """Joint commands (2000, N) rad in the commands plot: the first ``COMMAND_PLOT_SECONDS``, every
        ``COMMAND_PLOT_STEP``-th sample."""
        self_n = len(self.plots["commands"].series) - 1
        if commands.shape[1] != self_n:
            return  # a gait of the robot the tab just left: the next one is drawn
        shown = commands[: COMMAND_PLOT_STEP * len(COMMAND_PLOT_TIMES) : COMMAND_PLOT_STEP]
        set_plot_data(self.plots["commands"], plot_series(COMMAND_PLOT_TIMES, *shown.T))


def plot_series(*series: np.ndarray) -> tuple[np.ndarray, ...]:
    """Series as the plots hold and send them (``PLOT_DTYPE``)."""
    return tuple(np.ascontiguousarray(s, dtype=PLOT_DTYPE) for s in series)


def path_plot_values(series: np.ndarray) -> np.ndarray:
    """What a path plot draws of one (500,) body series, as sent (``PLOT_DTYPE``): of each
    ``PATH_PLOT_BUCKET`` samples the lowest and the highest, the earlier first (a monotone bucket
    keeps its first and last sample exactly), at ``PATH_PLOT_TIMES``."""
    buckets = np.asarray(series).reshape(-1, PATH_PLOT_BUCKET)
    order = np.sort(np.stack([buckets.argmin(axis=1), buckets.argmax(axis=1)], axis=1), axis=1)
    return plot_series(np.take_along_axis(buckets, order, axis=1).ravel())[0]


def build_sliders(gui: viser.GuiApi, folder, z_b_dim: int, components: list[str] | None = None):
    """In ``folder``: the Gait cluster dropdown (where the model has a density: ``components`` names
    its components), one slider per z_B dimension, and the Reset and Random buttons.

    With a density the sliders move within the chosen cluster: slider i is the position along the
    cluster's i-th principal axis (largest spread first) in its standard deviations, so the whole
    slider range stays where the training records are. Without one, slider i is z_B dimension i."""
    with folder:
        component = None
        if components:
            component = gui.add_dropdown(
                "Gait cluster",
                tuple(components),
                initial_value=components[0],
                hint="A cluster of the training records in z_B, named by where its mean gait goes; the "
                "sliders move within it",
            )
            hint = "Along the cluster's axis {} (largest spread first), in its standard deviations"
            reset_hint, random_hint = "To the cluster's centre", "Draw z_B where the training records are"
        else:
            hint = "Body latent dimension {}"
            reset_hint, random_hint = "All z_B to 0 (the prior mean)", "Draw z_B from its N(0, I) prior"
        sliders = [
            gui.add_slider(f"z_B {i + 1}", -SLIDER_RANGE, SLIDER_RANGE, 0.01, 0.0, hint=hint.format(i + 1))
            for i in range(z_b_dim)
        ]
        reset_button = gui.add_button("Reset z_B", hint=reset_hint)
        random_button = gui.add_button("Random z_B", hint=random_hint)
    return component, sliders, reset_button, random_button


def add_commands_plot(gui: viser.GuiApi, n_joints: int, order: float | None = None) -> viser.GuiUplotHandle:
    """The joint commands plot: one series per joint of the robot, the first seconds of the gait."""
    colors = joint_colors(n_joints)
    return gui.add_uplot(
        data=(COMMAND_PLOT_TIMES, *[np.zeros(len(COMMAND_PLOT_TIMES))] * n_joints),
        series=(
            uplot.Series(label="t (s)"),
            *[
                uplot.Series(label=f"joint {k + 1}", stroke=hex_color(colors[k]), width=1)
                for k in range(n_joints)
            ],
        ),
        scales={"x": {"time": False}},  # uPlot would read x as dates
        title=f"joint commands, first {COMMAND_PLOT_SECONDS:.0f} s (rad)",
        aspect=1.5,
        order=order,
    )


def build_controls(
    gui: viser.GuiApi,
    z_b_dim: int,
    families: tuple[str, ...],
    family: str,
    components: list[str] | None = None,
    wide: bool = False,
    *,
    n_joints: int,
    worlds: tuple[str, ...] = ("flat",),
    world: str = "flat",
) -> Controls:
    """Add every folder and control of a tab to ``gui``: the readout first, in view without
    scrolling; ``wide`` (a window of at least ``WIDE_PX``): the plots open too."""
    readout = gui.add_html("<div>Decoding...</div>")
    with gui.add_folder("Model"):
        family_dropdown = gui.add_dropdown(
            "Gait family",
            families,
            initial_value=family,
            hint="The checkpoint this tab designs with: structured (undulation with steering that physics "
            "can predict; Design for target lands its gaits in MuJoCo) or paper (the paper's random-phase "
            "gaits: only their statistics can be promised)",
        )
        world_dropdown = gui.add_dropdown(
            "World",
            worlds,
            initial_value=world,
            hint="The ground this tab replays on and draws (docs/terrain.md): the flat plane, rough ground, "
            "steps, pegs, a 10° slope, or serve --world's; the model's paths were learnt on the flat plane",
        )
        fan_dropdown = gui.add_dropdown(
            "Fan over",
            FAN_SETS,
            initial_value=FAN_SETS[0],
            hint="What the Variations fan replays each gait on: other robots (12 physics variations, "
            "docs/variations.md) or other ground (the terrain set's 12 worlds, docs/terrain.md)",
        )
    zb_folder = gui.add_folder("Body latent z_B")
    component, sliders, reset_button, random_button = build_sliders(gui, zb_folder, z_b_dim, components)
    with gui.add_folder("Joint latents z_k"):
        zk_mode = gui.add_dropdown("z_k mode", ("zero", "sampled"), initial_value="zero")
        zk_seed = gui.add_number("z_k seed", 0, min=0, step=1)
        zk_temperature = gui.add_slider("Temperature", 0.0, 2.0, 0.05, 1.0)
        resample_button = gui.add_button("Resample z_k", hint="New seed for the sampled joint latents")
    with gui.add_folder("Playback"):
        play_button = gui.add_button("Pause")
        speed = gui.add_slider("Speed", 0.25, 8.0, 0.25, 1.0, hint="Playback speed (x real time)")
        last = float(RECORD.times[-1])
        scrubber = gui.add_slider("Time (s)", 0.0, last, 1.0 / RECORD.sample_rate, 0.0)
        follow = gui.add_checkbox("Follow snake", False, hint="Keep the camera on the snake as it travels")
        frame_button = gui.add_button(
            "Frame paths",
            hint="Point the camera at the snake and both paths (it does so by itself after "
            "each decode and replay until you move the camera)",
        )
    with gui.add_folder("Layers"):
        layers = {name: gui.add_checkbox(name, True) for name in LAYERS}
        light = gui.add_checkbox(
            LIGHT_RENDERING,
            False,
            hint="Draw without shadows, environment lighting or the shaded grid (the metre grid stays): a browser without a GPU "
            "(software WebGL) draws each frame 2-3x sooner and answers the controls sooner. Set on by "
            "the page itself when it renders in software; turn the Grid back on at will",
        )
    with gui.add_folder("Baseline"):
        baseline = gui.add_dropdown(
            "Baseline",
            (NO_BASELINE, *GAIT_PRESETS),
            initial_value=NO_BASELINE,
            hint="Load a gait of the library tuned on this robot as the current gait (docs/gaits.md)",
        )
    design = build_design_controls(gui)
    with gui.add_folder("Gait file"):
        export_button = gui.add_button(
            "Export CSV",
            hint=f"Download the current gait ({RECORD.n_samples} rows, {RECORD.sample_rate:g} Hz, rad)",
        )
        import_button = gui.add_upload_button("Import CSV", mime_type=".csv,text/csv,text/plain")
        robot_format = gui.add_dropdown(
            "Robot format",
            tuple(ROBOT_FORMATS),
            initial_value=next(iter(ROBOT_FORMATS)),
            hint="What Export for robot writes (docs/export.md): a ROS 2 JointTrajectory with velocities, "
            "commands resampled at 100 Hz, Dynamixel goal positions in ticks, or the gait's parameters; "
            "each starts with the simulation's 3 s lead-in from rest",
        )
        robot_export_button = gui.add_button(
            "Export for robot",
            hint="Download the current gait in the Robot format, checked against the robot's limits",
        )
        share_button = gui.add_button(
            "Share",
            hint="Download a page that plays this replay (snake, paths, fan, figures) in any browser, with no server",
        )
    fit = build_fit_controls(gui)
    loop = build_loop_controls(gui)
    with gui.add_folder("Consistency"):
        panel = gui.add_markdown("Decoding...")
    with gui.add_folder("Plots", expand_by_default=wide) as plots_folder:
        no_time = {"x": {"time": False}}  # uPlot would read x as dates
        nan = np.full(len(PATH_PLOT_TIMES), np.nan)
        plots = {}
        for name in PATH_PLOTS:
            plots[name] = gui.add_uplot(
                data=(PATH_PLOT_TIMES, nan, nan),
                series=(
                    uplot.Series(label="t (s)"),
                    uplot.Series(label="model", stroke=hex_color(GEN_COLOR), width=2),
                    uplot.Series(label="MuJoCo", stroke=hex_color(SIM_COLOR), width=2),
                ),
                scales=no_time,
                title=name,
                aspect=2.0,
            )
        plots["commands"] = add_commands_plot(gui, n_joints)
    with gui.add_folder("Help", expand_by_default=False):
        gui.add_markdown(help_text())
    return Controls(
        readout=readout,
        family=family_dropdown,
        world=world_dropdown,
        fan=fan_dropdown,
        zb_folder=zb_folder,
        component=component,
        sliders=sliders,
        reset_button=reset_button,
        random_button=random_button,
        zk_mode=zk_mode,
        zk_seed=zk_seed,
        zk_temperature=zk_temperature,
        resample_button=resample_button,
        play_button=play_button,
        speed=speed,
        scrubber=scrubber,
        follow=follow,
        frame_button=frame_button,
        layers=layers,
        light=light,
        baseline=baseline,
        design=design,
        export_button=export_button,
        robot_format=robot_format,
        robot_export_button=robot_export_button,
        share_button=share_button,
        import_button=import_button,
        fit=fit,
        loop=loop,
        panel=panel,
        plots=plots,
        plots_folder=plots_folder,
    )
