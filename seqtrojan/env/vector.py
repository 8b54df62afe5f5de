"""Gymnasium vector-env view over the batched core (numpy in and out), with NEXT_STEP autoreset.

NEXT_STEP is Gymnasium's default: the step *after* an episode ends resets that env (its action is ignored,
its reward is 0 and its flags are false), exactly as ``gymnasium.vector.SyncVectorEnv`` does. Env ``i`` seeded
with ``s`` runs the same episodes as a :class:`TrojanGridEnv` seeded with ``s + i`` (Gymnasium's convention).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import VectorEnv
from gymnasium.vector.utils import batch_space
from gymnasium.vector.vector_env import AutoresetMode

from seqtrojan.env.config import EnvConfig
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.gym_env import build_config
from seqtrojan.env.render import render_ansi, render_rgb
from seqtrojan.errors import ConfigError, ShapeError


class TrojanGridVectorEnv(VectorEnv):
    """``num_envs`` trojan grid worlds stepped together. Arguments as :class:`~seqtrojan.env.gym_env.TrojanGridEnv`."""

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int,
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
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.core = TrojanGridCore(
            self.config, num_envs, device=device, trojan_probability=trojan_probability, phase=phase
        )
        self.single_observation_space = spaces.Box(0.0, 1.0, (self.config.obs_dim,), np.float32)
        self.single_action_space = spaces.Discrete(self.config.num_actions)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._needs_reset = np.zeros(num_envs, dtype=bool)
        self._seeded = False

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        if seed is None and not self._seeded:
            seed = int(np.random.default_rng().integers(0, 2**62))
        if seed is not None:
            self._np_random_seed = seed if isinstance(seed, int) else None
        obs = self.core.reset(seed=seed)
        self._seeded = True
        self._needs_reset[:] = False
        return obs.cpu().numpy(), {}

    def step(self, actions: Any):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,):
            raise ShapeError(f"actions must have shape ({self.num_envs},), got {actions.shape}")
        result = self.core.step(torch.as_tensor(actions, dtype=torch.int64), autoreset=False)
        rewards = result.reward.cpu().numpy().astype(np.float64)
        terminated = result.terminated.cpu().numpy().copy()
        truncated = result.truncated.cpu().numpy().copy()
        infos: dict[str, Any] = {}
        done = terminated | truncated
        if done.any():
            infos = {
                "outcome": result.outcome.cpu().numpy(),
                "_outcome": done.copy(),
                "success": result.success.cpu().numpy(),
                "_success": done.copy(),
            }
        if self._needs_reset.any():
            mask = self._needs_reset
            self.core.reset_envs(torch.as_tensor(mask, device=self.core.device))
            rewards[mask], terminated[mask], truncated[mask] = 0.0, False, False
            for key in list(infos):
                if key.startswith("_"):
                    infos[key] = infos[key] & ~mask
        self._needs_reset = terminated | truncated
        return self.core.observe().cpu().numpy(), rewards, terminated, truncated, infos

    def render(self) -> tuple[Any, ...] | None:
        if self.render_mode is None:
            return None
        renderer = render_ansi if self.render_mode == "ansi" else render_rgb
        return tuple(renderer(self.core.snapshot(i)) for i in range(self.num_envs))
