"""The readout's numbers as a person reads them (``app.designer.readout``)."""

from __future__ import annotations


def test_the_readout_says_headings_in_half_turns_and_no_percentage_of_a_short_path():
    from snakeloco.app.designer.readout import PathEnd, Readout, heading_text, readout_html

    assert (
        heading_text(402.0) == "+42° (1.1 turns left)" and heading_text(-607.0) == "+113° (1.7 turns right)"
    )
    assert (
        heading_text(57.0) == "+57°"
        and heading_text(-180.0) == "+180°"
        and heading_text(190) == "-170° (0.5 turns left)"
    )
    colors = dict.fromkeys(("model", "mujoco", "ensemble", "ring", "variations"), (0, 0, 0))
    short = PathEnd(0.25, 10.0, 402.0, 0.25, 0.04)
    model = PathEnd(0.6, 0.0, 20.0, 0.6, 0.0)
    text = readout_html(Readout(model=model, mujoco=short, state="done"), colors)
    assert "too short a base for a percentage" in text and "gap-share" not in text
    assert "+42° (1.1 turns left)" in text and "402" not in text
    far = PathEnd(3.0, 10.0, 5.0, 3.0, 0.5)
    assert 'data-key="gap-share"' in readout_html(Readout(model=model, mujoco=far, state="done"), colors)


def test_the_panel_says_each_error_where_it_has_a_base_and_no_r2_of_a_path_that_barely_moved():
    """Issue 59's numbers: a net-roll error of 618% where the gait does not roll, R² -1.42 beside
    "inside the ensemble spread", "95% off this member" beside a 0.03 m gap."""
    import math

    import numpy as np

    from snakeloco.app.designer.gui import PATH_PLOTS, PLOT_SCALE
    from snakeloco.app.designer.panel import error_text, gait_text, r2_text
    from snakeloco.app.designer.session import DecodedGait
    from snakeloco.sim.gaits.library import PRESETS
    from snakeloco.sim.gaits.members import Member

    no_roll = {"net_roll_simulated": 0.2, "net_roll_decoded": 0.03, "net_roll_err": 6.18}
    assert error_text("net_roll", no_roll, 1.0) == "0.17"  # rad, not 618%
    rolls = {"net_roll_simulated": 30.0, "net_roll_decoded": 27.0, "net_roll_err": 0.1}
    assert error_text("net_roll", rolls, 1.0) == "10%"
    assert r2_text({"displacement_m": 0.2, "xy_r2": -1.42}).startswith(
        "xy-path R²: not shown (the replay moved 0.20 m"
    )
    assert r2_text({"displacement_m": 3.0, "xy_r2": 0.97}) == "xy-path R²: 0.97"
    member = Member(kind="undulate", wave=PRESETS["undulate"].gait)
    gait = DecodedGait(
        None, np.zeros((8, 8, 2)), None, np.zeros((2000, 8)), 1.0, member=member, residual=0.95
    )
    text = gait_text(gait)
    assert "95%" in text and "the member itself is replayed" in text and "off this member" not in text
    assert "heading (deg)" in PATH_PLOTS and PLOT_SCALE["heading (deg)"] == 180 / math.pi  # one unit: degrees


def test_framing_keeps_the_paths_and_the_point_clouds_left_of_the_control_panel():
    """Issue 59, point 2: a path's end sat behind the panel and the point clouds were cut."""
    import numpy as np

    from snakeloco.app.designer.scene_geometry import SHAPE_CORNERS
    from snakeloco.app.designer.view import PANEL_PX, framing

    fov, width, height = np.radians(50), 1500, 950
    aspect, covered = width / height, PANEL_PX / width
    for path in (np.array([[0, 0, 0], [16.0, -4.0, 0]]), np.array([[0, 0, 0], [-2.0, 9.5, 0]])):
        points = np.concatenate([SHAPE_CORNERS, path])
        position, look_at = framing(points, fov, aspect, covered)
        f = (look_at - position) / np.linalg.norm(look_at - position)
        right = np.cross(f, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, f)
        v = points - position
        x = (v @ right) / (v @ f) / (np.tan(fov / 2) * aspect)  # -1 left edge, +1 right edge
        y = (v @ up) / (v @ f) / np.tan(fov / 2)
        panel_edge = 1 - 2 * covered
        assert (x > -1).all() and (x < panel_edge).all() and (np.abs(y) < 1).all()


def test_the_readout_says_when_a_slider_move_left_the_gait_cluster():
    """Issue 71: the Gait cluster the sliders move in is named as left once the decoded z_B sits in
    another cluster, and nothing is said while it is inside."""
    from types import SimpleNamespace

    import numpy as np

    from snakeloco.app.designer.readout import TabReadout
    from snakeloco.model import load_pretrained

    tab = TabReadout(SimpleNamespace(model=load_pretrained("structured")))
    density = tab.tab.model.config.density
    means = np.asarray(density.means)
    gait = SimpleNamespace(latents=SimpleNamespace(component=0, z_b=tuple(means[0])))
    assert tab._cluster_line(gait) == ""
    gait.latents.z_b = tuple(means[1])
    line = tab._cluster_line(gait)
    assert f"move in '{density.names[0]}'" in line and f"sits in '{density.names[1]}'" in line
