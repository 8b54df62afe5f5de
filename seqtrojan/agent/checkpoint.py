"""Model files: weights in safetensors plus a JSON card. Never pickle.

The threat model is a shared-model marketplace, so loading never runs code from the file: safetensors holds only
tensors, and the card is plain JSON. A model folder holds::

    model.safetensors   the network's tensors
    card.json           format, architecture, the full training config (env, trigger, PPO, curriculum, seed),
                        label ("clean" or "backdoored"), metrics, tensor names/shapes and the weights' SHA-256

Loading refuses pickled files (``.pt``, ``.pth``, ``.pkl``, ``.ckpt`` or pickle/zip content), corrupt files, and a
card that does not match its weights, each with a clear :class:`CheckpointError`.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig, from_dict, to_dict
from seqtrojan.errors import CheckpointError, ConfigError

FORMAT = "seqtrojan-model"
FORMAT_VERSION = 1
WEIGHTS = "model.safetensors"
CARD = "card.json"
PICKLE_SUFFIXES = (".pt", ".pth", ".pkl", ".pickle", ".ckpt", ".bin")


def build_agent(config: ExperimentConfig) -> RecurrentActorCritic:
    a = config.agent
    return RecurrentActorCritic(config.env.obs_dim, config.env.num_actions, a.lstm_sizes, a.forget_bias, a.memory)


def save_agent(
    folder: str | Path,
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    label: str,
    metrics: dict[str, Any] | None = None,
    env_steps: int | None = None,
) -> Path:
    """Write ``model.safetensors`` and ``card.json`` into ``folder`` (created); returns the folder."""
    if label not in ("clean", "backdoored"):
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
            "type": "RecurrentActorCritic",
            "obs_dim": agent.obs_dim,
            "num_actions": agent.num_actions,
            "lstm_sizes": list(agent.lstm_sizes),
        },
        "seed": config.run.seed,
        "env_steps": env_steps,
        "config": to_dict(config),
        "metrics": metrics or {},
        "tensors": {k: list(v.shape) for k, v in tensors.items()},
        "weights_sha256": sha256_file(folder / WEIGHTS),
    }
    _write_json(folder / CARD, card)
    return folder


def load_agent(
    folder: str | Path, device: str | torch.device = "cpu"
) -> tuple[RecurrentActorCritic, ExperimentConfig, dict[str, Any]]:
    """Load a model folder; returns (agent in eval mode, its ExperimentConfig, the card)."""
    folder = Path(folder)
    if folder.suffix.lower() in PICKLE_SUFFIXES or (folder.is_file() and folder.suffix != ".safetensors"):
        raise CheckpointError(
            f"refusing to load {str(folder)!r}: pickled model files can run arbitrary code; seqtrojan models are a "
            f"folder with {WEIGHTS} and {CARD}"
        )
    if folder.is_file():
        folder = folder.parent
    card = read_card(folder)
    tensors = read_safetensors(folder / WEIGHTS)
    expected = {k: list(v) for k, v in card["tensors"].items()}
    actual = {k: list(v.shape) for k, v in tensors.items()}
    if expected != actual:
        diff = _first_difference(expected, actual)
        raise CheckpointError(f"card.json does not match {WEIGHTS} in {str(folder)!r}: {diff}")
    digest = sha256_file(folder / WEIGHTS)
    if card.get("weights_sha256") not in (None, digest):
        raise CheckpointError(f"{WEIGHTS} in {str(folder)!r} does not match the SHA-256 recorded in card.json")
    try:
        config = from_dict(ExperimentConfig, card["config"], "config")
    except (ConfigError, KeyError) as err:
        raise CheckpointError(f"card.json in {str(folder)!r} has an invalid config: {err}") from None
    arch = card["architecture"]
    if [arch["obs_dim"], arch["num_actions"], list(arch["lstm_sizes"])] != [
        config.env.obs_dim,
        config.env.num_actions,
        list(config.agent.lstm_sizes),
    ]:
        raise CheckpointError(f"card.json in {str(folder)!r}: architecture {arch} disagrees with its config")
    agent = build_agent(config)
    try:
        agent.load_state_dict(tensors, strict=True)
    except RuntimeError as err:
        raise CheckpointError(
            f"{WEIGHTS} in {str(folder)!r} does not fit the architecture in card.json: {err}"
        ) from None
    return agent.to(device).eval(), config, card


def read_card(folder: Path) -> dict[str, Any]:
    path = folder / CARD
    if not path.is_file():
        raise CheckpointError(f"no {CARD} in {str(folder)!r}: not a seqtrojan model folder")
    try:
        card = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CheckpointError(f"{str(path)!r} is not valid JSON: {err}") from None
    if not isinstance(card, dict) or card.get("format") != FORMAT:
        raise CheckpointError(f"{str(path)!r} is not a seqtrojan model card (format must be {FORMAT!r})")
    if card.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{str(path)!r} has format_version {card.get('format_version')}, expected {FORMAT_VERSION}"
        )
    for key in ("architecture", "config", "tensors", "label"):
        if key not in card:
            raise CheckpointError(f"{str(path)!r} lacks the field {key!r}")
    return card


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    """Load a safetensors file after checking that it is one (and not a pickle or a truncated file)."""
    if not path.is_file():
        raise CheckpointError(f"{str(path)!r} does not exist")
    with path.open("rb") as fh:
        head = fh.read(9)
    if head[:2] == b"PK" or head[:1] == b"\x80":
        raise CheckpointError(f"{str(path)!r} is a pickle/zip file, not safetensors: refusing to load it")
    size = path.stat().st_size
    header_len = int.from_bytes(head[:8], "little") if len(head) >= 8 else -1
    if len(head) < 9 or header_len <= 0 or header_len + 8 > size or head[8:9] != b"{":
        raise CheckpointError(f"{str(path)!r} is not a valid safetensors file (corrupt or truncated)")
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


def _first_difference(expected: dict[str, list[int]], actual: dict[str, list[int]]) -> str:
    for name in sorted(set(expected) | set(actual)):
        if name not in actual:
            return f"tensor {name!r} is listed in the card but missing from the weights"
        if name not in expected:
            return f"tensor {name!r} is in the weights but not in the card"
        if expected[name] != actual[name]:
            return f"tensor {name!r} has shape {actual[name]} but the card says {expected[name]}"
    return "unknown difference"


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False))
    tmp.replace(path)
