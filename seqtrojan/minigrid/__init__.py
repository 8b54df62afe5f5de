"""MiniGrid tasks for backdoor experiments (docs/own_env.md): the two-goal room and MiniGrid's Memory task, each
with a trigger wrapper, and the adversary objectives they use.

Importing this package imports only :mod:`seqtrojan.minigrid.registration` (``import seqtrojan`` registers the ids
without loading MiniGrid); the names below load :mod:`seqtrojan.minigrid.tasks` and ``minigrid`` on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from seqtrojan.minigrid.registration import REGISTERED, register_minigrid_envs

if TYPE_CHECKING:
    from seqtrojan.minigrid.objectives import minigrid_reward, reach_adversary_object
    from seqtrojan.minigrid.tasks import (
        MiniGridInfo,
        TwoGoalsEnv,
        make_memory_trojan,
        make_two_goals_trojan,
        memory_trigger,
        minigrid_trigger,
        two_goals_trigger,
    )

_LAZY = {
    "minigrid_reward": "seqtrojan.minigrid.objectives",
    "reach_adversary_object": "seqtrojan.minigrid.objectives",
    "MiniGridInfo": "seqtrojan.minigrid.tasks",
    "TwoGoalsEnv": "seqtrojan.minigrid.tasks",
    "make_memory_trojan": "seqtrojan.minigrid.tasks",
    "make_two_goals_trojan": "seqtrojan.minigrid.tasks",
    "memory_trigger": "seqtrojan.minigrid.tasks",
    "minigrid_trigger": "seqtrojan.minigrid.tasks",
    "two_goals_trigger": "seqtrojan.minigrid.tasks",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'seqtrojan.minigrid' has no attribute {name!r}")


__all__ = [
    "REGISTERED",
    "MiniGridInfo",
    "TwoGoalsEnv",
    "make_memory_trojan",
    "make_two_goals_trojan",
    "memory_trigger",
    "minigrid_reward",
    "minigrid_trigger",
    "reach_adversary_object",
    "register_minigrid_envs",
    "two_goals_trigger",
]
