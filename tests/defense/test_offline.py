"""Offline detection: size-invariant weight features, held-out scoring, and refusing bad models in a zoo."""

from __future__ import annotations

import hashlib
import json
import pickle
import shutil

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from seqtrojan.agent.checkpoint import build_agent, save_agent
from seqtrojan.cli import main
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
from seqtrojan.defense.results import Prediction
from seqtrojan.env.codes import TRIGGER
from seqtrojan.errors import SeqTrojanError


def tensors_of(agent):
    return {k: v.detach().numpy() for k, v in agent.state_dict().items()}


def test_features_are_the_same_for_every_architecture():
    keys = []
    for sizes in ((64, 32), (32,), (48, 24, 16)):
        cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=sizes))
        feats = weight_features(tensors_of(build_agent(cfg)), 54, "lstm")
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
    assert cross_validated_scores(models, "input_codes", folds=3).roc_auc > 0.95
    scrambled = [type(m)(m.model_id, int(i in (0, 3, 4, 7, 8, 11)), m.features, m.truth) for i, m in enumerate(models)]
    assert cross_validated_scores(scrambled, "input_codes", folds=3).roc_auc < 0.9


def test_pickled_model_in_a_zoo_is_rejected_and_the_rest_is_scored(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo", pickled=True)
    result = detect_zoo(zoo, folds=3)
    assert [r.model for r in result.rejected] == ["zz_pickled"]
    assert "pickle" in result.rejected[0].reason
    scores = {s.group: s for s in result.scores}
    assert set(scores) == {"all", "gate_stats", "spectral", "input_codes"}
    assert scores["all"].models == 12
    for s in scores.values():  # the scores of the out-of-fold predictions, recomputed from their definitions
        y = np.array([r.label for r in s.predictions])
        p = np.array([r.p_backdoored for r in s.predictions])
        pos, neg = p[y == 1], p[y == 0]
        auc = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (len(pos) * len(neg))
        q = np.clip(p, 1e-6, 1 - 1e-6)
        assert s.roc_auc == pytest.approx(auc, abs=1e-12), s.group
        assert s.cross_entropy == pytest.approx(-np.mean(y * np.log(q) + (1 - y) * np.log(1 - q)), rel=1e-9)
        assert s.brier == pytest.approx(np.mean((p - y) ** 2), rel=1e-9)
        assert [r.model for r in s.predictions] == [f"m{i:02d}" for i in range(12)]
    assert (result.clean_models, result.backdoored_models) == (6, 6)
    assert set(result.auc_by_trigger_value) == {"trigger"}
    assert [h.key for h in result.held_out] == ["lstm_sizes", "trigger_value", "curriculum"]
    assert all(h.skipped == (None,) for h in result.held_out)  # this fake zoo records no variation


def spoil(zoo, name, file, edit):
    """A copy of model m00 named ``name`` whose ``file`` (card.json / label.json) is rewritten by ``edit``."""
    folder = zoo / "models" / name
    shutil.copytree(zoo / "models" / "m00", folder)
    path = folder / file
    path.write_text(edit(path.read_text()))


def edit_json(change):
    def edit(text):
        data = json.loads(text)
        change(data)
        return json.dumps(data)

    return edit


def test_malformed_cards_and_labels_are_each_rejected_with_a_reason_and_the_rest_scored(tmp_path, capsys):
    zoo = fake_zoo(tmp_path / "zoo")
    spoil(zoo, "zz_card_not_json", "card.json", lambda text: text[: len(text) // 2])
    spoil(zoo, "zz_card_wrong_types", "card.json", edit_json(lambda c: c.update(tensors=["cells.0.weight_ih"])))
    spoil(zoo, "zz_card_missing_key", "card.json", edit_json(lambda c: c["architecture"].pop("obs_dim")))
    spoil(zoo, "zz_card_metrics_list", "card.json", edit_json(lambda c: c.update(metrics=[0.9])))
    spoil(zoo, "zz_label_list", "label.json", lambda text: json.dumps([json.loads(text)]))
    spoil(zoo, "zz_label_unknown", "label.json", edit_json(lambda t: t.update(label="maybe")))
    spoil(zoo, "zz_label_trigger_string", "label.json", edit_json(lambda t: t.update(trigger="trigger")))
    spoil(zoo, "zz_label_not_json", "label.json", lambda text: "{")
    nan = zoo / "models" / "zz_nan_weights"
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(16,)))
    save_agent(nan, build_agent(cfg), cfg, label="clean")  # saving refuses NaN weights: the file is tampered after
    tensors = load_file(str(nan / "model.safetensors"))
    tensors["cells.0.weight_hh"][0, 0] = float("nan")
    save_file(tensors, str(nan / "model.safetensors"))
    card = json.loads((nan / "card.json").read_text())
    card["weights_sha256"] = hashlib.sha256((nan / "model.safetensors").read_bytes()).hexdigest()
    (nan / "card.json").write_text(json.dumps(card))
    (nan / "label.json").write_text(json.dumps({"label": "clean", "trigger": None}))

    assert main(["zoo", "detect", "--zoo", str(zoo), "--folds", "3"]) == 0
    result = json.loads((zoo / "detection.json").read_text())
    reasons = {r["model"]: r["reason"] for r in result["rejected"]}
    expected = {
        "zz_card_not_json": "not valid JSON", "zz_card_wrong_types": "card.json",
        "zz_card_missing_key": "obs_dim", "zz_card_metrics_list": "metrics must be a mapping",
        "zz_label_list": "must be a JSON object, got list", "zz_label_unknown": "label must be 'clean' or 'backdoored'",
        "zz_label_trigger_string": "trigger must be null or an object",
        "zz_label_not_json": "label.json' is not valid JSON",
        "zz_nan_weights": "NaN or infinite",
    }  # fmt: skip
    assert set(reasons) == set(expected)
    for model, words in expected.items():
        assert words in reasons[model], (model, reasons[model])
        assert "\n" not in reasons[model]
    assert all(s["models"] == 12 for s in result["scores"])  # every good model scored, no bad one
    out = capsys.readouterr().out.splitlines()
    assert sorted(line for line in out if line.startswith("rejected ")) == sorted(
        f"rejected {model}: {reason}" for model, reason in reasons.items()
    )


def test_models_that_have_not_learned_their_task_are_left_out_of_the_scores(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo")
    before = {s.group: s.predictions for s in detect_zoo(zoo, folds=3).scores}
    learned = {"learned_task": True, "clean_success": 0.97}
    spoil(zoo, "zz_learned", "label.json", edit_json(lambda t: t.update(learned)))
    spoil(zoo, "zz_not_learned", "label.json", edit_json(lambda t: t.update(learned_task=False, clean_success=0.31)))
    result = detect_zoo(zoo, folds=3)
    assert [(r.model, r.reason) for r in result.rejected] == [
        ("zz_not_learned", "task not learned (clean, clean success 0.31)")
    ]
    scored = {s.group: [p.model for p in s.predictions] for s in result.scores}
    assert all(models == [p.model for p in before[g]] + ["zz_learned"] for g, models in scored.items())


def test_too_few_models_after_rejections_names_the_rejected_ones(tmp_path):
    zoo = fake_zoo(tmp_path / "zoo", n=4)
    (zoo / "models" / "m01" / "label.json").write_text("[]")
    with pytest.raises(SeqTrojanError, match=r"has 2 clean and 1 backdoored.*1 model\(s\) rejected \(m01: .*got list"):
        detect_zoo(zoo, folds=2)
    (zoo / "zoo.json").write_text("[")
    with pytest.raises(SeqTrojanError, match=r"zoo\.json' is not a zoo config"):
        detect_zoo(zoo, folds=2)


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
    assert carries.roc_auc > 0.95 and [g.value for g in carries.groups] == ["A", "B"]
    assert all(g.models == 20 and g.backdoored == 10 for g in carries.groups)
    local = held_out_group_scores(synthetic_models(flip_in_group_b=True), "lstm_sizes")
    assert local.roc_auc < 0.3  # trained on A, the detector reads B's backdoored models as clean, and back
    assert cross_validated_scores(synthetic_models(flip_in_group_b=True), folds=5).roc_auc < 0.9
    single = held_out_group_scores(synthetic_models(flip_in_group_b=False), "curriculum")  # one value: no test
    assert single.models == 0 and single.skipped == (None,) and single.roc_auc is None and not single.groups


def test_working_and_failed_backdoors_are_scored_apart():
    models = [ZooModel(f"m{i}", label, {}, {}, attack) for i, (label, attack) in
              enumerate([(0, None), (0, None), (1, 0.9), (1, 0.2), (1, 0.6)])]  # fmt: skip
    predictions = [Prediction(m.model_id, m.label, p) for m, p in zip(models, (0.1, 0.5, 0.9, 0.3, 0.7))]
    split = _functional_split(models, predictions, at=0.5)
    assert (split.functional, split.not_functional) == (2, 1)
    assert split.functional_roc_auc == 1.0  # 0.9 and 0.7 above both clean models
    assert split.not_functional_roc_auc == 0.5  # 0.3: above 0.1, below 0.5
