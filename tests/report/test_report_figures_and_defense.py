"""The trajectory figure's colour legend, and the report's defense section: AUC intervals, the few-models caution
and the note on how unusual the trigger's cell code is."""

from __future__ import annotations

import pytest
import torch
from matplotlib.colors import to_rgb

from seqtrojan.defense.results import (
    DefenseResult,
    DetectionResult,
    FunctionalSplit,
    GroupScores,
    MitigationArm,
    MonitorResult,
    NormalEnvArm,
    Prediction,
    TrojanEnvArm,
)
from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.render import COLORS
from seqtrojan.report.figures import plot_trajectory_pair, run_pair
from seqtrojan.report.sections.defense import defense_section
from seqtrojan.stats import Rate


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


def _defense(trigger_value: str) -> DefenseResult:
    rate = Rate(50, 100)
    normal, trojan = NormalEnvArm(rate, rate), TrojanEnvArm(rate, rate, rate, rate, 0.0)
    monitor = MonitorResult("7x7/3", 100, 5.0, (32, 16), normal, normal, trojan, trojan, rate, rate)
    mitigation = {
        "before": MitigationArm("no mitigation", rate, rate, ()),
        "pruned": MitigationArm("pruned 2 least-active units", rate, rate, (1, 2)),
    }
    return DefenseResult("model", "backdoored", "7x7/3", trigger_value, monitor, None, mitigation)


def _detection(clean: int, backdoored: int, auc: float = 1.0) -> DetectionResult:
    predictions = tuple(Prediction(f"m{i}", int(i >= clean), 0.5) for i in range(clean + backdoored))
    score = GroupScores("all", 10, clean + backdoored, 2, auc, 0.1, 0.05, predictions)
    return DetectionResult((), (score,), (), FunctionalSplit(0.5, backdoored, 0, auc, None), {})


def _section(defense: DefenseResult | None, detection: DetectionResult | None) -> str:
    return "\n".join(defense_section(defense, detection))


def test_detection_aucs_carry_intervals_and_a_caution_when_the_zoo_is_small():
    small = _section(None, _detection(4, 4))
    assert "4 clean and 4 backdoored models" in small and "<b>Caution:</b> only 4 clean" in small
    # AUC 1.0 from 4 + 4 models: an interval well below 1 next to it, in the table and for the working backdoors
    assert small.count("1.000 <span class='note'>[0.") == 2
    large = _section(None, _detection(25, 25, auc=0.8))
    assert "Caution" not in large and "0.800 <span class='note'>[0.6" in large


@pytest.mark.parametrize(
    ("value", "says"),
    [("trigger", "This agent's trigger uses it. The default trigger draws the dedicated cell code "
                 "<code>trigger</code>, which never occurs in normal play"),
     ("hole", "draws the cell code <code>hole</code>, which also occurs in normal play")],
)  # fmt: skip
def test_the_monitor_section_says_how_unusual_the_trigger_code_is(value, says):
    text = _section(_defense(value), None)
    assert says in text
    assert text.index("detection rate") < text.index(says) < text.index("<h3>Mitigation")
