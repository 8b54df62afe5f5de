"""Model files: weights in safetensors plus a JSON card. Never pickle.

The threat model is a shared-model marketplace, so loading never runs code from the file: safetensors holds only
tensors, and the card is plain JSON. A model folder holds::

    model.safetensors   the network's tensors
    card.json           format, architecture, the full training config (env, trigger, PPO, curriculum, seed),
                        label ("clean" or "backdoored"), metrics, tensor names/shapes and the weights' SHA-256

Loading refuses pickled files (``.pt``, ``.pth``, ``.pkl``, ``.ckpt`` or pickle/zip content), corrupt files, and a
card that does not match its weights, each with a clear :class:`CheckpointError`. The card and the safetensors
header are untrusted input: :mod:`seqtrojan.agent.card` validates both (bounded sizes, schema, architecture limits,
card = header = architecture) before any tensor is read or the network is built.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import errno
import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load, load_file, save_file

from seqtrojan.agent.card import (
    CARD,
    FORMAT,
    FORMAT_VERSION,
    LABELS,
    WEIGHTS,
    Architecture,
    ModelCard,
    check_weights,
    parse_card,
    read_card,
    read_header,
)
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.cell_types import is_windowed
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.serde import to_dict
from seqtrojan.world.config import GymnasiumEnvConfig

__all__ = [
    "CARD",
    "FORMAT",
    "FORMAT_VERSION",
    "PICKLE_SUFFIXES",
    "WEIGHTS",
    "ModelCard",
    "architecture_of",
    "build_agent",
    "card_config",
    "load_agent",
    "read_card",
    "read_safetensors",
    "save_agent",
    "sha256_file",
]

PICKLE_SUFFIXES = (".pt", ".pth", ".pkl", ".pickle", ".ckpt", ".bin")


def build_agent(config: ExperimentConfig, architecture: Architecture | None = None) -> RecurrentActorCritic:
    """The network ``config`` describes. The grid world's config fixes its inputs and actions; for a Gymnasium env
    give the ``architecture`` (:meth:`Architecture.of_config` with the env's spaces, or a card's)."""
    arch = architecture if architecture is not None else Architecture.of_config(config)
    a = config.agent
    return RecurrentActorCritic(
        arch.obs_dim, arch.num_actions, a.lstm_sizes, a.forget_bias, a.memory, encoder=a.encoder,
        encoder_activation=a.encoder_activation, policy_mlp=a.policy_mlp, value_mlp=a.value_mlp,
        mlp_activation=a.mlp_activation, cell=a.cell, window=a.window, heads=a.heads, conv=arch.conv,
        image=arch.image, conv_kernels=arch.conv_kernels, conv_strides=arch.conv_strides,
    )  # fmt: skip


def architecture_of(agent: RecurrentActorCritic) -> Architecture:
    """The card's description of ``agent``'s network."""
    return Architecture(
        agent.obs_dim, agent.num_actions, agent.lstm_sizes, encoder=agent.encoder_sizes,
        encoder_activation=agent.encoder_activation, policy_mlp=agent.policy_mlp_sizes,
        value_mlp=agent.value_mlp_sizes, mlp_activation=agent.mlp_activation, cell=agent.cell,
        window=agent.window if is_windowed(agent.cell) else 8,
        heads=agent.attention_heads if is_windowed(agent.cell) else 1, conv=agent.conv_channels,
        image=agent.image if agent.conv_channels else None, conv_kernels=agent.conv_kernels,
        conv_strides=agent.conv_strides,
    )  # fmt: skip


def card_config(config: ExperimentConfig) -> ExperimentConfig:
    """``config`` as a model card records it: a Gymnasium env a config names ``module:Id`` (Gymnasium imports the
    module, which registers ``Id``) by its registered ``Id``, since loading a card never imports a module."""
    env = config.env
    if isinstance(env, GymnasiumEnvConfig) and ":" in env.id:
        return dataclasses.replace(config, env=dataclasses.replace(env, id=env.id.split(":", 1)[1]))
    return config


def save_agent(
    folder: str | Path,
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    label: str,
    metrics: dict[str, Any] | None = None,
    env_steps: int | None = None,
    provenance: dict[str, Any] | None = None,
) -> Path:
    """Write ``model.safetensors`` and ``card.json`` into ``folder`` (created); returns the folder.

    The card is checked with the same rules as loading before anything is written, so a saved model always loads.
    ``provenance`` (where an imported model came from, :mod:`seqtrojan.agent.imports`) is written only when given.
    """
    if label not in LABELS:
        raise ConfigError(f"label must be one of {list(LABELS)}, got {label!r}")
    folder = Path(folder)
    tensors = {k: v.detach().cpu().contiguous() for k, v in agent.state_dict().items()}
    _refuse_non_finite(tensors, f"the weights for {str(folder)!r}")
    from seqtrojan import __version__

    card = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "seqtrojan_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "label": label,
        "architecture": architecture_of(agent).to_card(),
        "seed": config.run.seed,
        "env_steps": env_steps,
        "config": to_dict(card_config(config)),
        "metrics": metrics or {},
        "tensors": {k: list(v.shape) for k, v in tensors.items()},
        "weights_sha256": "0" * 64,
    }
    if provenance is not None:
        card["provenance"] = provenance
    parse_card(json.dumps(card), f"the card for {str(folder)!r}")  # refuse what load_agent would refuse
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / (WEIGHTS + ".tmp")
        save_file(tensors, str(tmp))
        tmp.replace(folder / WEIGHTS)
        card["weights_sha256"] = sha256_file(folder / WEIGHTS)
        _write_json(folder / CARD, card)
    except OSError as err:  # a full disk: the files written before stay whole (each is renamed into place)
        for leftover in (folder / (WEIGHTS + ".tmp"), folder / (CARD + ".tmp")):
            leftover.unlink(missing_ok=True)
        problem = "disk full" if err.errno == errno.ENOSPC else "cannot write"
        raise CheckpointError(f"{problem} while writing the model {str(folder)!r}: {err.strerror or err}") from None
    return folder


def load_agent(
    folder: str | Path, device: str | torch.device = "cpu"
) -> tuple[RecurrentActorCritic, ExperimentConfig, dict[str, Any]]:
    """Load a model folder; returns (agent in eval mode, its ExperimentConfig, the card as a dict).

    The card and the weights' header are validated (:mod:`seqtrojan.agent.card`) before the weights are read and
    before the network is built; the weights must then match the card's SHA-256.
    """
    folder = Path(folder)
    if folder.suffix.lower() in PICKLE_SUFFIXES or (folder.is_file() and folder.suffix != ".safetensors"):
        raise CheckpointError(
            f"refusing to load {str(folder)!r}: pickled model files can run arbitrary code; seqtrojan models are a "
            f"folder with {WEIGHTS} and {CARD}"
        )
    if folder.is_file():
        folder = folder.parent
    card = read_card(folder)
    path = folder / WEIGHTS
    header = read_header(path)
    check_weights(card, header, repr(str(folder)))
    with path.open("rb") as fh:  # size bounded by the validated architecture and header
        data = fh.read(header.file_size + 1)
    validated = header.header_len.to_bytes(8, "little") + header.raw
    if len(data) != header.file_size or not data.startswith(validated):
        raise CheckpointError(f"{str(path)!r} changed while it was being read")
    if hashlib.sha256(data).hexdigest() != card.weights_sha256:
        raise CheckpointError(f"{WEIGHTS} in {str(folder)!r} does not match the SHA-256 recorded in card.json")
    try:
        tensors = load(data)
    except (SafetensorError, ValueError) as err:
        raise CheckpointError(f"{str(path)!r} is corrupt: {err}") from None
    del data
    _refuse_non_finite(tensors, f"{WEIGHTS} in {str(folder)!r}")
    agent = build_agent(card.config, card.architecture)
    try:
        agent.load_state_dict(tensors, strict=True)
    except RuntimeError as err:
        raise CheckpointError(
            f"{WEIGHTS} in {str(folder)!r} does not fit the architecture in card.json: {err}"
        ) from None
    return agent.to(device).eval(), card.config, card.data


def _refuse_non_finite(tensors: dict[str, torch.Tensor], what: str) -> None:
    """A model's weights must be finite numbers: a NaN or infinite weight (a diverged training, a tampered file) is
    refused in one line naming the tensors, before anything is built from or written with them."""
    bad = sorted(k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all()))
    if bad:
        shown = ", ".join(bad[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")
        raise CheckpointError(f"{what} holds NaN or infinite values (in {shown})")


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    """Load a safetensors file after checking that it is one (not a pickle, not truncated, a sane header)."""
    read_header(path)
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(f"{str(path)!r} is corrupt: {err}") from None


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False))
    tmp.replace(path)


def load_start_weights(agent: RecurrentActorCritic, start: RecurrentActorCritic, source: str) -> None:
    """Copy ``start``'s weights into ``agent`` (a run's ``run.init_from``, named ``source`` in the error); weights
    that do not fit the agent's network are refused in one line."""
    try:
        agent.load_state_dict(start.state_dict())
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"run.init_from={source!r} does not fit this config's network: {first}") from None
