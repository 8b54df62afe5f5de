"""A training run named the way the experiment configs name one: a shipped preset (or a YAML file) and overrides
merged into it."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from seqtrojan.config import ExperimentConfig
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml


@dataclass(frozen=True)
class AgentSpec:
    """A training preset (a name in configs/ or a path) and overrides merged into it."""

    preset: str = "clean_s17_h30"
    set: dict[str, Any] = field(default_factory=dict)


def deep_merge(base: dict, update: dict) -> dict:
    """``base`` with ``update`` merged in: nested mappings key by key, anything else replaced (copies)."""
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def experiment_from_spec(spec: AgentSpec, out_dir: Path, name: str, device: str) -> ExperimentConfig:
    """The preset with its overrides, run in ``<out_dir>/<name>`` on ``device``."""
    data = deep_merge(load_yaml(resolve_preset(spec.preset)), spec.set)
    data = deep_merge(data, {"run": {"out_dir": str(out_dir), "name": name, "device": device}})
    return from_dict(ExperimentConfig, data, "")
