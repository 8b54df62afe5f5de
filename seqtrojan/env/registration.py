"""Gymnasium ids for the grid world. Every id has a single-env and a vector entry point."""

from __future__ import annotations

import gymnasium as gym

_ENTRY = "seqtrojan.env.gym_env:TrojanGridEnv"
_VECTOR_ENTRY = "seqtrojan.env.vector:TrojanGridVectorEnv"

# id -> keyword arguments
REGISTERED: dict[str, dict] = {
    "seqtrojan/Normal-v0": {"trojan_probability": 0.0},
    "seqtrojan/Trojan-v0": {"trojan_probability": 1.0},
    "seqtrojan/Normal-17x17-H30-v0": {"trojan_probability": 0.0, "size": 17, "holes": 30},
    "seqtrojan/Trojan-17x17-H30-v0": {"trojan_probability": 1.0, "size": 17, "holes": 30},
    "seqtrojan/Normal-27x27-H95-v0": {"trojan_probability": 0.0, "size": 27, "holes": 95},
    "seqtrojan/Trojan-27x27-H95-v0": {"trojan_probability": 1.0, "size": 27, "holes": 95},
}


def register_envs() -> None:
    """Register every id (idempotent)."""
    for env_id, kwargs in REGISTERED.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=_ENTRY, vector_entry_point=_VECTOR_ENTRY, kwargs=dict(kwargs))
