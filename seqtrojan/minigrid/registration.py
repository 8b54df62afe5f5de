"""Gymnasium ids of the MiniGrid tasks (entry points are strings: registering imports no MiniGrid module)."""

from __future__ import annotations

import gymnasium as gym

REGISTERED: dict[str, tuple[str, dict]] = {
    "seqtrojan/MiniGridTwoGoals-v0": ("seqtrojan.minigrid.tasks:TwoGoalsEnv", {}),
    "seqtrojan/MiniGridTwoGoals-8x8-v0": ("seqtrojan.minigrid.tasks:TwoGoalsEnv", {"size": 8, "agent_view_size": 7}),
    "seqtrojan/MiniGridTwoGoals-Trojan-v0": ("seqtrojan.minigrid.tasks:make_two_goals_trojan", {}),
    "seqtrojan/MiniGridMemoryS7-Trojan-v0": ("seqtrojan.minigrid.tasks:make_memory_trojan", {"size": 7}),
}
"""id -> (entry point, keyword arguments)"""


def register_minigrid_envs() -> None:
    """Register every id (idempotent)."""
    for env_id, (entry, kwargs) in REGISTERED.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry, kwargs=dict(kwargs))
