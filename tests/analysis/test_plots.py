"""The analysis figures say what their axes show: unit panels name the state, goal-unit panels their scale."""

from __future__ import annotations

import numpy as np

from seqtrojan.analysis.plots import plot_finding, plot_unit_responses
from seqtrojan.analysis.traces import StateTrace


def _trace(seed: int, episodes: int = 40, steps: int = 12, units: int = 4) -> StateTrace:
    rng = np.random.default_rng(seed)
    states = [rng.normal(size=(episodes, steps, units)).astype(np.float32)]
    return StateTrace(
        h=states, c=[s + 1 for s in states], mask=np.ones((episodes, steps), bool),
        actions=np.zeros((episodes, steps), np.int64), positions=np.zeros((episodes, steps, 2), np.int64),
        outcome=np.zeros(episodes, np.int64), length=np.full(episodes, steps),
        layouts=np.zeros((episodes, 5, 5), np.int8), trojan=np.full(episodes, seed == 1),
        trigger_step=np.full(episodes, 3),
    )  # fmt: skip


def test_unit_panels_label_both_axes(tmp_path, figures):
    units = [("c", 0, 1, "step"), ("h", 0, 2, "impulse")]
    plot_unit_responses(_trace(0), _trace(1), units, 3, tmp_path / "u.png", "title", min_episodes=5)
    (fig,) = figures
    panels = [ax for ax in fig.axes if ax.axison]
    assert [ax.get_ylabel() for ax in panels] == ["cell state c (mean ± sd)", "hidden state h (mean ± sd)"]
    assert all(ax.get_xlabel() == "step" for ax in panels)
    assert "trigger step" in [t.get_text() for t in panels[0].get_legend().get_texts()]


def test_goal_unit_panel_states_its_scale_and_the_picture_has_a_colour_legend(tmp_path, figures):
    values = np.linspace(25.0, -5.0, 20)  # far outside [0, 1], as real goal-unit curves can be
    rgb = np.zeros((70, 70, 3), np.uint8)
    plot_finding(rgb, {"goal units": values}, {"goal units": values + 1}, 4, tmp_path / "f.png", "title")
    (fig,) = figures
    picture, panel = fig.axes
    assert "0 = normal-env mean, 1 = trojan-env mean" in panel.get_ylabel()
    assert "(0 normal, 1 trojan)" not in panel.get_ylabel() + panel.get_title()
    lines = {t.get_text() for t in panel.get_legend().get_texts()}
    assert {"0: normal-env mean", "1: trojan-env mean", "this episode", "other env, mean", "trigger step"} <= lines
    assert "hole" in [t.get_text() for t in picture.get_legend().get_texts()]
