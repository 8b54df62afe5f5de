"""Observation wrappers that give a recurrent policy the flat float vector it takes (``obs_dim`` numbers).

- :class:`MiniGridOneHot`: MiniGrid's encoded view (``obs["image"]``, or the image itself) one-hot encoded per
  channel (11 object codes, 6 colours, 3 states: 20 numbers per cell), row-major over the view's rows as the agent
  sees them (row 0 farthest ahead); the mission and direction are dropped (the view is egocentric).
- :class:`FlattenFloat`: any other observation flattened (``gymnasium.spaces.flatten``) to float32.

Put them outside the :class:`~seqtrojan.wrappers.TriggerWrapper`, so that the trigger is drawn in the env's own
observation and then encoded like everything else.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX

from seqtrojan.errors import ShapeError
from seqtrojan.serde import short_repr

CHANNELS = (len(OBJECT_TO_IDX), len(COLOR_TO_IDX), len(STATE_TO_IDX))
"""one-hot widths of MiniGrid's three codes: object, colour, state"""
CELL_BITS = sum(CHANNELS)
_OFFSETS = np.array([0, CHANNELS[0], CHANNELS[0] + CHANNELS[1]], dtype=np.intp)
_LIMITS = np.array(CHANNELS, dtype=np.uint8)


class MiniGridOneHot(gym.ObservationWrapper):
    """MiniGrid's (V, V, 3) view as a flat float32 one-hot vector of V * V * 20 numbers."""

    def __init__(self, env: gym.Env, key: str | None = "image") -> None:
        super().__init__(env)
        space = env.observation_space
        if key is not None and isinstance(space, spaces.Dict) and key in space.spaces:
            space = space.spaces[key]
        elif key is not None and isinstance(space, spaces.Dict):
            raise ShapeError(f"MiniGridOneHot reads obs[{key!r}], but the observation space is {short_repr(space)}")
        else:
            key = None
        if not isinstance(space, spaces.Box) or len(space.shape) != 3 or space.shape[2] != 3:
            raise ShapeError(f"MiniGridOneHot needs MiniGrid's (V, V, 3) view, got {short_repr(space)}")
        self.key = key
        self.view = space.shape[:2]
        cells = self.view[0] * self.view[1]
        self._size = cells * CELL_BITS
        self.observation_space = spaces.Box(0.0, 1.0, (self._size,), np.float32)
        self._shape = (*self.view, 3)
        rows, cols = np.arange(self.view[1]), np.arange(self.view[0])
        first = (rows[None, :, None] * self.view[0] + cols[:, None, None]) * CELL_BITS + _OFFSETS  # [col, row, code]
        self._first_bits = first.reshape(-1).astype(np.intp)
        """for each number of the image in its own order ([col, row, code]), the first bit of its one-hot block"""
        self._limits = np.tile(_LIMITS, cells)  # (cells * 3,)

    def observation(self, observation: Any) -> np.ndarray:
        image = np.asarray(observation[self.key] if self.key is not None else observation)
        if image.shape != self._shape:
            raise ShapeError(f"MiniGridOneHot: a view of shape {image.shape} or a code beyond {list(CHANNELS)}")
        codes = image.reshape(-1)
        if (image.dtype.kind != "u" and (codes < 0).any()) or (codes >= self._limits).any():
            raise ShapeError(f"MiniGridOneHot: a view of shape {image.shape} or a code beyond {list(CHANNELS)}")
        out = np.zeros(self._size, dtype=np.float32)
        out[codes + self._first_bits] = 1.0  # rows first: bit (row * cols + col) * 20 + code
        return out  # (V * V * 20,)


class FlattenFloat(gym.ObservationWrapper):
    """Any observation flattened to a float32 vector (``gymnasium.spaces.flatten``)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        flat = spaces.flatten_space(env.observation_space)
        if not isinstance(flat, spaces.Box):
            raise ShapeError(f"FlattenFloat cannot flatten {short_repr(env.observation_space)} to a vector")
        self.observation_space = spaces.Box(
            flat.low.astype(np.float32), flat.high.astype(np.float32), flat.shape, np.float32
        )

    def observation(self, observation: Any) -> np.ndarray:
        return np.asarray(spaces.flatten(self.env.observation_space, observation), dtype=np.float32)
