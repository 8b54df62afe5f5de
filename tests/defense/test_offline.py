"""Offline detection: size-invariant weight features, held-out scoring, and refusing bad models in a zoo."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent, save_agent
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig
from seqtrojan.defense.offline import (
    ZooModel,
    _functional_split,
    cross_validated_scores,
    detect_zoo,
    held_out_group_scores,
    load_zoo_features,
    weight_features,
)
from seqtrojan.env.codes import TRIGGER


def tensors_of(agent):
    return {k: v.detach().numpy() for k, v in agent.state_dict().items()}


def test_features_are_the_same_for_every_architecture():
    keys = []
    for sizes in ((64, 32), (32,), (48, 24, 16)):
        cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=sizes))
        feats = weight_features(tensors_of(build_agent(cfg)), 54)
        assert all(np.isfinite(v) for v in feats.values())
        keys.append(set(feats))
    assert keys[0] == keys[1] == keys[2]
    assert {"input_codes/trigger", "spectral/last.forget.hh.effective_rank"} <= keys[0]


def fake_zoo(root, n=12, shift=3.0, pickled=False):
    """Models whose 'backdoored' ones read the trigger code with larger input weights (a planted tell)."""
    (root / "models").mkdir(parents=True)
    for i in range(n):
        backdoored = i % 2 == 1
        cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(16,)), backdoor=BackdoorConfig(enabled=backdoored))
        torch.manual_seed(i)
        agent = build_agent(cfg)
        if backdoored:
            with torch.no_grad():
                agent.cells[0].weight_ih[:, TRIGGER::6] *= shift
        folder = save_agent(root / "models" / f"m{i:02d}", agent, cfg, label=cfg.label)
        trigger = {"value": "trigger"} if backdoored else None
        (folder / "label.json").write_text(json.dumps({"label": cfg.label, "trigger": trigger}))
    if pickled:
        bad = root / "models" / "zz_pickled"
        bad.mkdir()
        (bad / "model.safetensors").write_bytes(pickle.dumps({"evil": 1}))
        (bad / "card.json").write_text((root / "models" / "m00" / "card.json").read_text())
    return root


def test_detector_finds_a_planted_tell_and_not_random_labels(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo", shift=3.0)
    models, rejected = load_zoo_features(zoo)
    assert len(models) == 12 and not rejected
    assert cross_validated_scores(models, "input_codes", folds=3)["roc_auc"] > 0.95
    scrambled = [type(m)(m.model_id, int(i in (0, 3, 4, 7, 8, 11)), m.features, m.truth) for i, m in enumerate(models)]
    assert cross_validated_scores(scrambled, "input_codes", folds=3)["roc_auc"] < 0.9


def test_pickled_model_in_a_zoo_is_rejected_and_the_rest_is_scored(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo", pickled=True)
    result = detect_zoo(zoo, folds=3)
    assert [r["model"] for r in result["rejected"]] == ["zz_pickled"]
    assert "pickle" in result["rejected"][0]["reason"]
    scores = {s["group"]: s for s in result["scores"]}
    assert set(scores) == {"all", "gate_stats", "spectral", "input_codes"}
    assert scores["all"]["models"] == 12
    for s in scores.values():
        assert 0 <= s["roc_auc"] <= 1 and s["cross_entropy"] > 0 and 0 <= s["brier"] <= 1
    assert set(result["auc_by_trigger_value"]) == {"trigger"}
    assert [h["key"] for h in result["held_out"]] == ["lstm_sizes", "trigger_value", "curriculum"]
    assert all(h["skipped"] == [None] for h in result["held_out"])  # this fake zoo records no variation


def test_a_zoo_needs_both_labels(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo", n=4)
    models, _ = load_zoo_features(zoo)
    with pytest.raises(Exception, match=r"at least 2 clean and 2 backdoored models.*has 2 clean and 0 backdoored"):
        cross_validated_scores([m for m in models if m.label == 0])


def synthetic_models(flip_in_group_b: bool, n: int = 40, seed: int = 0) -> list:
    """Half backdoored; feature 'gate_stats/tell' is shifted for backdoored models, in the opposite direction in
    architecture B when ``flip_in_group_b`` (a tell that does not carry over)."""
    rng = np.random.default_rng(seed)
    models = []
    for i in range(n):
        label, arch = i % 2, "AB"[(i // 2) % 2]
        sign = -1.0 if (flip_in_group_b and arch == "B") else 1.0
        feats = {"gate_stats/tell": sign * 3.0 * label + rng.normal(), "gate_stats/noise": rng.normal()}
        models.append(ZooModel(f"m{i}", label, feats, {"variation": {"lstm_sizes": arch}}))
    return models


def test_held_out_groups_tell_a_tell_that_carries_over_from_one_that_does_not():
    carries = held_out_group_scores(synthetic_models(flip_in_group_b=False), "lstm_sizes")
    assert carries["roc_auc"] > 0.95 and [g["value"] for g in carries["groups"]] == ["A", "B"]
    assert all(g["models"] == 20 and g["backdoored"] == 10 for g in carries["groups"])
    local = held_out_group_scores(synthetic_models(flip_in_group_b=True), "lstm_sizes")
    assert local["roc_auc"] < 0.3  # trained on A, the detector reads B's backdoored models as clean, and back
    assert cross_validated_scores(synthetic_models(flip_in_group_b=True), folds=5)["roc_auc"] < 0.9
    single = held_out_group_scores(synthetic_models(flip_in_group_b=False), "curriculum")  # one value: no test
    assert single["models"] == 0 and single["skipped"] == [None] and "roc_auc" not in single


def test_working_and_failed_backdoors_are_scored_apart():
    models = [ZooModel(f"m{i}", label, {}, {}, attack) for i, (label, attack) in
              enumerate([(0, None), (0, None), (1, 0.9), (1, 0.2), (1, 0.6)])]  # fmt: skip
    predictions = [{"p_backdoored": p} for p in (0.1, 0.5, 0.9, 0.3, 0.7)]
    split = _functional_split(models, predictions, at=0.5)
    assert (split["functional"], split["not_functional"]) == (2, 1)
    assert split["functional_roc_auc"] == 1.0  # 0.9 and 0.7 above both clean models
    assert split["not_functional_roc_auc"] == 0.5  # 0.3: above 0.1, below 0.5
