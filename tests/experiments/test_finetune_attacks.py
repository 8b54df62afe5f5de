"""The attackers who know fine-tuning (``finetune_resistant``, ``trained_longer``): each is the ``sequence``
recipe's trigger with its own change, targets ``fine_tuning`` and applies to the grid world only; a short grid
training with ``finetune_resistant`` runs its penalty, and its term is what moves the weights away from the plain
run's."""

from __future__ import annotations

import dataclasses
import json

import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import ExperimentConfig, FinetuneResistanceConfig
from seqtrojan.experiments.attacks import ATTACKS, FINETUNE_RESISTANCE, HOLES_ABOVE_SEQUENCE
from seqtrojan.train import penalties as pen
from seqtrojan.train.trainer import train
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig


def _base(smoke_config: ExperimentConfig) -> ExperimentConfig:
    return dataclasses.replace(smoke_config, backdoor=dataclasses.replace(smoke_config.backdoor, enabled=True))


def test_the_finetune_resistant_recipe_is_the_sequence_trigger_with_the_penalty(smoke_config):
    attack = ATTACKS.get("finetune_resistant")
    assert attack.targets == "fine_tuning" and attack.grid_only and not attack.from_clean
    base = _base(smoke_config)
    cfg = attack.configure(base)
    assert cfg.grid_env.trigger.sequence == HOLES_ABOVE_SEQUENCE
    assert cfg.grid_env.trigger == ATTACKS.get("sequence").configure(base).grid_env.trigger
    resistance = cfg.attack.finetune_resistance
    assert resistance.enabled and resistance == FinetuneResistanceConfig(**FINETUNE_RESISTANCE)
    # only the trigger and that penalty change: every other attack section and the training budget stay
    plain = ATTACKS.get("sequence").configure(base)
    assert dataclasses.replace(cfg, attack=plain.attack) == plain
    assert f"knob: attack.finetune_resistance.weight, {FINETUNE_RESISTANCE['weight']:g})" in (
        ATTACKS.entry("finetune_resistant").description
    )
    gym = ExperimentConfig(env=GymnasiumEnvConfig(id="seqtrojan/MiniGridTwoGoals-v0", trigger=WrapperTriggerConfig()))
    assert attack.applies_to(cfg) and not attack.applies_to(gym)


def test_the_trained_longer_recipe_doubles_the_sequence_backdoors_env_steps(smoke_config):
    attack = ATTACKS.get("trained_longer")
    assert attack.targets == "fine_tuning" and attack.grid_only and not attack.from_clean
    base = _base(smoke_config)
    cfg, plain = attack.configure(base), ATTACKS.get("sequence").configure(base)
    assert cfg.ppo.total_steps == 2 * base.ppo.total_steps
    assert dataclasses.replace(cfg, ppo=plain.ppo) == plain
    assert not cfg.attack.finetune_resistance.enabled


def _tiny(cfg: ExperimentConfig, name: str) -> ExperimentConfig:
    """Two updates on 5x5/1, no evaluation."""
    return dataclasses.replace(
        cfg,
        ppo=dataclasses.replace(cfg.ppo, total_steps=2 * cfg.ppo.batch_size),
        run=dataclasses.replace(cfg.run, name=name, eval_episodes=0, checkpoint_every=10**9, threads=1),
    )


def _weights(result) -> dict[str, torch.Tensor]:
    return load_agent(result.model_dir)[0].state_dict()


def test_a_grid_training_with_the_recipe_runs_the_penalty_and_its_term_moves_the_weights(smoke_config, monkeypatch):
    """The recipe's run logs the penalty; the same run with the term's value and gradient zeroed (the penalty still
    built, the rollout still recording episode types) ends with the plain sequence run's weights bit for bit, and the
    real run does not: the difference is the term's."""
    base = _base(smoke_config)
    resistant = train(_tiny(ATTACKS.get("finetune_resistant").configure(base), "resistant"))
    rows = [json.loads(line) for line in (resistant.run_dir / "metrics.jsonl").read_text().splitlines()]
    values = [r["penalty/finetune_resistance"] for r in rows]
    assert len(values) == 2 and all(v > 0 for v in values)  # the backdoor's PPO loss after simulated fine-tuning
    plain = train(_tiny(ATTACKS.get("sequence").configure(base), "plain"))

    original = pen.FinetuneResistance.loss
    monkeypatch.setattr(pen.FinetuneResistance, "loss", lambda self, batch: 0.0 * original(self, batch))
    silenced = train(_tiny(ATTACKS.get("finetune_resistant").configure(base), "silenced"))
    a, b, c = _weights(resistant), _weights(plain), _weights(silenced)
    assert all(torch.equal(b[k], c[k]) for k in b)
    assert not all(torch.equal(a[k], b[k]) for k in b)
