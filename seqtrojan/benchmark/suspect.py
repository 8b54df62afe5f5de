"""What a detector is given of a model: its network and the clean env, never the trigger or the attack.

A zoo model's folder holds more than a detector may read: ``label.json`` (the truth) and a card whose training
config names the trigger, the backdoor's mixing and any penalties. :func:`load_suspect` reads the folder through
the model checks of the zoo and keeps only the network (weights and architecture), architecture facts, and the
env with the attack taken out: a Gymnasium env without its trigger wrapper, the grid world with the default
trigger settings (every model alike). Detectors receive :class:`Suspect` objects and nothing else, so no detector
can read the answer from the files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import EnvSection
from seqtrojan.env.config import EnvConfig, TriggerConfig
from seqtrojan.world.config import GymnasiumEnvConfig


@dataclass(frozen=True)
class ModelFacts:
    """The architecture as anyone holding the model file sees it."""

    obs_dim: int
    num_actions: int
    cell: str
    widths: tuple[int, ...]
    parameters: int


@dataclass(frozen=True)
class Suspect:
    """One model as a detector sees it."""

    model_id: str
    agent: RecurrentActorCritic
    env: EnvSection
    """the env the model acts in, attack taken out (:func:`clean_env`)"""
    facts: ModelFacts


def clean_env(env: EnvSection) -> EnvSection:
    """``env`` without what the attacker chose: a Gymnasium env's trigger wrapper dropped, the grid world's trigger
    settings reset to the defaults (every suspect of a zoo then gets the same ones)."""
    if isinstance(env, GymnasiumEnvConfig):
        return dataclasses.replace(env, trigger=None)
    assert isinstance(env, EnvConfig)
    return dataclasses.replace(env, trigger=TriggerConfig())


def load_suspect(folder: Path) -> Suspect:
    """A zoo model folder as a :class:`Suspect`; a malformed folder is a one-line
    :class:`~seqtrojan.errors.SeqTrojanError` (see :func:`seqtrojan.zoo.build.load_zoo_agent`)."""
    from seqtrojan.zoo.build import load_zoo_agent

    agent, cfg, _ = load_zoo_agent(folder)
    agent.eval()
    facts = ModelFacts(
        agent.obs_dim, agent.num_actions, agent.cell, tuple(agent.lstm_sizes),
        sum(p.numel() for p in agent.parameters()),
    )  # fmt: skip
    return Suspect(folder.name, agent, clean_env(cfg.env), facts)
