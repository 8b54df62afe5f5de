"""The headline agents over several training seeds: one run per seed, per-seed evaluation, spread in the report."""

from __future__ import annotations

import html
import json

import pytest

from seqtrojan.errors import ConfigError
from seqtrojan.experiments.reproduce import ReproduceConfig, reproduce
from seqtrojan.serde import from_dict

TINY_SET = {
    "env": {"size": 5, "holes": 1},
    "ppo": {"total_steps": 4096, "num_envs": 32, "rollout_steps": 32, "num_minibatches": 2, "update_epochs": 1},
    "curriculum": {"stages": [{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]},
    "run": {"eval_episodes": 16, "checkpoint_every": 4096, "progress": False},
}
HEADLINE_ONLY = {
    "clean": {"preset": "clean_s17_h30", "set": TINY_SET},
    "backdoor": {"preset": "trojan_s17_h30", "set": {**TINY_SET, "backdoor": {"enabled": True, "eval_episodes": 8}}},
    "seeds": 2,
    "evaluation": {"configs": "5x5/0,7x7/3", "episodes": 24},
    "curves": None,
    "trajectory": None,
    "analysis": None,
    "defense": None,
}


@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory):
    out = tmp_path_factory.mktemp("seeds")
    report = reproduce(from_dict(ReproduceConfig, HEADLINE_ONLY), out, scale="tiny", log=lambda *_: None)
    return out, report


def test_each_seed_trains_its_own_agents_with_its_own_seed(two_seeds):
    out, _ = two_seeds
    seeds = {}
    for name in ("clean", "backdoor", "clean_seed1", "backdoor_seed1"):
        card = json.loads((out / "runs" / name / "model" / "card.json").read_text())
        seeds[name] = card["seed"]
    assert seeds == {"clean": 0, "backdoor": 0, "clean_seed1": 1, "backdoor_seed1": 1}
    # the skipped stages wrote nothing
    for skipped in ("curves", "analysis", "defense", "trajectory.png"):
        assert not (out / skipped).exists()


def test_summary_holds_each_seed_and_the_report_shows_mean_sd_and_each_value(two_seeds):
    out, report = two_seeds
    rows = json.loads((out / "evaluation" / "evaluation.json").read_text())
    assert sorted({r["seed"] for r in rows}) == [0, 1]
    summary = json.loads((out / "evaluation" / "summary.json").read_text())
    # clean: normal env; backdoored: normal and trojan; 2 configs + the training grid 5x5/1
    assert len(summary) == 3 * 3
    text = report.read_text()
    for cell in summary:
        assert cell["seeds"] == [0, 1]
        per_seed = [r["success"]["rate"] for r in rows if r["agent"] == cell["agent"] and r["env"] == cell["env"]
                    and r["config"] == cell["config"]]  # fmt: skip
        assert cell["success"] == per_seed
        assert cell["mean"] == pytest.approx(sum(per_seed) / 2)
        assert cell["sd"] == pytest.approx(abs(per_seed[0] - per_seed[1]) / 2**0.5)
        shown = f"{cell['mean']:.3f} {html.unescape('&plusmn;')} {cell['sd']:.3f}"
        assert shown in html.unescape(text)
    assert "Over 2 training seeds" in text
    for name in ("clean_seed1", "backdoor_seed1"):
        assert f"<td class='l'>{name}</td>" in text  # the training table lists every seed's run


def test_rerun_reuses_every_seed_and_its_evaluation(two_seeds):
    out, _ = two_seeds
    before = (out / "evaluation" / "seed1.json").read_text()
    stamp = (out / "runs" / "backdoor_seed1" / "model" / "card.json").stat().st_mtime_ns
    logs = []
    reproduce(from_dict(ReproduceConfig, HEADLINE_ONLY), out, scale="tiny", log=logs.append)
    assert (out / "evaluation" / "seed1.json").read_text() == before
    assert (out / "runs" / "backdoor_seed1" / "model" / "card.json").stat().st_mtime_ns == stamp
    assert "training: done (outputs exist), skipped" in logs
    assert not any(line.startswith("training ") or "evaluating" in line for line in logs)


@pytest.mark.parametrize("seeds", [0, -1, 101])
def test_seeds_out_of_range_are_refused(seeds):
    with pytest.raises(ConfigError, match="seeds must be"):
        from_dict(ReproduceConfig, {"seeds": seeds})
