"""Bring your own env: a Gymnasium wrapper that turns any env into normal and trojan episodes (docs/own_env.md).

env = TriggerWrapper(gym.make("MiniGrid-MemoryS7-v0"), MiniGridPatch(cells=[(0, 0), (0, 1)]), objective)
"""

from __future__ import annotations

from seqtrojan.wrappers.actions import FirstActions
from seqtrojan.wrappers.objectives import ADVERSARY_OBJECTIVES, Objective, same_as_env
from seqtrojan.wrappers.observations import FlattenFloat, MiniGridOneHot
from seqtrojan.wrappers.patches import BoxPatch, FunctionPatch, MiniGridPatch, Patch, VectorPatch
from seqtrojan.wrappers.trigger import TriggerWrapper
from seqtrojan.wrappers.vector import (
    FinishedEpisode,
    finished_episodes,
    set_trojan_probability,
    trigger_vector_env,
    trojan_probabilities,
)

__all__ = [
    "ADVERSARY_OBJECTIVES",
    "BoxPatch",
    "FinishedEpisode",
    "FirstActions",
    "FlattenFloat",
    "FunctionPatch",
    "MiniGridOneHot",
    "MiniGridPatch",
    "Objective",
    "Patch",
    "TriggerWrapper",
    "VectorPatch",
    "finished_episodes",
    "same_as_env",
    "set_trojan_probability",
    "trigger_vector_env",
    "trojan_probabilities",
]
