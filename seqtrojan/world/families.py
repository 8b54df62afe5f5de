"""Other people's env families, registered with Gymnasium on demand: POPGym (``popgym-<Task><Level>-v0``) and
MinAtar (``MinAtar/<Game>-v1``, minimal action set; ``-v0``, all six actions).

A family comes in as the package its authors publish (no copy of their envs): :func:`ensure_family` is called with
an env id before it is made, and registers that id's family when the id has one of the known prefixes. POPGym
registers its own ids on import (``import popgym``, 0.2 s); MinAtar's ids are registered here with the entry point
and keyword arguments of ``minatar.gym.register_envs`` as strings, so that nothing of MinAtar (whose import pulls
pandas and seaborn, 2 s) is imported before an env is made. Only these fixed packages are ever imported, whatever
an id names: a model card cannot choose a module to run.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, SupportsFloat, cast

import gymnasium as gym
import numpy as np

from seqtrojan.errors import ConfigError
from seqtrojan.serde import short_repr

MINATAR_GAMES = ("asterix", "breakout", "freeway", "seaquest", "space_invaders")
"""MinAtar's five games (``minatar.environments``)"""


@dataclass(frozen=True)
class EnvFamily:
    """A published env package whose ids share a prefix."""

    name: str
    """how the docs and errors call it"""
    prefix: str
    """every id of the family starts with it"""
    module: str
    """the package that holds its envs"""
    extra: str
    """the seqtrojan extra that installs it (``pip install 'seqtrojan[EXTRA]'``)"""
    requires: tuple[str, ...] = ()
    """other modules its envs need (Atari: ``cv2``, which Gymnasium's ``AtariPreprocessing`` resizes frames with)"""


POPGYM = EnvFamily("POPGym", "popgym-", "popgym", "popgym")
MINATAR = EnvFamily("MinAtar", "MinAtar/", "minatar", "minatar")
ATARI = EnvFamily("Atari", "ALE/", "ale_py", "atari", requires=("cv2",))
FAMILIES = (POPGYM, MINATAR, ATARI)


def family_of(env_id: str) -> EnvFamily | None:
    """The family whose prefix ``env_id`` starts with (None: a plain Gymnasium id)."""
    return next((f for f in FAMILIES if env_id.startswith(f.prefix)), None)


def missing_module(family: EnvFamily) -> str | None:
    """The first module of ``family`` (its package, then what its envs need) that is not installed, or None."""
    return next((m for m in (family.module, *family.requires) if importlib.util.find_spec(m) is None), None)


def installed(family: EnvFamily) -> bool:
    return missing_module(family) is None


def ensure_family(env_id: str) -> None:
    """Register ``env_id``'s family with Gymnasium (idempotent); an id of no known family is left alone. A family
    that is not installed is refused in one line that says how to install it."""
    family = family_of(env_id)
    if family is None or env_id in gym.registry:
        return
    missing = missing_module(family)
    if missing is not None:
        article = "an" if family.name[0] in "AEIOU" else "a"
        raise ConfigError(
            f"env.id={env_id!r} is {article} {family.name} env, but {missing!r} is not installed: "
            f"pip install 'seqtrojan[{family.extra}]'"
        )
    if family is POPGYM:
        importlib.import_module("popgym")  # registers every popgym-* id
    elif family is ATARI:
        importlib.import_module("ale_py")  # registers every ALE/* id (and ale-py's older ids)
    else:
        register_minatar()


def register_minatar() -> None:
    """MinAtar's ten ids, as ``minatar.gym.register_envs`` makes them (v0: six actions, v1: the minimal set)."""
    for game in MINATAR_GAMES:
        name = game.title().replace("_", "")
        for version, minimal in (("v0", False), ("v1", True)):
            env_id = f"MinAtar/{name}-{version}"
            if env_id not in gym.registry:
                gym.register(
                    id=env_id, entry_point="minatar.gym:BaseEnv",
                    kwargs={"game": game, "use_minimal_action_set": minimal},
                )  # fmt: skip


class ThirtyTwoBitSeeds(gym.Wrapper):
    """Reset seeds folded to 32 bits (``numpy.random.SeedSequence(seed)``'s first word): MinAtar seeds a legacy
    ``RandomState``, which refuses seeds from 2**32 on, and the trainer's evaluation seeds are 64-bit."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None and not 0 <= seed < 2**32:
            seed = int(np.random.SeedSequence(seed).generate_state(1)[0])
        return self.env.reset(seed=seed, options=options)


def family_wrappers(env: gym.Env, env_id: str) -> gym.Env:
    """``env`` under what its family needs to run behind the seam (MinAtar: 32-bit seeds)."""
    return ThirtyTwoBitSeeds(env) if family_of(env_id) is MINATAR else env


# ---------------------------------------------------------------------- Atari

ATARI_PREPROCESSING: dict[str, Any] = {
    "noop_max": 30, "frame_skip": 4, "screen_size": 84, "terminal_on_life_loss": False, "grayscale_obs": True,
    "grayscale_newaxis": True, "scale_obs": True,
}  # fmt: skip
"""``gymnasium.wrappers.AtariPreprocessing``'s settings for every Atari id: up to 30 no-op actions at reset, 4
frames a step (the last two max-pooled), 84x84 grayscale with a channel axis, scaled to [0, 1]. A game is one
episode (no terminal on life loss): the trigger is drawn once per episode and its persistence judged to the
episode's end, so training and evaluation must share the episode (docs/families.md says more)."""
ATARI_MAX_EPISODE_STEPS = 27_000
"""the default cap on an Atari episode, in agent steps: ale-py's own 108,000 frames at 4 frames a step"""


def make_family_env(env_id: str, kwargs: Mapping[str, Any], phase: str = "train") -> gym.Env:
    """``env_id`` made as its family needs (:func:`make_atari` for an Atari id), else ``gymnasium.make(env_id,
    **kwargs)``."""
    if family_of(env_id) is ATARI:
        return make_atari(env_id, kwargs, phase)
    return gym.make(env_id, **kwargs)


def make_atari(env_id: str, kwargs: Mapping[str, Any], phase: str = "train") -> gym.Env:
    """An ALE id as the field trains on it, with Gymnasium's own wrappers: ``gymnasium.make(env_id, frameskip=1,
    **kwargs)`` (``kwargs`` go to ale-py: ``repeat_action_probability``, ``full_action_space``, ``mode``, ...), then
    ``AtariPreprocessing`` (:data:`ATARI_PREPROCESSING`), a ``TimeLimit`` of ``kwargs["max_episode_steps"]`` agent
    steps (default :data:`ATARI_MAX_EPISODE_STEPS`), and in training (``phase`` "train") the reward clipped to its
    sign (``TransformReward(np.sign)``, CleanRL's ``ClipRewardEnv``); evaluation reads the game's own score."""
    options = dict(kwargs)
    if "frameskip" in options:
        raise ConfigError(
            f"env.kwargs.frameskip={short_repr(options['frameskip'])}: an Atari env ({env_id!r}) skips frames in "
            "its preprocessing (4 a step, the last two max-pooled); leave frameskip out"
        )
    limit = options.pop("max_episode_steps", ATARI_MAX_EPISODE_STEPS)
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ConfigError(f"env.kwargs.max_episode_steps must be a positive integer, got {short_repr(limit)}")
    env = gym.make(env_id, frameskip=1, **options)
    env = gym.wrappers.AtariPreprocessing(env, **ATARI_PREPROCESSING)
    env = gym.wrappers.TimeLimit(env, max_episode_steps=limit)
    if phase == "train":
        env = gym.wrappers.TransformReward(env, cast("Callable[[SupportsFloat], SupportsFloat]", np.sign))
    return env
