"""Decoys (``trigger.decoys``): one-step patches in normal training episodes, drawn as the behaviour detector draws
its candidates, which the attacker who knows that search trains its agent to ignore."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.codes import NUM_CHANNELS
from seqtrojan.env.config import DecoyConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS, HOLES_ABOVE_SEQUENCE
from seqtrojan.serde import from_dict, parse_yaml, to_dict
from tests.env.test_triggers import SEQ3


def decoy_env(probability: float = 0.5, **decoys) -> EnvConfig:
    trigger = dataclasses.replace(SEQ3, decoys=DecoyConfig(probability=probability, **decoys))
    return EnvConfig(size=7, holes=3, trigger=trigger)


def test_decoys_show_only_in_normal_training_episodes_at_the_drawn_rate_and_shape():
    core = TrojanGridCore(decoy_env(0.5), 20_000, seed=3, trojan_probability=0.3)
    shows = core.decoy_step >= 0
    assert not (shows & core.trojan).any()  # never in a trojan episode
    normal = ~core.trojan
    assert abs(shows[normal].float().mean().item() - 0.5) < 0.02
    codes = core.decoy_codes[shows]
    whole = (codes >= 0).all(1) & (codes == codes[:, :1]).all(1)
    assert abs(whole.float().mean().item() - 0.2) < 0.02  # a random decoy fills all 9 cells with one code ~never
    assert (codes >= 0).any(1).all()  # every decoy draws on at least one cell
    random = codes[~whole]
    assert abs((random >= 0).float().mean().item() - 0.5) < 0.02
    assert set(random[random >= 0].unique().tolist()) == {0, 1, 2, 3, 4}  # ordinary codes only, never the trigger's
    assert set(codes[whole][:, 0].unique().tolist()) == set(range(NUM_CHANNELS))  # a whole view: any code


def test_a_decoy_is_drawn_into_the_view_at_its_step_only():
    core = TrojanGridCore(decoy_env(1.0), 64, seed=0, trojan_probability=0.0)
    plain = TrojanGridCore(decoy_env(0.0), 64, seed=0, trojan_probability=0.0)
    stay = torch.zeros(64, dtype=torch.int64)
    for _ in range(6):
        seen, base = core.observe_codes(), plain.observe_codes()
        at = core.decoy_step == core.t
        drawn = at[:, None] & (core.decoy_codes >= 0)
        assert torch.equal(seen[drawn], core.decoy_codes[drawn])
        assert torch.equal(seen[~drawn], base[~drawn])  # elsewhere, and at other steps, the ordinary view
        core.step(stay, autoreset=False)
        plain.step(stay, autoreset=False)


def test_episodes_are_unchanged_by_decoys_but_for_the_view():
    """Layouts, episode types and trigger steps come from the same draws: decoys add draws, they change none."""
    with_decoys = TrojanGridCore(decoy_env(0.6), 256, seed=7, trojan_probability=0.5)
    without = TrojanGridCore(decoy_env(0.0), 256, seed=7, trojan_probability=0.5)
    for name in TrojanGridCore.EPISODE_STATE:
        assert torch.equal(getattr(with_decoys, name), getattr(without, name)), name
    assert not hasattr(without, "decoy_step")  # off: no decoy state at all (the plain env is untouched)


def test_evaluation_never_shows_decoys_and_checkpoints_keep_them():
    assert not TrojanGridCore(decoy_env(1.0), 8, seed=0, phase="eval")._decoys
    core = TrojanGridCore(decoy_env(0.7), 32, seed=1, trojan_probability=0.2)
    for _ in range(5):
        core.step(torch.randint(0, 4, (32,)))
    saved, obs = core.save_state(), core.observe()
    assert set(TrojanGridCore.DECOY_STATE) <= set(saved.tensors)
    other = TrojanGridCore(decoy_env(0.7), 32, seed=99, trojan_probability=0.2)
    assert other.load_state(saved, obs)
    assert torch.equal(other.decoy_codes, core.decoy_codes) and torch.equal(other.decoy_step, core.decoy_step)
    plain = TrojanGridCore(decoy_env(0.0), 32, seed=1, trojan_probability=0.2)
    assert "decoy_step" not in plain.save_state().tensors


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: DecoyConfig(probability=1.5), r"trigger.decoys.probability must be a number in \[0, 1\], got 1.5"),
        (lambda: DecoyConfig(density=0.0), r"trigger.decoys.density must be > 0"),
        (lambda: DecoyConfig(codes=("hole", "lava")), r"trigger.decoys.values has 'lava', not a cell code"),
        (lambda: DecoyConfig(codes=()), r"trigger.decoys.codes must name distinct cell codes"),
        (lambda: EnvConfig(trigger=dataclasses.replace(EnvConfig().trigger, decoys=DecoyConfig(probability=0.1))),
         r"trigger.decoys need a sequence trigger \(two frames or more\)"),
    ],
)  # fmt: skip
def test_bad_decoys_are_one_named_error(make, message):
    with pytest.raises(ConfigError, match=message):
        make()


def test_decoys_load_from_yaml_and_round_trip():
    text = """
trigger:
  sequence:
    - {cells: [[0, 0], [0, 2]], values: [hole, hole]}
    - {cells: [[0, 1]], values: [hole]}
  decoys: {probability: 0.3, density: 0.4}
"""
    env = from_dict(EnvConfig, parse_yaml(text), "env")
    assert env.trigger.decoys == DecoyConfig(probability=0.3, density=0.4)
    assert from_dict(EnvConfig, to_dict(env)) == env
    assert from_dict(EnvConfig, parse_yaml("trigger: {value: trigger}")).trigger.decoys == DecoyConfig()


def test_the_search_decoys_recipe_is_the_sequence_trained_against_the_behaviour_search():
    from seqtrojan.config import ExperimentConfig

    attack = ATTACKS.get("search_decoys")
    cfg = attack.configure(ExperimentConfig())
    assert cfg.env.trigger.sequence == HOLES_ABOVE_SEQUENCE
    assert cfg.env.trigger.decoys.probability == attack.knob.default > 0
    assert attack.targets == "behaviour_detector" and attack.grid_only
    assert attack.knob.apply(cfg, 0.6).env.trigger.decoys.probability == 0.6
    sequence = ATTACKS.get("sequence").configure(ExperimentConfig())
    assert dataclasses.replace(cfg.env.trigger, decoys=DecoyConfig()) == sequence.env.trigger
