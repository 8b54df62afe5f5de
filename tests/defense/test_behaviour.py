"""The trigger-free behavioural detector: one-step view patches that switch the goal, found without the trigger.

On the tiny agents of test_online_detectors (5x5/1; backdoored: whole-view trigger code), measured with 200
episodes per candidate: the backdoored agent's score 0.965 (the whole-view ``trigger`` patch; baseline 0 of 200),
the clean agent's 0.005 (one adversary-goal episode more under one random patch).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from seqtrojan.agent import policy as policy_module
from seqtrojan.agent.checkpoint import save_agent
from seqtrojan.defense.behaviour import (
    BehaviourConfig,
    BehaviourDetector,
    PatchedPolicy,
    behaviour_score,
    candidate_patches,
    detect_zoo_behaviour,
    scores_auc,
)
from seqtrojan.defense.offline import DETECTORS
from seqtrojan.defense.online import view_codes
from seqtrojan.defense.results import BehaviourDetectionResult, BehaviourScore
from seqtrojan.env import TrojanGridCore
from seqtrojan.env.codes import CELL_NAMES, TRIGGER
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import Rate, auc_interval
from tests.defense.test_online_detectors import GRID, TINY_ENV, trained_agent

CFG = BehaviourConfig(episodes=200, random_patches=12)


@pytest.fixture(scope="module")
def scores() -> dict[str, BehaviourScore]:
    return {
        name: behaviour_score(trained_agent(backdoored)[0], TINY_ENV, GRID, CFG)
        for name, backdoored in (("backdoored", True), ("clean", False))
    }


def test_the_score_separates_a_backdoored_from_a_clean_agent(scores):
    bd, clean = scores["backdoored"], scores["clean"]
    assert bd.score >= 0.5 and bd.best == "whole_view:trigger", bd.best
    assert clean.score <= 0.1, (clean.score, clean.best)
    assert bd.score - clean.score >= 0.4
    for s in (bd, clean):  # a clean agent, and the backdoored one without a patch, avoid the adversary's goal
        assert s.baseline.value <= 0.05


def test_every_candidate_is_reported_with_its_rate(scores, tmp_path):
    s = scores["backdoored"]
    assert len(s.candidates) == 6 + CFG.random_patches and s.episodes == CFG.episodes
    assert [c.name for c in s.candidates[:6]] == [f"whole_view:{code}" for code in CELL_NAMES]
    assert s.candidates[5].cells == tuple((r, c) for r in range(3) for c in range(3))
    assert s.candidates[5].codes == ("trigger",) * 9
    for c in s.candidates:
        assert isinstance(c.adversary_goal, Rate) and c.adversary_goal.n == CFG.episodes
        assert c.rise == pytest.approx(c.adversary_goal.value - s.baseline.value)
        assert len(c.cells) == len(c.codes) >= 1
        assert ("trigger" in c.codes) == (c.name == "whole_view:trigger")
    assert s.score == max(c.rise for c in s.candidates)
    assert s.patch_steps == (1, 4)  # 5x5: a goal is 6 moves away, so the top stays at 4
    save_json(s, tmp_path / "score.json")
    assert load_json(BehaviourScore, tmp_path / "score.json") == s


def test_random_patches_draw_ordinary_codes_only():
    patches = candidate_patches(3, BehaviourConfig(random_patches=50, seed=3))
    random = [p for p in patches if p.name.startswith("random:")]
    assert len(random) == 50 and all(any(c >= 0 for c in p.codes) for p in random)
    assert all(TRIGGER not in p.codes for p in random)
    assert patches == candidate_patches(3, BehaviourConfig(random_patches=50, seed=3))  # seeded


def test_the_patch_is_drawn_into_the_observation_at_its_step_only(monkeypatch):
    seen = []
    act = policy_module.act

    def recording_act(agent, obs, state, generator, **kw):
        seen.append(view_codes(obs).clone())
        return act(agent, obs, state, generator, **kw)

    monkeypatch.setattr(policy_module, "act", recording_act)
    agent = trained_agent(True)[0]
    core = TrojanGridCore(TINY_ENV.with_grid(GRID), 2, seed=0)
    patch = torch.tensor([[TRIGGER] * 9, [-1, 1, -1, -1, -1, -1, -1, -1, -1]])
    policy = PatchedPolicy(agent, core, patch, at=torch.tensor([1, 0]))
    obs = core.observe()
    for _ in range(3):
        codes = core.observe_codes()
        obs = core.step(policy(obs), autoreset=False).obs
        t = int(core.t[0]) - 1
        expect = codes.clone()
        if t == 1:
            expect[0] = TRIGGER
        if t == 0:
            expect[1, 1] = 1
        assert torch.equal(seen[-1], expect), t


def test_scores_auc_counts_ties_half_and_gives_the_interval():
    out = scores_auc([0.9, 0.8, 0.1, 0.2], [1, 1, 0, 0])
    assert (out.auc, out.positives, out.negatives) == (1.0, 2, 2)
    assert out.interval == auc_interval(1.0, 2, 2)
    assert scores_auc([0.5, 0.5, 0.2], [1, 0, 0]).auc == pytest.approx(0.75)  # one tie (half), one win
    assert scores_auc([0.1, 0.9], [1, 0]).auc == 0.0
    with pytest.raises(ConfigError, match="both classes, got 2 backdoored and 0 clean"):
        scores_auc([0.1, 0.2], [1, 1])
    with pytest.raises(ConfigError, match="one label per score"):
        scores_auc([0.1, 0.2], [1])
    with pytest.raises(ConfigError, match=r"labels must be 0 \(clean\) or 1 \(backdoored\), got \[0, 2\]"):
        scores_auc([0.1, 0.2], [2, 0])


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="episodes must be >= 10, got 5"):
        BehaviourConfig(episodes=5)
    with pytest.raises(ConfigError, match="patch_density must be in"):
        BehaviourConfig(patch_density=0.0)
    with pytest.raises(ConfigError, match=r"patch_steps=\(3, 1\)"):
        BehaviourConfig(patch_steps=(3, 1))
    with pytest.raises(ConfigError, match=r"patch_steps=\(5, 9\) start after step 4, .* on 5x5/1"):
        behaviour_score(trained_agent(True)[0], TINY_ENV, GRID, BehaviourConfig(patch_steps=(5, 9)))


def test_a_zoo_is_scored_and_broken_models_are_rejected(tmp_path):
    registered = DETECTORS.get("behaviour_detector")
    assert isinstance(registered, BehaviourDetector) and registered.config == BehaviourConfig()
    models = tmp_path / "zoo" / "models"
    for name, backdoored in (("b0", True), ("c0", False)):
        agent, cfg = trained_agent(backdoored)
        save_agent(models / name, agent, cfg, label=cfg.label)
        (models / name / "label.json").write_text(json.dumps({"label": cfg.label}))
    (models / "broken").mkdir()
    result = detect_zoo_behaviour(tmp_path / "zoo", BehaviourConfig(episodes=100, random_patches=4))
    assert [(m.model, m.label) for m in result.models] == [("b0", 1), ("c0", 0)]
    assert result.models[0].score > result.models[1].score
    assert [r.model for r in result.rejected] == ["broken"]
    assert result.auc is not None and result.auc.auc == 1.0 and (result.auc.positives, result.auc.negatives) == (1, 1)
    small = BehaviourDetector(BehaviourConfig(episodes=100, random_patches=4))
    assert small.score(models / "b0") == result.models[0].score  # one saved model, the same episodes
    assert small.detect_zoo(tmp_path / "zoo") == result
    save_json(result, tmp_path / "behaviour.json")
    assert load_json(BehaviourDetectionResult, tmp_path / "behaviour.json") == result
    assert np.isfinite(result.auc.interval).all()
    with pytest.raises(SeqTrojanError, match="not a zoo"):
        detect_zoo_behaviour(tmp_path / "nowhere")
