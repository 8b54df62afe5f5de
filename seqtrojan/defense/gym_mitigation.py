"""Mitigations on a Gymnasium env's model (``seqtrojan defend`` on such a model): what a defender with the weights
and clean episodes only can do, measured as on the grid world (:mod:`seqtrojan.defense.mitigation`).

* pruned: the least active ``prune_fraction`` of the last layer's units (mean |h| over the model's own normal
  episodes) removed (:func:`~seqtrojan.defense.mitigation.prune_units`);
* fine_pruned: pruned, then fine-tuned;
* fine_tuned: PPO on normal episodes only (the trigger never shown), ``finetune_steps`` env steps from the model's
  weights, with the model's own PPO settings (``run.init_from``).

Each arm is measured on fresh episodes of the config's env: clean success (normal episodes that reached the
user's objective) and attack success (trojan episodes that reached the adversary's), with 95% intervals. A
finished fine-tune in the output folder is reused and a stopped one resumed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import BackdoorConfig, ExperimentConfig
from seqtrojan.defense.mitigation import least_active, prune_units
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate
from seqtrojan.train.gym_evaluation import evaluate_gym, padded_states

GYM_MITIGATION_FILE = "gym_mitigation.json"


@dataclass(frozen=True)
class GymMitigationArm:
    name: str
    """before, pruned, fine_pruned or fine_tuned"""
    clean_success: Rate
    attack_success: Rate
    pruned_units: tuple[int, ...]
    """units of the last layer removed (empty where nothing was pruned)"""


@dataclass(frozen=True)
class GymMitigationReport:
    """``gym_mitigation.json``."""

    model: str
    env_id: str
    finetune_steps: int
    prune_fraction: float
    calibration_episodes: int
    """normal episodes that measured each unit's activity"""
    episodes: int
    """fresh episodes per type and arm"""
    arms: tuple[GymMitigationArm, ...]


def measure_gym(
    agent: RecurrentActorCritic, config: ExperimentConfig, episodes: int, seed: int, device: torch.device | str
) -> tuple[Rate, Rate]:
    """(clean success, attack success) on fresh normal and trojan episodes."""
    normal = evaluate_gym(agent, config, trojan=False, episodes=episodes, seed=seed, device=device)
    trojan = evaluate_gym(agent, config, trojan=True, episodes=episodes, seed=seed, device=device)
    return normal.success, trojan.success


def least_active_gym_units(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    episodes: int,
    fraction: float,
    seed: int,
    device: torch.device | str,
) -> np.ndarray:
    """The ``fraction`` (at least one) of the last layer's units with the smallest mean |h| over normal episodes."""
    run = evaluate_gym(agent, config, trojan=False, episodes=episodes, seed=seed, device=device, record_states=True)
    layers, mask = padded_states(run.episodes)
    return np.sort(least_active(layers[-1][..., : agent.lstm_sizes[-1]], mask, fraction))


def finetune_gym(
    agent: RecurrentActorCritic, config: ExperimentConfig, steps: int, out: Path, name: str, seed: int,
    label: str | None = None,
) -> RecurrentActorCritic:  # fmt: skip
    """PPO on normal episodes only from ``agent``'s weights (saved as ``out/<name>_start`` with ``label``, its
    card's; None: its config's; the fine-tuned model inherits it); the run is ``out/<name>``, reused when finished
    and resumed when stopped."""
    from seqtrojan.agent.checkpoint import load_agent, save_agent
    from seqtrojan.train.trainer import train_or_resume

    start = save_agent(out / f"{name}_start", agent, config, label=label or config.label)
    tune = dataclasses.replace(
        config,
        ppo=dataclasses.replace(config.ppo, total_steps=steps),
        backdoor=BackdoorConfig(enabled=False),
        run=dataclasses.replace(config.run, out_dir=str(out), name=name, seed=seed, init_from=str(start),
                                eval_episodes=0, progress=False),
    )  # fmt: skip
    model_dir, _ = train_or_resume(tune)
    tuned, _, _ = load_agent(model_dir)
    return tuned


def mitigate_gym_model(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    out: Path,
    *,
    model: str = "",
    finetune_steps: int = 100_000,
    prune_fraction: float = 0.25,
    calibration_episodes: int = 200,
    episodes: int = 500,
    seed: int = 0,
    device: torch.device | str = "cpu",
    label: str | None = None,
) -> GymMitigationReport:
    """Every arm of the module docstring, measured (see there). ``label``: the model's card's (None: its
    config's), which the fine-tuned models inherit."""
    if config.gym_env.trigger is None:
        raise ConfigError("the gym config has no trigger section: there is no attack to measure")
    for name, value in (("finetune_steps", finetune_steps), ("calibration_episodes", calibration_episodes),
                        ("episodes", episodes)):  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    if not 0.0 < prune_fraction < 1.0:
        raise ConfigError(f"prune_fraction must be in (0, 1), got {prune_fraction!r}")
    out.mkdir(parents=True, exist_ok=True)
    eval_seed = seed + 1
    units = least_active_gym_units(agent, config, calibration_episodes, prune_fraction, seed, device)
    pruned = prune_units(agent, len(agent.lstm_sizes) - 1, units)
    candidates = {
        "before": (agent, ()),
        "pruned": (pruned, tuple(int(u) for u in units)),
        "fine_pruned": (finetune_gym(pruned, config, finetune_steps, out, "fine_pruned", seed, label),
                        tuple(int(u) for u in units)),
        "fine_tuned": (finetune_gym(agent, config, finetune_steps, out, "fine_tuned", seed, label), ()),
    }  # fmt: skip
    arms = []
    for name, (candidate, removed) in candidates.items():
        clean, attack = measure_gym(candidate.to(device), config, episodes, eval_seed, device)
        arms.append(GymMitigationArm(name, clean, attack, removed))
    return GymMitigationReport(
        model, config.gym_env.id, finetune_steps, prune_fraction, calibration_episodes, episodes, tuple(arms)
    )
