"""A Gymnasium run's model folder: ``model.safetensors`` (the network's tensors) and ``gym_card.json``.

The grid world's model card (:mod:`seqtrojan.agent.checkpoint`) records an :class:`~seqtrojan.config.ExperimentConfig`
for the built-in grid, which cannot describe a Gymnasium env; a Gymnasium run's card records its
:class:`~seqtrojan.train.gym_config.GymTrainConfig` instead, with the architecture, the metrics and the weights'
SHA-256. Never pickle; loading checks the format, the config (every key), the hash and the tensor shapes.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
from pathlib import Path
from typing import Any

from safetensors.torch import load, save_file

from seqtrojan.agent.card import LABELS
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.serde import from_dict, short_repr, to_dict
from seqtrojan.train.gym_config import GymAgentConfig, GymTrainConfig
from seqtrojan.wrappers.observations import CELL_BITS

WEIGHTS = "model.safetensors"
CARD = "gym_card.json"
FORMAT = "seqtrojan-gym-model"
FORMAT_VERSION = 1
MAX_CARD_BYTES = 1 << 20


def minigrid_image(obs_dim: int) -> tuple[int, int, int]:
    """The (rows, cols, channels) of a flat MiniGrid one-hot view (:class:`~seqtrojan.wrappers.MiniGridOneHot`)."""
    cells, rest = divmod(obs_dim, CELL_BITS)
    side = math.isqrt(cells)
    if rest or side * side != cells:
        raise ConfigError(f"{obs_dim} inputs are not a square MiniGrid view of {CELL_BITS} numbers per cell")
    return side, side, CELL_BITS


def build_gym_agent(config: GymTrainConfig, obs_dim: int, num_actions: int) -> RecurrentActorCritic:
    a = config.agent
    return RecurrentActorCritic(
        obs_dim, num_actions, a.lstm_sizes, a.forget_bias, encoder=a.encoder, encoder_activation=a.encoder_activation,
        policy_mlp=a.policy_mlp, value_mlp=a.value_mlp, mlp_activation=a.mlp_activation, cell=a.cell,
        window=a.window, heads=a.heads, conv=a.conv, image=minigrid_image(obs_dim) if a.conv else None,
    )  # fmt: skip


def save_gym_agent(
    folder: str | Path,
    agent: RecurrentActorCritic,
    config: GymTrainConfig,
    *,
    label: str | None = None,
    metrics: dict[str, Any] | None = None,
    env_steps: int | None = None,
    provenance: dict[str, Any] | None = None,
) -> Path:
    """Write ``model.safetensors`` and ``gym_card.json`` into ``folder`` (created); returns the folder.
    ``label``: 'clean' or 'backdoored' (None: the config's); ``provenance``: where an imported agent came from
    (:func:`import_gym_agent`; a trained one's card has none)."""
    label = config.label if label is None else label
    if label not in LABELS:
        raise ConfigError(f"label must be 'clean' or 'backdoored', got {label!r}")
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
        "label": label,
        "architecture": {
            "obs_dim": agent.obs_dim,
            "num_actions": agent.num_actions,
            "lstm_sizes": list(agent.lstm_sizes),
            **({"cell": agent.cell} if agent.cell != "lstm" else {}),
        },
        "env_steps": env_steps,
        "config": to_dict(config),
        "metrics": metrics or {},
        "weights_sha256": hashlib.sha256((folder / WEIGHTS).read_bytes()).hexdigest(),
    }
    if provenance is not None:
        card["provenance"] = provenance
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
    if card.get("label") not in LABELS:
        raise CheckpointError(
            f"{str(card_path)!r}: label must be 'clean' or 'backdoored', got {short_repr(card.get('label'))}"
        )
    try:
        config = from_dict(GymTrainConfig, card.get("config"), "config")
        arch = card["architecture"]
        obs_dim, num_actions = int(arch["obs_dim"]), int(arch["num_actions"])
        if list(arch["lstm_sizes"]) != list(config.agent.lstm_sizes):
            raise ConfigError(f"architecture.lstm_sizes={arch['lstm_sizes']} differs from the config's")
        if arch.get("cell", "lstm") != config.agent.cell:
            raise ConfigError(f"architecture.cell={arch.get('cell', 'lstm')!r} differs from the config's")
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


def import_gym_agent(
    source: str,
    path: str | Path,
    out: str | Path,
    config: GymTrainConfig,
    *,
    label: str | None = None,
    obs_dim: int | None = None,
    num_actions: int | None = None,
    activation: str = "relu",
) -> Path:
    """Import an agent trained on a Gymnasium env (``source`` 'sb3' or 'cleanrl', read as
    :func:`seqtrojan.agent.imports.import_agent` reads it, never unpickled) as a Gymnasium model folder ``out``
    (``model.safetensors`` + ``gym_card.json`` with ``provenance``); returns ``out``.

    ``config`` is the run config whose env the agent acts in: the env it builds (:func:`make_gym_env`: the trigger
    wrapper, then the flat observation, e.g. MiniGrid's one-hot view) must give the agent's observation size and
    its ``Discrete`` action count. ``label`` is what the caller states ('backdoored' needs the config's trigger
    section); None writes 'clean' with ``provenance.label_stated = false``. Nothing is written unless everything
    is accepted."""
    from seqtrojan.agent.imports import provenance_of, read_foreign
    from seqtrojan.train.gym_env import check_spaces, make_gym_env

    imported = read_foreign(source, path, out, label=label, obs_dim=obs_dim, num_actions=num_actions,
                            activation=activation)  # fmt: skip
    env = make_gym_env(config)
    try:
        env_obs, env_actions = check_spaces(env, config.env.id)
    finally:
        env.close()
    if (imported.obs_dim, imported.num_actions) != (env_obs, env_actions):
        raise CheckpointError(
            f"{str(path)!r}: the agent reads {imported.obs_dim} inputs and chooses among {imported.num_actions} "
            f"actions, but the gym config's env ({config.env.id}, observation {config.env.observation!r}) gives "
            f"{env_obs} inputs and {env_actions} actions"
        )
    a = imported.agent
    agent_cfg = GymAgentConfig(
        lstm_sizes=a.lstm_sizes, forget_bias=a.forget_bias, encoder=a.encoder, encoder_activation=a.encoder_activation,
        policy_mlp=a.policy_mlp, value_mlp=a.value_mlp, mlp_activation=a.mlp_activation,
    )  # fmt: skip
    stated = label is not None
    backdoor = dataclasses.replace(config.backdoor, enabled=label == "backdoored")
    try:
        cfg = dataclasses.replace(config, agent=agent_cfg, backdoor=backdoor)
    except ConfigError as err:
        raise ConfigError(f"--label backdoored: {err}") from None
    agent = build_gym_agent(cfg, imported.obs_dim, imported.num_actions)
    agent.load_state_dict(dict(imported.tensors), strict=True)  # names and shapes were checked by the reader
    provenance = provenance_of(imported, path, stated)
    return save_gym_agent(out, agent.eval(), cfg, env_steps=imported.env_steps, provenance=provenance)
