"""The readout's numbers as a person reads them (``app.readout``)."""

from __future__ import annotations


def test_the_readout_says_headings_in_half_turns_and_no_percentage_of_a_short_path():
    from snakeloco.app.readout import PathEnd, Readout, heading_text, readout_html

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
