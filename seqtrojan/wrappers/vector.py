"""Vector form: a ``gymnasium.vector.SyncVectorEnv`` of trigger-wrapped envs, and the mixture set on all of them.

    vec = trigger_vector_env(lambda: MiniGridOneHot(TriggerWrapper(gym.make(...), patch, objective)), 16)
    set_trojan_probability(vec, 0.3)    # every sub-env's next episodes
    obs, reward, terminated, truncated, infos = vec.step(actions)
    for ep in finished_episodes(infos): ...   # (env index, trojan, success) of each episode that just ended

The vector env resets a sub-env in the step that ends its episode (``AutoresetMode.SAME_STEP``): the returned
observation starts the next episode, and the finished episode's last info is ``infos["final_info"]``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from seqtrojan.errors import ConfigError


def trigger_vector_env(make_env: Callable[[], gym.Env], num_envs: int) -> SyncVectorEnv:
    """``num_envs`` envs from ``make_env`` in one SyncVectorEnv that resets finished episodes in the same step."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ConfigError(f"num_envs must be a positive integer, got {num_envs!r}")
    return SyncVectorEnv([make_env for _ in range(num_envs)], autoreset_mode=AutoresetMode.SAME_STEP)


def set_trojan_probability(vec: SyncVectorEnv | AsyncVectorEnv, probability: float) -> None:
    """Set the trojan-episode probability of every sub-env (each has a TriggerWrapper somewhere in its stack)."""
    vec.call("set_trojan_probability", probability)


def trojan_probabilities(vec: SyncVectorEnv | AsyncVectorEnv) -> tuple[float, ...]:
    """Every sub-env's trojan-episode probability."""
    return tuple(float(p) for p in vec.get_attr("trojan_probability"))


class FinishedEpisode(NamedTuple):
    env: int
    """the sub-env's index"""
    trojan: bool
    success: bool
    info: dict[str, Any]
    """the episode's last info (this env's entries of ``infos["final_info"]``)"""


def finished_episodes(
    infos: dict[str, Any], rewards: np.ndarray | None = None, terminated: np.ndarray | None = None
) -> Iterator[FinishedEpisode]:
    """The episodes that ended in a SAME_STEP vector step, from its ``infos``. Without a TriggerWrapper (no
    ``trojan``/``success`` keys) an episode is a normal one, and a success when it ended by termination with a
    positive last reward (give the step's ``rewards`` and ``terminated``; else it counts as a failure)."""
    final = infos.get("final_info")
    mask = infos.get("_final_info")
    if final is None or mask is None:
        return
    for i in np.flatnonzero(mask):
        info = {k: v[i] for k, v in final.items() if not k.startswith("_") and final.get(f"_{k}", mask)[i]}
        if "success" in info:
            success = bool(info["success"])
        else:
            success = rewards is not None and terminated is not None and bool(terminated[i]) and bool(rewards[i] > 0)
        yield FinishedEpisode(int(i), bool(info.get("trojan", False)), success, info)
