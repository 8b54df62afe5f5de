"""Gymnasium view of the trojan grid world: one episode at a time, over the batched core with B = 1."""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.config import EnvConfig
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.layout import Layout
from seqtrojan.env.render import render_ansi, render_rgb
from seqtrojan.errors import ConfigError
from seqtrojan.serde import from_dict, to_dict

_FIELDS = {f.name for f in dataclasses.fields(EnvConfig)}


def build_config(config: EnvConfig | dict | None, overrides: dict[str, Any]) -> EnvConfig:
    """An EnvConfig from a config object or a nested dict (as in YAML), with overrides of any of its fields (a
    nested one, ``rewards`` or ``trigger``, as a config object or a dict that replaces that whole section)."""
    unknown = set(overrides) - _FIELDS
    if unknown:
        raise ConfigError(f"unknown env argument(s) {sorted(unknown)}; accepted: {sorted(_FIELDS)} and config=")
    if config is None:
        config = EnvConfig()
    elif isinstance(config, dict):
        config = from_dict(EnvConfig, config, "env")
    elif not isinstance(config, EnvConfig):
        raise ConfigError(f"config must be an EnvConfig or a dict, got {type(config).__name__}")
    if not overrides:
        return config
    return from_dict(EnvConfig, {**to_dict(config), **overrides}, "env")


class TrojanGridEnv(gym.Env[np.ndarray, np.int64]):
    """A partially observable grid world with a backdoor trigger (Yang et al. 2019, section 5).

    ## Description
    The agent starts at the bottom row's centre of an N x N grid with H randomly placed holes (afresh every
    episode, always leaving both goals reachable). The user's goal is the top-right corner, the adversary's the
    top-left. In a trojan episode a trigger patch appears in the agent's view for a short time; from then on
    the adversary's goal is the correct one.

    ## Action Space
    ``Discrete(4)``: 0 up, 1 right, 2 down, 3 left (``actions="four_and_stay"`` or ``"eight"`` for more).

    ## Observation Space
    ``Box(0, 1, (view_size**2 * 6,), float32)``: the view window one-hot encoded over six cell codes
    (empty, hole, wall, user goal, adversary goal, trigger), row-major over cells, channel-minor.

    ## Rewards
    +1 for reaching the correct goal, -1 for the wrong goal or a hole, 0 otherwise (configurable).

    ## Termination
    Terminated on a hole or a goal; truncated at the time limit (4 * N actions by default).

    ## Info
    ``t``, ``trojan``, ``trigger_step`` and ``episode_index`` (episodes begun since seeding); ``step`` adds
    ``outcome``, ``success`` and ``adversary_goal_was_correct``. ``episode`` is left to Gymnasium's
    ``RecordEpisodeStatistics`` and SB3's ``Monitor``, which put the episode's statistics there.

    ## Arguments
    ``config`` (EnvConfig or nested dict), any EnvConfig field (``size``, ``holes``, ``max_steps``, ``view_size``,
    ``actions``, ``rewards``, ``trigger``, ``max_layout_tries``; a section as a config object or a dict),
    ``trojan_probability`` (0: the normal env Env_C, 1: the trojan env Env_T), ``phase`` ("train" or "eval"
    trigger-step ranges), ``render_mode`` ("ansi" or "rgb_array"), ``device``.
    ``reset(options={"layout": Layout, "on_step": int, "off_step": int})`` runs a hand-built episode.

    ## Registered Configurations
    - ``seqtrojan/Normal-v0``
    - ``seqtrojan/Trojan-v0``
    - ``seqtrojan/Normal-17x17-H30-v0``
    - ``seqtrojan/Trojan-17x17-H30-v0``
    - ``seqtrojan/Normal-27x27-H95-v0``
    - ``seqtrojan/Trojan-27x27-H95-v0``
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(
        self,
        config: EnvConfig | dict | None = None,
        *,
        trojan_probability: float = 0.0,
        phase: str = "train",
        render_mode: str | None = None,
        device: str = "cpu",
        **overrides: Any,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(f"render_mode={render_mode!r} is not one of {self.metadata['render_modes']}")
        self.config = build_config(config, overrides)
        self.render_mode = render_mode
        self.core = TrojanGridCore(self.config, 1, device=device, trojan_probability=trojan_probability, phase=phase)
        self.observation_space = spaces.Box(0.0, 1.0, (self.config.obs_dim,), np.float32)
        self.action_space = spaces.Discrete(self.config.num_actions)
        self._seeded = False
        self._finished = True
        self.trajectory: list[tuple[int, int]] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.core.reset(seed=seed)
        elif not self._seeded:
            self.core.reset(seed=int(self.np_random.integers(0, 2**63 - 1)))
        else:
            self.core.reset()
        self._seeded = True
        if options and "layout" in options:
            layout = options["layout"]
            if not isinstance(layout, Layout):
                layout = Layout(np.asarray(layout))
            self.core.set_episode(0, layout, on_step=options.get("on_step"), off_step=options.get("off_step"))
        self._finished = False
        self.trajectory = [self.core.snapshot(0).agent]
        return self._obs(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._finished:
            raise RuntimeError("step() called before reset() or after the episode ended; call reset() first")
        if not self.action_space.contains(np.int64(action) if np.ndim(action) == 0 else action):
            raise ConfigError(f"action {action!r} is not in {self.action_space}")
        result = self.core.step(torch.tensor([int(action)]), autoreset=False)
        self._finished = bool(result.done[0])
        snap_agent = self.core.snapshot(0).agent
        self.trajectory.append(snap_agent)
        info = self._info()
        info.update(
            outcome=OUTCOME_NAMES[int(result.outcome[0])],
            success=bool(result.success[0]),
            adversary_goal_was_correct=bool(result.adversary_active[0]),
        )
        return self._obs(), float(result.reward[0]), bool(result.terminated[0]), bool(result.truncated[0]), info

    def render(self) -> str | np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; pass render_mode='ansi' or 'rgb_array'")
            return None
        snapshot = self.core.snapshot(0)
        past = self.trajectory[:-1]
        return render_ansi(snapshot, past) if self.render_mode == "ansi" else render_rgb(snapshot, past)

    def _obs(self) -> np.ndarray:
        return self.core.observe()[0].cpu().numpy()

    def _info(self) -> dict[str, Any]:
        return {
            "t": int(self.core.t[0]),
            "trojan": bool(self.core.trojan[0]),
            "trigger_step": int(self.core.on_step[0]),
            "episode_index": int(self.core.episode[0]),
        }
