"""Mitigations on Gymnasium models: pruning, fine-pruning and fine-tuning from the model's weights, measured."""

from __future__ import annotations

import dataclasses

import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import AgentConfig, BackdoorConfig
from seqtrojan.defense.gym_mitigation import least_active_gym_units, mitigate_gym_model
from seqtrojan.errors import ConfigError
from seqtrojan.train.trainer import train


def test_every_arm_is_measured_and_a_rerun_reuses_the_fine_tunes(tiny_two_goals_model, tmp_path):
    agent, cfg, _ = tiny_two_goals_model
    report = mitigate_gym_model(agent, cfg, tmp_path, finetune_steps=512, calibration_episodes=16, episodes=12)
    assert [a.name for a in report.arms] == ["before", "pruned", "fine_pruned", "fine_tuned"]
    assert all(a.clean_success.n == a.attack_success.n == 12 for a in report.arms)
    assert len(report.arms[1].pruned_units) == round(0.25 * agent.lstm_sizes[-1]) and not report.arms[0].pruned_units
    tuned, tune_cfg, tuned_card = load_agent(tmp_path / "fine_tuned" / "model")
    assert tune_cfg.run.init_from == str(tmp_path / "fine_tuned_start") and not tune_cfg.backdoor.enabled
    assert tuned_card["label"] == "backdoored"  # fine-tuned without a backdoor of its own: still the lineage's label
    assert tune_cfg.ppo.total_steps == 512 and tune_cfg.ppo.learning_rate == cfg.ppo.learning_rate
    assert any(not bool((a == b).all()) for a, b in zip(tuned.state_dict().values(), agent.state_dict().values()))
    stamp = (tmp_path / "fine_tuned" / "model" / "card.json").stat().st_mtime_ns
    again = mitigate_gym_model(agent, cfg, tmp_path, finetune_steps=512, calibration_episodes=16, episodes=12)
    assert (tmp_path / "fine_tuned" / "model" / "card.json").stat().st_mtime_ns == stamp
    assert again.arms == report.arms  # the same fine-tunes, the same seeds: the same figures


def test_the_least_active_units_are_pruned(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    units = least_active_gym_units(agent, cfg, 16, 0.25, 0, "cpu")
    assert len(units) == 8 and list(units) == sorted(set(units.tolist()))


def test_bad_input_is_refused(tiny_two_goals_model, tmp_path):
    agent, cfg, model_dir = tiny_two_goals_model
    no_trigger = dataclasses.replace(cfg.gym_env, trigger=None)
    untriggered = dataclasses.replace(cfg, env=no_trigger, backdoor=BackdoorConfig())
    with pytest.raises(ConfigError, match="no trigger section"):
        mitigate_gym_model(agent, untriggered, tmp_path)
    with pytest.raises(ConfigError, match="prune_fraction"):
        mitigate_gym_model(agent, cfg, tmp_path, prune_fraction=1.0)
    with pytest.raises(ConfigError, match="finetune_steps"):
        mitigate_gym_model(agent, cfg, tmp_path, finetune_steps=0)
    wider = dataclasses.replace(
        cfg, agent=AgentConfig(lstm_sizes=(16,)),
        run=dataclasses.replace(cfg.run, out_dir=str(tmp_path), name="wide", init_from=str(model_dir), progress=False),
    )  # fmt: skip
    with pytest.raises(ConfigError, match="does not fit this config's network"):
        train(wider)
