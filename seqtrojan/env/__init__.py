"""The trojan grid world: a batched tensor core, a Gymnasium env and a Gymnasium vector env over it."""

from seqtrojan.env.config import EnvConfig, GridSpec, OffTriggerConfig, RewardConfig, TriggerConfig
from seqtrojan.env.core import EpisodeSnapshot, StepResult, TrojanGridCore
from seqtrojan.env.layout import Layout

__all__ = [
    "EnvConfig",
    "EpisodeSnapshot",
    "GridSpec",
    "Layout",
    "OffTriggerConfig",
    "RewardConfig",
    "StepResult",
    "TriggerConfig",
    "TrojanGridCore",
]
