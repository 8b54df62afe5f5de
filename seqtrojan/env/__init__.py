"""The trojan grid world: a batched tensor core, a Gymnasium env and a Gymnasium vector env over it."""

from seqtrojan.env.config import EnvConfig, GridSpec, OffTriggerConfig, PatternConfig, RewardConfig, TriggerConfig
from seqtrojan.env.core import EpisodeSnapshot, StepResult, TrojanGridCore
from seqtrojan.env.layout import Layout

__all__ = [
    "EnvConfig",
    "EpisodeSnapshot",
    "GridSpec",
    "Layout",
    "OffTriggerConfig",
    "PatternConfig",
    "RewardConfig",
    "StepResult",
    "TriggerConfig",
    "TrojanGridCore",
]
