"""The trajectory figure's colour legend, and the report's defense section: AUC intervals, the few-models caution
and the note on how unusual the trigger's cell code is."""

from __future__ import annotations

import json

import matplotlib.pyplot as plt
import pytest
import torch
from matplotlib.colors import to_rgb

from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.render import COLORS
from seqtrojan.report.figures import plot_trajectory_pair, run_pair
from seqtrojan.report.html import _defense_section


@pytest.fixture
def figures(monkeypatch):
    """Figures the plotting functions close, kept open for inspection."""
    kept, close = [], plt.close
    monkeypatch.setattr(plt, "close", kept.append)
    yield kept
    for fig in kept:
        close(fig)


def test_the_trajectory_figure_has_a_colour_legend(tmp_path, figures):
    core = TrojanGridCore(EnvConfig(size=7, holes=3), 1, seed=0, phase="eval")
    up = lambda obs: torch.zeros(obs.shape[0], dtype=torch.int64)  # noqa: E731
    runs = run_pair(core, core.layout(0), 2, lambda: up)
    plot_trajectory_pair(runs, "title", tmp_path / "t.png")
    (fig,) = figures
    (legend,) = fig.legends
    colours = {t.get_text(): h for t, h in zip(legend.get_texts(), legend.legend_handles)}
    expected = {"hole": "hole", "user's goal (top right)": "user_goal", "adversary's goal (top left)": "adversary_goal",
                "trigger patch (when shown)": "on_trigger"}  # fmt: skip
    for label, name in expected.items():
        assert to_rgb(colours[label].get_facecolor()) == pytest.approx([v / 255 for v in COLORS[name]])
    assert {"path taken", "agent (last position)", "the agent's view", "empty cell"} <= set(colours)
    assert (tmp_path / "t.png").stat().st_size > 10_000


def _defense(model_dir) -> dict:
    rate = {"rate": 0.5, "ci95": [0.4, 0.6]}
    return {
        "model": str(model_dir),
        "monitor": {
            "grid": "7x7/3", "episodes": 100, "monitor": {"threshold": 5.0},
            "normal_alarm": {"false_alarm": rate}, "normal_reset": {"success": rate},
            "normal_undefended": {"success": rate}, "trojan_undefended": {"attack_success": rate},
            "trojan_alarm": {"detected": rate, "alarm_before_trigger": rate, "median_steps_to_detect": 0.0},
            "trojan_reset": {"attack_success": rate},
        },
        "mitigation": {"pruned_units": [1, 2], "before": {"clean_success": rate, "attack_success": rate}},
    }  # fmt: skip


def _detection(clean: int, backdoored: int, auc: float = 1.0) -> dict:
    predictions = [{"model": f"m{i}", "label": int(i >= clean), "p_backdoored": 0.5} for i in range(clean + backdoored)]
    score = {"folds": 2, "group": "all", "features": 10, "models": clean + backdoored, "roc_auc": auc,
             "cross_entropy": 0.1, "brier": 0.05, "predictions": predictions}  # fmt: skip
    return {"scores": [score], "held_out": [], "rejected": [],
            "functional_backdoors": {"functional_at": 0.5, "functional": backdoored, "not_functional": 0,
                                     "functional_roc_auc": auc}}  # fmt: skip


def test_detection_aucs_carry_intervals_and_a_caution_when_the_zoo_is_small():
    small = _defense_section(None, _detection(4, 4))
    assert "4 clean and 4 backdoored models" in small and "<b>Caution:</b> only 4 clean" in small
    # AUC 1.0 from 4 + 4 models: an interval well below 1 next to it, in the table and for the working backdoors
    assert small.count("1.000 <span class='note'>[0.") == 2
    large = _defense_section(None, _detection(25, 25, auc=0.8))
    assert "Caution" not in large and "0.800 <span class='note'>[0.6" in large


@pytest.mark.parametrize(
    ("value", "says"),
    [("trigger", "This agent's trigger uses it. The default trigger draws the dedicated cell code"),
     ("hole", "draws the cell code <code>hole</code>, which also occurs in normal play"),
     (None, "The default trigger draws the dedicated cell code <code>trigger</code>, which never occurs in normal")],
)  # fmt: skip
def test_the_monitor_section_says_how_unusual_the_trigger_code_is(tmp_path, value, says):
    if value is not None:
        (tmp_path / "card.json").write_text(json.dumps({"config": {"env": {"trigger": {"value": value}}}}))
    text = _defense_section(_defense(tmp_path), None)
    assert says in text
    assert text.index("detection rate") < text.index(says) < text.index("<h3>Mitigation")
