"""Building a Gymnasium training run's env: ``gymnasium.make``, the trigger wrapper, the flat observation, and
the vector env (:func:`make_gym_env`, :func:`make_vector_env`); :class:`EpisodeRecorder` keeps what replays each
sub-env's episode in flight, so that a resumed run continues the very episodes a checkpoint interrupted."""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import SyncVectorEnv
from minigrid.minigrid_env import MiniGridEnv

import seqtrojan.minigrid.objectives  # noqa: F401  (registers the MiniGrid objectives)
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.minigrid.fast_obs import use_fast_observation
from seqtrojan.minigrid.tasks import MiniGridInfo
from seqtrojan.serde import short_repr
from seqtrojan.train.gym_config import GymTrainConfig, GymTriggerConfig
from seqtrojan.wrappers import (
    ADVERSARY_OBJECTIVES,
    BoxPatch,
    FirstActions,
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
    """One env of the run: ``gymnasium.make(env.id, **env.kwargs)`` (a MiniGrid env with the fast view unless
    ``env.fast_view`` is false; only its first ``env.num_actions`` actions when set), MiniGrid's info
    (``reached``) for a MiniGrid env, the config's trigger wrapper (when it has a trigger section), then the flat
    float observation."""
    try:
        env = gym.make(config.env.id, **config.env.kwargs)
    except gym.error.Error as err:
        raise ConfigError(f"env.id={config.env.id!r} cannot be made: {err}") from None
    if config.env.fast_view:
        use_fast_observation(env)
    if config.env.num_actions is not None:
        env = FirstActions(env, config.env.num_actions)
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
    config: GymTrainConfig,
    num_envs: int,
    phase: str = "train",
    trojan_probability: float = 0.0,
    record: bool = False,
) -> SyncVectorEnv:
    """``num_envs`` envs of the run (:func:`make_gym_env`) in a SAME_STEP SyncVectorEnv; ``record`` puts each in an
    :class:`EpisodeRecorder` (the trainer's envs, so that a checkpoint can hold their episodes in flight)."""

    def make() -> gym.Env:
        env = make_gym_env(config, phase, trojan_probability)
        return EpisodeRecorder(env) if record else env

    return trigger_vector_env(make, num_envs)


_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "SFC64", "Philox")
"""numpy bit generators whose state is plain JSON (Gymnasium seeds envs with PCG64)"""


def _rng_state(rng: np.random.Generator | None) -> dict[str, Any] | None:
    """A generator's state as plain JSON (None when there is none, or its bit generator keeps arrays)."""
    if rng is None or type(rng.bit_generator).__name__ not in _BIT_GENERATORS:
        return None
    return dict(rng.bit_generator.state)


def _rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    name = state.get("bit_generator") if isinstance(state, dict) else None
    if name not in _BIT_GENERATORS:
        raise CheckpointError(f"episode record: bit_generator={short_repr(name)} is not one of {list(_BIT_GENERATORS)}")
    rng = np.random.Generator(getattr(np.random, name)())
    try:
        rng.bit_generator.state = state
    except (TypeError, ValueError, KeyError) as err:
        raise CheckpointError(f"episode record: a {name} state that numpy refuses ({err})") from None
    return rng


class EpisodeRecorder(gym.Wrapper):
    """Records, for the episode in flight, what replays it: the random state just before its reset (the env's
    ``np_random`` and the TriggerWrapper's generator, or the reset's seed) and every action since.

    :meth:`replay` restores that state, resets and takes the actions again: for an env whose randomness all comes
    from its ``np_random`` (Gymnasium's convention, MiniGrid's way) the env ends exactly where it was, which the
    trainer checks against the saved observation. Outermost in the stack, so the replayed observation is the
    policy's."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.trigger = find_trigger(env)
        self.start: dict[str, Any] | None = None
        """how the episode in flight began (None: it cannot be replayed, e.g. a reset with options)"""
        self.actions: list[int] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        p = None if self.trigger is None else self.trigger.trojan_probability
        start: dict[str, Any] | None = None  # a reset with options cannot be replayed
        if not options and seed is not None:
            start = {"seed": int(seed), "np_random": None, "trigger_rng": None, "trojan_probability": p}
        elif not options:
            np_random = _rng_state(getattr(self.env.unwrapped, "_np_random", None))
            trigger_rng = None if self.trigger is None else _rng_state(self.trigger.trigger_rng)
            replayable = np_random is not None and (self.trigger is None or trigger_rng is not None)
            start = {"seed": None, "np_random": np_random, "trigger_rng": trigger_rng, "trojan_probability": p}
            start = start if replayable else None
        obs, info = self.env.reset(seed=seed, options=options)
        self.start, self.actions = start, []
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        self.actions.append(int(action))
        return self.env.step(action)

    def record(self) -> dict[str, Any] | None:
        """The episode in flight as plain JSON (None when it cannot be replayed)."""
        return None if self.start is None else {"start": dict(self.start), "actions": list(self.actions)}

    def replay(self, record: dict[str, Any]) -> Any:
        """Restore the random state ``record`` holds, reset and take its actions; returns the last observation.
        Raises CheckpointError when the record is malformed or the replayed episode ends early."""
        try:
            start, actions = record["start"], [int(a) for a in record["actions"]]
            seed = start["seed"]
            if seed is None:
                self.env.unwrapped.np_random = _rng_from_state(start["np_random"])
                if self.trigger is not None:
                    self.trigger.trigger_rng = _rng_from_state(start["trigger_rng"])
            if self.trigger is not None:
                self.trigger.set_trojan_probability(float(start["trojan_probability"]))
        except (KeyError, TypeError, ValueError) as err:
            raise CheckpointError(f"episode record is malformed: {short_repr(err)}") from None
        obs, _ = self.reset(seed=seed)
        for t, action in enumerate(actions):
            obs, _, terminated, truncated, _ = self.step(action)
            if terminated or truncated:
                raise CheckpointError(f"the replayed episode ended at step {t + 1} of {len(actions)}")
        return obs
