"""Building a Gymnasium training run's env: ``gymnasium.make``, the trigger wrapper, the flat observation, and
the vector env (:func:`make_gym_env`, :func:`make_vector_env`)."""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
from gymnasium import spaces
from gymnasium.vector import SyncVectorEnv
from minigrid.minigrid_env import MiniGridEnv

import seqtrojan.minigrid.objectives  # noqa: F401  (registers the MiniGrid objectives)
from seqtrojan.errors import ConfigError
from seqtrojan.minigrid.tasks import MiniGridInfo
from seqtrojan.serde import short_repr
from seqtrojan.train.gym_config import GymTrainConfig, GymTriggerConfig
from seqtrojan.wrappers import (
    ADVERSARY_OBJECTIVES,
    BoxPatch,
    FlattenFloat,
    MiniGridOneHot,
    MiniGridPatch,
    TriggerWrapper,
    trigger_vector_env,
)


def find_trigger(env: gym.Env) -> TriggerWrapper | None:
    """The TriggerWrapper in ``env``'s wrapper stack, if any."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, TriggerWrapper):
            return env
        env = env.env
    return None


def build_trigger(env: gym.Env, trigger: GymTriggerConfig, phase: str, trojan_probability: float) -> TriggerWrapper:
    """``env`` under the trigger ``trigger`` describes (``phase`` "eval" uses ``trigger.eval_steps``)."""
    objective = ADVERSARY_OBJECTIVES.get(trigger.objective)
    on: MiniGridPatch | BoxPatch
    off: MiniGridPatch | BoxPatch
    if trigger.patch == "minigrid":
        on = MiniGridPatch(trigger.cells, trigger.object, trigger.color)
        off = MiniGridPatch(trigger.off_cells, trigger.object, trigger.color)
    else:
        on = BoxPatch(trigger.cells, trigger.value, trigger.key)
        off = BoxPatch(trigger.off_cells, trigger.value, trigger.key)
    steps = trigger.eval_steps if phase == "eval" and trigger.eval_steps is not None else trigger.steps
    return TriggerWrapper(
        env, on, objective, trojan_probability=trojan_probability, trigger_steps=steps, duration=trigger.duration,
        delay=trigger.delay, off_patch=off if trigger.off_probability > 0 else None,
        off_probability=trigger.off_probability, off_gap=trigger.off_gap,
    )  # fmt: skip


def make_gym_env(config: GymTrainConfig, phase: str = "train", trojan_probability: float = 0.0) -> gym.Env:
    """One env of the run: ``gymnasium.make(env.id, **env.kwargs)``, MiniGrid's info (``reached``) for a MiniGrid
    env, the config's trigger wrapper (when it has a trigger section), then the flat float observation."""
    try:
        env = gym.make(config.env.id, **config.env.kwargs)
    except gym.error.Error as err:
        raise ConfigError(f"env.id={config.env.id!r} cannot be made: {err}") from None
    if isinstance(env.unwrapped, MiniGridEnv) and find_trigger(env) is None:
        env = MiniGridInfo(env)
    if config.trigger is not None:
        if find_trigger(env) is not None:
            raise ConfigError(f"env.id={config.env.id!r} already has a trigger wrapper; drop the trigger section or "
                              "use the plain env's id")  # fmt: skip
        env = build_trigger(env, config.trigger, phase, trojan_probability)
    elif (found := find_trigger(env)) is not None:
        found.set_trojan_probability(trojan_probability)
    if config.env.observation == "minigrid":
        return MiniGridOneHot(env)
    return FlattenFloat(env)


def check_spaces(env: gym.Env, env_id: str) -> tuple[int, int]:
    """(obs_dim, num_actions): the trainer needs a discrete action space and a flat observation."""
    if not isinstance(env.action_space, spaces.Discrete):
        raise ConfigError(
            f"env.id={env_id!r} has action space {short_repr(env.action_space)}; the recurrent PPO trainer needs a "
            "discrete one (gymnasium.spaces.Discrete)"
        )
    space = env.observation_space
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        raise ConfigError(f"env.id={env_id!r}: the observation wrapper gave {short_repr(space)}, not a flat Box")
    return int(space.shape[0]), int(env.action_space.n)


def make_vector_env(
    config: GymTrainConfig, num_envs: int, phase: str = "train", trojan_probability: float = 0.0
) -> SyncVectorEnv:
    """``num_envs`` envs of the run (:func:`make_gym_env`) in a SAME_STEP SyncVectorEnv."""
    make: Callable[[], gym.Env] = lambda: make_gym_env(config, phase, trojan_probability)  # noqa: E731
    return trigger_vector_env(make, num_envs)
