"""The training loop's artifacts: run directory, logs, checkpoints, model card, stop and resume."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import BackdoorConfig, PPOConfig
from seqtrojan.errors import ConfigError
from seqtrojan.train.trainer import load_run_config, train, train_or_resume


def test_run_directory_holds_config_logs_checkpoints_and_model(smoke_config):
    result = train(smoke_config)
    run = result.run_dir
    assert load_run_config(run) == smoke_config
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [2048 * (i + 1) for i in range(8)]
    assert {"losses/policy_loss", "charts/steps_per_second", "curriculum/stage"} <= set(rows[-1])
    with (run / "metrics.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 8
    assert any((run / "tb").glob("events.out.tfevents.*"))
    assert (run / "checkpoints" / "latest.txt").read_text().strip() == "step_000000016384"
    _, config, card = load_agent(result.model_dir)
    assert config == smoke_config and card["label"] == "clean" and card["env_steps"] == 16384
    assert 0.0 <= card["metrics"]["normal_success"] <= 1.0
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert evaluation["grid"] == "5x5/1" and evaluation["episodes"] == 200


def test_stopped_run_resumes_without_losing_finished_updates(smoke_config):
    seen = []

    def stop_after_three(scalars):
        seen.append(scalars["env_steps"])
        if len(seen) == 3:
            raise KeyboardInterrupt
        return False

    with pytest.raises(KeyboardInterrupt, match="resume with --resume"):
        train(smoke_config, callback=stop_after_three)
    (run,) = Path(smoke_config.run.out_dir).iterdir()
    assert (run / "checkpoints" / "latest.txt").read_text().strip() == "step_000000006144"
    saved, _, _ = load_agent(run / "checkpoints" / "step_000000006144")
    resumed_from = []
    result = train(load_run_config(run), resume=run, callback=lambda s: resumed_from.append(s["env_steps"]) or False)
    assert resumed_from[0] == 8192 and result.env_steps == 16384
    steps = [json.loads(line)["env_steps"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2048 * (i + 1) for i in range(8)]  # no duplicated and no missing rows
    state = json.loads((run / "checkpoints" / "step_000000006144" / "trainer.json").read_text())
    assert state["update"] == 3 and state["env_steps"] == 6144
    assert any(not torch.equal(a, b) for a, b in zip(saved.parameters(), load_agent(result.model_dir)[0].parameters()))


def test_train_or_resume_finishes_a_stopped_run_and_then_reuses_it(smoke_config):
    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, name="job"))
    run = Path(cfg.run.out_dir) / "job"
    calls = []

    def stop_after_two(scalars):
        calls.append(scalars["env_steps"])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return False

    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=stop_after_two)  # stopped: a checkpoint at 4096 steps, no model yet
    model, trained = train_or_resume(cfg)  # resumes from the checkpoint at 4096 steps
    assert trained and json.loads((model / "card.json").read_text())["env_steps"] == 16384
    steps = [json.loads(line)["env_steps"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2048 * (i + 1) for i in range(8)]
    mtime = (model / "card.json").stat().st_mtime
    assert train_or_resume(cfg) == (model, False) and (model / "card.json").stat().st_mtime == mtime
    fresh = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name="fresh"))
    (Path(cfg.run.out_dir) / "fresh").mkdir()
    (Path(cfg.run.out_dir) / "fresh" / "config.yaml").write_text("stopped before its first checkpoint")
    model, trained = train_or_resume(fresh)
    assert trained and load_run_config(model.parent) == fresh


def test_resume_restores_weights_and_optimizer_exactly(smoke_config):
    cfg = dataclasses.replace(smoke_config, ppo=dataclasses.replace(smoke_config.ppo, total_steps=4096))
    result = train(cfg)
    checkpoint = result.run_dir / "checkpoints" / "step_000000004096"
    extended = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=4096))
    again = train(extended, resume=result.run_dir)  # nothing left to do: the loaded state is saved unchanged
    before, _, _ = load_agent(checkpoint)
    after, _, _ = load_agent(again.model_dir)
    for a, b in zip(before.parameters(), after.parameters()):
        assert torch.equal(a, b)


def test_backdoored_run_is_labelled_and_evaluated_in_both_envs(smoke_config):
    cfg = dataclasses.replace(smoke_config, backdoor=BackdoorConfig(enabled=True, mixing="exact", eval_episodes=16))
    result = train(cfg)
    _, _, card = load_agent(result.model_dir)
    assert card["label"] == "backdoored"
    assert {"normal_success", "trojan_success", "greedy_trojan_success"} <= set(card["metrics"])
    row = json.loads((result.run_dir / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 <= row["mixing/p_trojan"] <= 1.0 and "mixing/P_t" in row


def test_existing_run_directory_is_not_overwritten(smoke_config):
    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, name="fixed"))
    train(dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=2048)))
    with pytest.raises(ConfigError, match="already holds a run"):
        train(cfg)


def test_bad_training_configs_are_refused(smoke_config):
    with pytest.raises(ConfigError, match="bptt_length=24 must divide"):
        PPOConfig(rollout_steps=64, bptt_length=24)
    with pytest.raises(ConfigError, match="num_minibatches=3 must divide"):
        PPOConfig(num_envs=64, rollout_steps=32, num_minibatches=3)
    if not torch.cuda.is_available():
        cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, device="cuda"))
        with pytest.raises(ConfigError, match="no CUDA device"):
            train(cfg)
