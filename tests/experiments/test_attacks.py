"""The adaptive attack recipes built against the trigger search and against several defenses at once: what each
sets, and that their mechanism reaches training (removing it changes the trained weights)."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS, COMBINED_DEFENSES, HOLES_ABOVE_SEQUENCE, resolve_attack
from seqtrojan.train.trainer import train
from seqtrojan.world import make_batched_env


def _recipe(smoke_config: ExperimentConfig, name: str, total_steps: int = 2048, **knob: float) -> ExperimentConfig:
    attack = ATTACKS.get(name)
    cfg = attack.configure(smoke_config)
    if knob:
        assert attack.knob is not None
        cfg = attack.knob.apply(cfg, knob["value"])
    ppo = dataclasses.replace(cfg.ppo, total_steps=total_steps)
    run = dataclasses.replace(cfg.run, name=f"{name}_{knob.get('value', 'default')}", eval_episodes=8)
    return dataclasses.replace(cfg, ppo=ppo, run=run)


def _weights(cfg: ExperimentConfig) -> dict[str, torch.Tensor]:
    agent, _, _ = load_agent(train(cfg).model_dir)
    return agent.state_dict()


def test_the_trainers_env_shows_the_search_decoys_recipes_decoys(smoke_config):
    cfg = _recipe(smoke_config, "search_decoys")
    env = make_batched_env(cfg.env, 512, seed=0, grids=cfg.grids, trojan_probability=0.5)
    shows = env.decoy_step >= 0  # type: ignore[attr-defined]
    assert 0.1 < shows.float().mean().item() < 0.2  # 0.3 of the half that is normal
    assert not make_batched_env(cfg.env, 8, grids=cfg.grids, phase="eval")._decoys  # type: ignore[attr-defined]


def test_decoys_reach_training(smoke_config):
    """The same seed with the decoy share at 0 trains other weights: the decoys are in the rollouts."""
    with_decoys = _weights(_recipe(smoke_config, "search_decoys"))
    without = _weights(_recipe(smoke_config, "search_decoys", value=0.0))
    assert any(not torch.equal(with_decoys[k], without[k]) for k in with_decoys)


def test_the_combined_attacker_knows_every_defense_it_targets_at_once(smoke_config):
    attack = ATTACKS.get("combined")
    assert attack.target_defenses == COMBINED_DEFENSES and attack.grid_only
    cfg = attack.configure(smoke_config)
    assert cfg.env.trigger.sequence == HOLES_ABOVE_SEQUENCE and cfg.env.trigger.decoys.enabled
    assert cfg.attack.state_camouflage.weight == cfg.attack.mahalanobis_camouflage.weight == attack.knob.default
    weaker = attack.knob.apply(cfg, 1.0)
    assert weaker.attack.state_camouflage.weight == weaker.attack.mahalanobis_camouflage.weight == 1.0
    assert weaker.env == cfg.env  # the knob changes the camouflage only
    from seqtrojan.train.penalties import PENALTIES

    on = [name for name, kind in PENALTIES.items() if kind.enabled(cfg)]
    assert on == ["state_camouflage", "mahalanobis_camouflage"]


def test_a_recipe_at_another_knob_value_is_its_own_matrix_row(smoke_config):
    plain = resolve_attack("weight_camouflage")
    assert plain.attack is ATTACKS.get("weight_camouflage") and plain.folder == "weight_camouflage"
    assert plain.value is None and plain.description == ATTACKS.entry("weight_camouflage").description
    strong = resolve_attack("weight_camouflage/2.5")
    assert strong.folder == "weight_camouflage_w2.5" and strong.value == 2.5
    assert strong.description.endswith("[attack.weight_camouflage.weight = 2.5]")
    cfg = strong.attack.configure(smoke_config)
    default = plain.attack.configure(smoke_config)
    assert cfg.attack.weight_camouflage.weight == 2.5 and default.attack.weight_camouflage.weight == 0.5
    assert cfg.attack.weight_camouflage.l2_weight == default.attack.weight_camouflage.l2_weight  # the rest stays
    assert strong.attack.from_clean and strong.attack.targets == "weight_detector"
    assert resolve_attack("search_decoys/0.3").attack.configure(smoke_config).env.trigger.decoys.probability == 0.3
    for bad, message in [
        ("sequence/2", "sequence has no knob to set; recipes with one: "),
        ("weight_camouflage/strong", "the knob value 'strong' is not a number"),
        ("weight_camouflage/-1", "must be a finite number >= 0, got '-1'"),
        ("weight_camouflage/nan", "must be a finite number >= 0"),
        ("weight_camouflage/inf", "must be a finite number >= 0"),
        ("nope/1", "unknown attack 'nope'"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(message)):
            resolve_attack(bad)
