"""The early-stopping rule: a streak of updates on the last stage, then a held-out check; off by default."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from seqtrojan.config import CurriculumConfig, ExperimentConfig, PPOConfig, RunConfig, StopConfig
from seqtrojan.env import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.train.stopping import StopRule
from seqtrojan.train.trainer import train


def _scalars(stage: int, normal: float, n: int = 100, trojan: float | None = None) -> dict:
    out = {f"stages/{stage}/normal_success": normal, f"stages/{stage}/normal_count": n}
    if trojan is not None:
        out |= {f"stages/{stage}/trojan_success": trojan, f"stages/{stage}/trojan_count": n}
    return out


def _rule(monkeypatch, held_out: list[float], **stop) -> StopRule:
    cfg = ExperimentConfig(
        curriculum=CurriculumConfig(stages=(GridSpec(5, 0), GridSpec(5, 1))),
        stop=StopConfig(enabled=True, success=0.9, updates=3, min_episodes=50, **stop),
    )
    rule = StopRule(cfg, torch.device("cpu"))
    answers = iter(held_out)
    monkeypatch.setattr(rule, "_held_out", lambda agent, trojan: next(answers))
    return rule


def test_a_streak_on_the_last_stage_then_a_passing_check_stops(monkeypatch):
    rule = _rule(monkeypatch, [0.95])
    agent = None
    assert not rule.after_update(_scalars(0, 1.0), 0, agent)  # not the last stage
    assert not rule.after_update(_scalars(1, 0.95), 1, agent)
    assert not rule.after_update(_scalars(1, 0.95, n=10), 1, agent)  # too few episodes: the streak starts again
    assert not rule.after_update(_scalars(1, 0.92), 1, agent)
    assert not rule.after_update(_scalars(1, 0.93), 1, agent)
    assert rule.after_update(_scalars(1, 0.91), 1, agent)  # third in a row: the check passes
    assert rule.confirmed == {"normal": 0.95} and rule.checks == 1


def test_a_failing_check_starts_the_count_again(monkeypatch):
    rule = _rule(monkeypatch, [0.85, 0.93])
    stops = [rule.after_update(_scalars(1, 0.95), 1, None) for _ in range(6)]
    assert stops == [False, False, False, False, False, True] and rule.checks == 2


def test_a_backdoored_agent_needs_both_env_types(monkeypatch):
    rule = _rule(monkeypatch, [0.95, 0.95])
    rule.kinds = ("normal", "trojan")
    assert not any(rule.after_update(_scalars(1, 0.95, trojan=0.5), 1, None) for _ in range(5))
    assert [rule.after_update(_scalars(1, 0.95, trojan=0.95), 1, None) for _ in range(3)] == [False, False, True]


def test_training_stops_early_on_an_easy_task_and_says_so(tmp_path):
    cfg = ExperimentConfig(
        env=EnvConfig(size=5, holes=0),
        ppo=PPOConfig(total_steps=2_000_000, num_envs=64, rollout_steps=32),
        run=RunConfig(out_dir=str(tmp_path), progress=False, eval_episodes=100, checkpoint_every=10**9),
        stop=StopConfig(enabled=True, success=0.8, updates=2, min_episodes=20, confirm_episodes=100),
    )
    result = train(cfg)
    evaluation = json.loads((result.run_dir / "evaluation.json").read_text())
    assert evaluation["stopped_early"] and evaluation["env_steps"] < 2_000_000
    assert set(evaluation["stop_confirmed"]) == {"normal"} and evaluation["stop_confirmed"]["normal"] >= 0.8
    assert evaluation["normal_success"] >= 0.7


def test_off_by_default_and_bad_settings_refused():
    assert not ExperimentConfig().stop.enabled
    with pytest.raises(ConfigError, match=r"stop\.success must be in \(0, 1\]"):
        StopConfig(success=1.5)
    with pytest.raises(ConfigError, match=r"stop\.updates must be a positive integer"):
        dataclasses.replace(StopConfig(), updates=0)


def test_a_weight_camouflage_with_a_warm_up_trains_its_whole_budget():
    """The weight camouflage hides the backdoor after its warm-up: a run that stopped once the backdoor worked would
    never hide it, so the stop rule does not apply to it (it does to the same recipe without a warm-up, and to a
    clean run of the same config)."""
    from seqtrojan.config import AttackConfig, BackdoorConfig, WeightCamouflageConfig

    stop = StopConfig(enabled=True)
    warm = AttackConfig(weight_camouflage=WeightCamouflageConfig(weight=0.5, warmup_steps=1000))
    cfg = ExperimentConfig(backdoor=BackdoorConfig(enabled=True), attack=warm, stop=stop, run=RunConfig(init_from="m"))
    assert not StopRule.applies(cfg)
    assert StopRule.applies(dataclasses.replace(cfg, backdoor=BackdoorConfig(enabled=False)))
    now = AttackConfig(weight_camouflage=WeightCamouflageConfig(weight=0.5))
    assert StopRule.applies(dataclasses.replace(cfg, attack=now))
    assert not StopRule.applies(dataclasses.replace(cfg, attack=now, stop=StopConfig()))
