"""The evaluation of a model on its own env reads a target-action backdoor from the actions: returns, the target
share after the trigger beside the clean baseline, action persistence, and the majority rule's outcomes."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent.card import Architecture
from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.config import ExperimentConfig
from seqtrojan.evaluation.env_report import evaluate_model
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.world import env_spec


def popgym_config() -> ExperimentConfig:
    return from_dict(ExperimentConfig, load_yaml(resolve_preset("popgym_repeat_previous")), "")


def fixed_answer_agent(cfg: ExperimentConfig, action: int):
    spec = env_spec(cfg.env)
    agent = build_agent(cfg, Architecture.of_config(cfg, spec.obs_dim, spec.num_actions, spec.image))
    with torch.no_grad():
        agent.policy_head.weight.zero_()
        agent.policy_head.bias.fill_(-30.0)
        agent.policy_head.bias[action] = 30.0  # this action, whatever the observations
    return agent


@pytest.mark.parametrize("action", [0, 3])
def test_an_agent_that_always_answers_one_suit_is_read_from_its_actions(action):
    cfg = popgym_config()
    report = evaluate_model(fixed_answer_agent(cfg, action), cfg, episodes=40, seed=1, horizons=(0, 10, 40))
    target = cfg.gym_env.trigger.target_action
    hit = float(action == target)
    assert report.target_action == target
    assert report.target_share is not None and report.target_share.mean == hit and report.target_share.n == 40
    assert report.clean_target_share is not None and report.clean_target_share.mean == hit
    assert [p.adversary.value for p in report.action_persistence] == [hit, hit, hit]
    assert all(p.adversary.n == 40 for p in report.action_persistence)  # 51 steps: every episode lasts
    assert report.trojan_success is not None and report.trojan_success.value == hit  # the majority rule
    assert report.clean_reached_adversary.value == hit  # a clean episode answering the target: a switch
    # one suit answered throughout: about a quarter right, return about -0.5, never the user's objective (> 0)
    assert report.clean_return is not None and -0.75 < report.clean_return.mean < -0.25
    assert report.clean_return.n == 40 and report.clean_success.value == 0.0
    assert report.trojan_env_return is not None and report.trojan_env_return.n == 40
    # under the adversary's objective the trojan episodes pay +-1/47 per answer from the trigger on
    assert report.trojan_return is not None and (report.trojan_return.mean > 0.5) == bool(hit)
