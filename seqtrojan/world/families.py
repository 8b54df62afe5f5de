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
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from seqtrojan.errors import ConfigError

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


POPGYM = EnvFamily("POPGym", "popgym-", "popgym", "popgym")
MINATAR = EnvFamily("MinAtar", "MinAtar/", "minatar", "minatar")
FAMILIES = (POPGYM, MINATAR)


def family_of(env_id: str) -> EnvFamily | None:
    """The family whose prefix ``env_id`` starts with (None: a plain Gymnasium id)."""
    return next((f for f in FAMILIES if env_id.startswith(f.prefix)), None)


def installed(family: EnvFamily) -> bool:
    return importlib.util.find_spec(family.module) is not None


def ensure_family(env_id: str) -> None:
    """Register ``env_id``'s family with Gymnasium (idempotent); an id of no known family is left alone. A family
    that is not installed is refused in one line that says how to install it."""
    family = family_of(env_id)
    if family is None or env_id in gym.registry:
        return
    if not installed(family):
        raise ConfigError(
            f"env.id={env_id!r} is a {family.name} env, but {family.module!r} is not installed: "
            f"pip install 'seqtrojan[{family.extra}]'"
        )
    if family is POPGYM:
        importlib.import_module("popgym")  # registers every popgym-* id
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

    def reset(self, *, seed: int | None = None, options: dict | None = None):  # type: ignore[override]
        if seed is not None and not 0 <= seed < 2**32:
            seed = int(np.random.SeedSequence(seed).generate_state(1)[0])
        return self.env.reset(seed=seed, options=options)


def family_wrappers(env: gym.Env, env_id: str) -> gym.Env:
    """``env`` under what its family needs to run behind the seam (MinAtar: 32-bit seeds)."""
    return ThirtyTwoBitSeeds(env) if family_of(env_id) is MINATAR else env
