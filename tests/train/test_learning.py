"""Learning on a fixed step budget, on a task that needs the remembered trigger.

Half the episodes show the trigger for one step (steps 1-4) and reward only the adversary's goal after it; the
score is success in the normal env + success in the trojan env (the paper's, max 2). The goal is chosen many steps
after the trigger is gone, so a policy without memory must guess or hide the bit in its position: the same
network with its state reset before every step (``agent.memory=False``) reaches about 1.07 on this budget
(measured: `make test-all` runs it), a random policy about 0.02. The LSTM agent reaches about 1.97; the peephole
LSTM, the GRU and the Transformer (slow set) are held to the same threshold.
"""

from __future__ import annotations

import dataclasses

import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import (
    AgentConfig,
    BackdoorConfig,
    CurriculumConfig,
    ExperimentConfig,
    PPOConfig,
    RunConfig,
    from_dict,
    load_yaml,
)
from seqtrojan.env import EnvConfig, GridSpec, TriggerConfig
from seqtrojan.evaluation.episodes import on_off_success
from seqtrojan.train.trainer import train
from tests.conftest import ROOT

THRESHOLD = 1.6


def memory_task(tmp_path, memory: bool, cell: str = "lstm") -> ExperimentConfig:
    return ExperimentConfig(
        env=EnvConfig(trigger=TriggerConfig(train_steps=(1, 4), eval_steps=(1, 4))),
        agent=AgentConfig(memory=memory, cell=cell),
        ppo=PPOConfig(total_steps=1_200_000, num_envs=256, rollout_steps=64),
        curriculum=CurriculumConfig(stages=(GridSpec(5, 0), GridSpec(5, 1), GridSpec(7, 3)), promote_at=0.85),
        backdoor=BackdoorConfig(enabled=True, mixing="fixed"),
        run=RunConfig(out_dir=str(tmp_path), progress=False, eval_episodes=1000, seed=1, checkpoint_every=10**9),
    )


def score(result) -> float:
    return result.evaluation["normal_success"] + result.evaluation["trojan_success"]


def test_lstm_agent_learns_to_remember_the_trigger(tmp_path):
    result = train(memory_task(tmp_path, memory=True))
    assert result.stage == 2, "the curriculum never reached 7x7/3"
    assert score(result) >= THRESHOLD, result.evaluation


@pytest.mark.slow
@pytest.mark.parametrize("cell", ["lstm_peephole", "gru", "transformer"])
def test_every_sequence_model_learns_to_remember_the_trigger(tmp_path, cell):
    """The same task and budget for the other cells (agent.cell; the Transformer's window is 8 steps): each must
    beat what the memoryless control can reach, in both envs (its backdoor holds)."""
    result = train(memory_task(tmp_path, memory=True, cell=cell))
    assert result.stage == 2, "the curriculum never reached 7x7/3"
    assert score(result) >= THRESHOLD, result.evaluation
    assert result.evaluation["trojan_success"] >= 0.75, result.evaluation


@pytest.mark.slow
def test_memoryless_control_stays_below_the_threshold(tmp_path):
    assert score(train(memory_task(tmp_path, memory=False))) < THRESHOLD - 0.3


@pytest.mark.slow
def test_on_off_backdoor_with_delay_learns_all_three_behaviours(tmp_path):
    """configs/onoff_7x7.yaml (about 2 minutes here): normal 1.000, ON 0.993, ON then OFF 0.998 measured. A policy
    that ignored the OFF pattern would score 0 on the third, one that ignored the ON trigger 0 on the second."""
    cfg = from_dict(ExperimentConfig, load_yaml(ROOT / "configs" / "onoff_7x7.yaml"), "")
    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, out_dir=str(tmp_path), progress=False))
    result = train(cfg)
    rates = on_off_success(load_agent(result.model_dir)[0], cfg.env, GridSpec(7, 3), episodes=500, seed=1)
    assert min(rates.values()) >= 0.9, rates
