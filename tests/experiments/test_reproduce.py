"""The end-to-end reproduction on a tiny scale: every stage's outputs, the report, and resuming."""

from __future__ import annotations

import json
import re

import pytest

from seqtrojan.config import from_dict
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.curves import aggregate_curves
from seqtrojan.experiments.reproduce import ReproduceConfig, deep_merge, load_reproduce_config, reproduce

TINY_STAGES = [{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]
TINY_SET = {
    "env": {"size": 5, "holes": 1},
    "ppo": {"total_steps": 8192, "num_envs": 64, "rollout_steps": 32, "num_minibatches": 2, "update_epochs": 2},
    "curriculum": {"stages": TINY_STAGES},
    "run": {"eval_episodes": 32, "checkpoint_every": 4096, "progress": False},
}
TINY = {
    "clean": {"preset": "clean_s17_h30", "set": TINY_SET},
    "backdoor": {"preset": "trojan_s17_h30", "set": deep_merge(TINY_SET, {"backdoor": {"eval_episodes": 16}})},
    "evaluation": {"configs": "7x7/0,7x7/7", "episodes": 32},
    "curves": {"configs": [[5, 0], [5, 1]], "seeds": 2, "total_steps": 4096, "num_envs": 32, "points": 5},
    "trajectory": {"size": 5, "holes": 1, "trigger_step": 2},
    "analysis": {
        "size": 7,
        "holes": [2, 3],
        "episodes": 40,
        "trigger_step": 2,
        "rule": {"min_episodes": 5, "response_window": 2, "late_start": 3, "late_end": 6},
        "intervention_episodes": 32,
        "unintentional_configs": "7x7/0,7x7/3",
        "unintentional_episodes": 32,
        "layout_search": {
            "size": 7,
            "holes": 3,
            "population": 4,
            "rollouts": 4,
            "generations": 2,
            "elite": 2,
            "restarts": 1,
        },
        "sequence_search": {"length": 6, "restarts": 4, "steps": 10},
        "walk_search": {"size": 7, "holes": 3, "length": 6, "restarts": 4, "steps": 10},
    },
    "defense": {
        "monitor": {"calibration_episodes": 40, "eval_episodes": 32, "false_alarm_target": 0.05},
        "mitigation": {"finetune_steps": 2048, "calibration_episodes": 32, "eval_episodes": 32},
        "oracle_episodes": 40,
    },
    "tradeoff": {"penalties": [-1.0, -4.0], "configs": "7x7/0,7x7/3", "episodes": 16, "seeds": 2},
    "zoo": {
        "clean": 2,
        "backdoored": 2,
        "total_steps": 2048,
        "num_envs": 32,
        "eval_episodes": 16,
        "lstm_sizes": [[8]],
        "curricula": [[{"size": 5, "holes": 0}]],
    },
    "zoo_workers": 1,
}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro")
    report = reproduce(from_dict(ReproduceConfig, TINY), out, scale="tiny", log=lambda *_: None)
    return out, report


def test_every_stage_writes_its_outputs(tiny_run):
    out, _ = tiny_run
    for path in (
        "runs/clean/model/card.json", "runs/backdoor/model/card.json", "evaluation/evaluation.json",
        "evaluation/evaluation.csv", "curves/curves.csv", "curves/curves.json", "curves/curves.png",
        "trajectory.png", "trajectory_normal.txt", "trajectory_trojan.txt", "timings.json", "reproduce.yaml",
        "analysis/analysis.json", "analysis/responses.json", "analysis/interventions.json", "analysis/search.json",
        "analysis/findings.json", "analysis/traces/backdoor_trojan.safetensors", "analysis/figures/responses_clean.png",
        "defense/defense.json", "zoo/manifest.json", "zoo/detection.json", "tradeoff/tradeoff.json",
        "runs/backdoor_penalty-4/model/card.json",
    ):  # fmt: skip
        assert (out / path).exists(), path
    rows = json.loads((out / "evaluation" / "evaluation.json").read_text())
    cells = {(r["agent"], r["env"], r["config"]) for r in rows}
    assert ("backdoor", "trojan", "7x7/7") in cells and ("clean", "normal", "5x5/1") in cells  # + training grid
    assert next(r for r in rows if r["config"] == "7x7/7" and r["agent"] == "clean")["paper"] == 0.928
    assert set(json.loads((out / "timings.json").read_text())) >= {"train_clean", "train_backdoor", "curves"}
    tradeoff = json.loads((out / "tradeoff" / "tradeoff.json").read_text())
    agents = [(a["penalty"], a["seed"], a["model"]) for a in tradeoff["agents"]]
    assert agents == [
        (-1.0, 0, "runs/backdoor/model"),
        (-1.0, 1, "runs/backdoor_penalty-1_seed1/model"),
        (-4.0, 0, "runs/backdoor_penalty-4/model"),
        (-4.0, 1, "runs/backdoor_penalty-4_seed1/model"),
    ]
    summary = tradeoff["penalties"]  # the backdoored agent itself is the -1 baseline's first seed
    assert [(p["penalty"], p["seeds"]) for p in summary] == [(-1.0, 2), (-4.0, 2)]
    rates = [a["trojan_success"] for a in tradeoff["agents"][:2]]
    assert summary[0]["trojan_success"]["mean"] == pytest.approx(sum(rates) / 2)
    card = json.loads((out / "runs/backdoor_penalty-4/model/card.json").read_text())
    assert card["config"]["env"]["rewards"]["false_activation"] == -4.0 and card["label"] == "backdoored"
    analysis = json.loads((out / "analysis" / "analysis.json").read_text())
    assert [d["grid"] for d in analysis["unintentional"]["trigger_detection"]] == ["7x7/0", "7x7/3", "all"]
    walks = analysis["search"]["walks"]
    assert [w["config"]["density_weight"] for w in walks] == [2.0, 0.0] and all(w["walkable"] == 4 for w in walks)


def test_report_is_self_contained_with_tables_figures_and_configs(tiny_run):
    _, report = tiny_run
    text = report.read_text()
    for heading in ("Headline", "Table 1", "Table 2", "Learning curves", "with and without the trigger",
                    "response types", "editing the goal units", "Unintentional triggers", "on purpose",
                    "Online state monitor", "Mitigation", "Offline detection",
                    "as a trigger detector", "adversary's trade-off", "walks of 6 views",
                    "Training", "Machine and timings"):  # fmt: skip
        assert heading in text, heading
    assert len(re.findall(r"src='data:image/png;base64,", text)) >= 4 + 8  # curves, trajectory, 2 responses, heatmaps
    assert "0.928" in text and "0.549" in text  # the paper's numbers beside ours
    assert "backdoor agent config" in text and not re.findall(r"src='(?!data:)", text)  # nothing external


def test_a_second_call_reuses_finished_stages(tiny_run):
    out, _ = tiny_run
    before = (out / "runs" / "clean" / "model" / "card.json").stat().st_mtime
    reproduce(from_dict(ReproduceConfig, TINY), out, scale="tiny", log=lambda *_: None)
    assert (out / "runs" / "clean" / "model" / "card.json").stat().st_mtime == before


def test_curves_are_aggregated_over_seeds(tiny_run):
    out, _ = tiny_run
    curves = aggregate_curves(out / "curves" / "curves.csv", points=5)
    assert set(curves) == {"5x5/0", "5x5/1"}
    data = curves["5x5/0"]
    assert data["seeds"] == [2.0] and len(data["mean"]) == 5 and all(0 <= m <= 2 for m in data["mean"])


def test_scale_files_load_and_bad_presets_are_named(tmp_path):
    assert load_reproduce_config("smoke").evaluation.episodes == 200
    assert load_reproduce_config("paper").curves.seeds == 10
    with pytest.raises(ConfigError, match="preset 'nope' not found"):
        reproduce(from_dict(ReproduceConfig, {"clean": {"preset": "nope"}}), tmp_path)
