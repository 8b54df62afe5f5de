"""A Gymnasium run's model folder: ``model.safetensors`` (the network's tensors) and ``gym_card.json``.

The grid world's model card (:mod:`seqtrojan.agent.checkpoint`) records an :class:`~seqtrojan.config.ExperimentConfig`
for the built-in grid, which cannot describe a Gymnasium env; a Gymnasium run's card records its
:class:`~seqtrojan.train.gym_config.GymTrainConfig` instead, with the architecture, the metrics and the weights'
SHA-256. Never pickle; loading checks the format, the config (every key), the hash and the tensor shapes.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from pathlib import Path
from typing import Any

from safetensors.torch import load, save_file

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.serde import from_dict, to_dict
from seqtrojan.train.gym_config import GymTrainConfig

WEIGHTS = "model.safetensors"
CARD = "gym_card.json"
FORMAT = "seqtrojan-gym-model"
FORMAT_VERSION = 1
MAX_CARD_BYTES = 1 << 20


def build_gym_agent(config: GymTrainConfig, obs_dim: int, num_actions: int) -> RecurrentActorCritic:
    return RecurrentActorCritic(obs_dim, num_actions, config.agent.lstm_sizes, config.agent.forget_bias)


def save_gym_agent(
    folder: str | Path,
    agent: RecurrentActorCritic,
    config: GymTrainConfig,
    *,
    metrics: dict[str, Any] | None = None,
    env_steps: int | None = None,
) -> Path:
    """Write ``model.safetensors`` and ``gym_card.json`` into ``folder`` (created); returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in agent.state_dict().items()}
    tmp = folder / (WEIGHTS + ".tmp")
    save_file(tensors, str(tmp))
    tmp.replace(folder / WEIGHTS)
    from seqtrojan import __version__

    card = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "seqtrojan_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "label": config.label,
        "architecture": {
            "obs_dim": agent.obs_dim,
            "num_actions": agent.num_actions,
            "lstm_sizes": list(agent.lstm_sizes),
        },
        "env_steps": env_steps,
        "config": to_dict(config),
        "metrics": metrics or {},
        "weights_sha256": hashlib.sha256((folder / WEIGHTS).read_bytes()).hexdigest(),
    }
    (folder / CARD).write_text(json.dumps(card, indent=2))
    return folder


def load_gym_agent(folder: str | Path) -> tuple[RecurrentActorCritic, GymTrainConfig, dict[str, Any]]:
    """(agent in eval mode, its GymTrainConfig, the card) from a folder :func:`save_gym_agent` wrote."""
    folder = Path(folder)
    card_path, weights = folder / CARD, folder / WEIGHTS
    if not card_path.is_file() or not weights.is_file():
        raise CheckpointError(f"{str(folder)!r} is not a Gymnasium model folder (needs {WEIGHTS} and {CARD})")
    if card_path.stat().st_size > MAX_CARD_BYTES:
        raise CheckpointError(f"{str(card_path)!r} is larger than {MAX_CARD_BYTES} bytes")
    try:
        card = json.loads(card_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"cannot read {str(card_path)!r}: {err}") from None
    if not isinstance(card, dict) or card.get("format") != FORMAT or card.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{str(card_path)!r} is not a {FORMAT} card, version {FORMAT_VERSION}")
    try:
        config = from_dict(GymTrainConfig, card.get("config"), "config")
        arch = card["architecture"]
        obs_dim, num_actions = int(arch["obs_dim"]), int(arch["num_actions"])
        if list(arch["lstm_sizes"]) != list(config.agent.lstm_sizes):
            raise ConfigError(f"architecture.lstm_sizes={arch['lstm_sizes']} differs from the config's")
    except (ConfigError, KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{str(card_path)!r}: {err}") from None
    data = weights.read_bytes()
    if hashlib.sha256(data).hexdigest() != card.get("weights_sha256"):
        raise CheckpointError(f"{WEIGHTS} in {str(folder)!r} does not match the SHA-256 recorded in {CARD}")
    agent = build_gym_agent(config, obs_dim, num_actions)
    try:
        agent.load_state_dict(load(data), strict=True)
    except (RuntimeError, ValueError) as err:
        raise CheckpointError(f"{WEIGHTS} in {str(folder)!r} does not fit its card's architecture: {err}") from None
    return agent.eval(), config, card
