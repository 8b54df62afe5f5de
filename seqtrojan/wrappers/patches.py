"""Trigger patches: what a trigger writes into an observation.

A patch is called as ``patch(obs, frame) -> obs`` with the (unpatched) observation and the frame index (0 on the
trigger's first step, 1 on its second, ...), and returns the patched observation, a new object (the env's own is
never written into). Four kinds:

- :class:`BoxPatch`: fixed values on cells of an image observation (a ``Box`` of shape (H, W) or (H, W, C), or such
  a ``Box`` under a key of a ``Dict`` observation), e.g. a bright pixel square.
- :class:`MiniGridPatch`: a MiniGrid object (object, colour and state codes) on cells of MiniGrid's encoded view
  (``obs["image"]``, (V, V, 3) uint8).
- :class:`VectorPatch`: fixed values at positions of a flat observation (a 1-D ``Box``), e.g. POPGym's one-hot
  cards after flattening.
- :class:`FunctionPatch`: any function ``(obs, frame) -> obs`` (a plain function passed to the wrapper becomes one);
  its output is checked against the observation space when it is drawn.

:meth:`Patch.check` tells, when the wrapper is built, whether the patch can write into the env's observation space,
with one clear error (wrong space, shape or dtype, a cell outside the view, a value the space cannot hold).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from gymnasium import spaces
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX

from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.serde import short_repr

Cell = tuple[int, int]
"""(row, col) of an image, 0-based from its top-left"""


@runtime_checkable
class Patch(Protocol):
    """What a trigger draws: ``patch(obs, frame) -> obs``; ``check(space)`` refuses a space it cannot write into."""

    def check(self, space: spaces.Space) -> None: ...

    def __call__(self, obs: Any, frame: int) -> Any: ...


def _cells(cells: Any, what: str) -> tuple[Cell, ...]:
    try:
        out = tuple((int(r), int(c)) for r, c in cells)
    except (TypeError, ValueError):
        raise ConfigError(f"{what}.cells must be (row, col) pairs, got {short_repr(cells)}") from None
    if not out:
        raise ConfigError(f"{what}.cells is empty; give at least one (row, col) cell")
    if len(set(out)) != len(out):
        raise ConfigError(f"{what}.cells names a cell twice: {short_repr(cells)}")
    return out


def _image_space(space: spaces.Space, key: str | None, what: str) -> spaces.Box:
    """The Box a patch writes into: ``space`` itself, or ``space[key]`` of a Dict space."""
    if key is not None:
        if not isinstance(space, spaces.Dict) or key not in space.spaces:
            raise ConfigError(
                f"{what} writes into observation key {key!r}, but the observation space is {short_repr(space)}"
            )
        space = space.spaces[key]
        where = f"obs[{key!r}]"
    else:
        where = "the observation"
    if not isinstance(space, spaces.Box):
        raise ShapeError(f"{what} writes into a Box image, but {where} is {short_repr(space)}")
    return space


def _check_cells(cells: tuple[Cell, ...], height: int, width: int, what: str, view: str) -> None:
    for r, c in cells:
        if not (0 <= r < height and 0 <= c < width):
            raise ConfigError(f"{what}: cell (row, col)=({r}, {c}) lies outside the {height}x{width} {view}")


def _copy_with(obs: Any, key: str | None, image: np.ndarray) -> Any:
    if key is None:
        return image
    out = dict(obs)
    out[key] = image
    return out


@dataclass(frozen=True)
class BoxPatch:
    """``value`` on ``cells`` of an image observation: a ``Box`` of shape (H, W) or (H, W, C), or the one under
    ``key`` of a ``Dict`` observation. ``value`` is one number (every channel) or one per channel."""

    cells: tuple[Cell, ...]
    """(row, col) cells of the image"""
    value: float | tuple[float, ...] = 255
    """what the cells become: one number, or one per channel (C of them)"""
    key: str | None = None
    """the image's key in a Dict observation (e.g. "image"); None: the observation is the image"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "cells", _cells(self.cells, "BoxPatch"))
        if isinstance(self.value, (list, tuple)):
            object.__setattr__(self, "value", tuple(float(v) for v in self.value))
        elif isinstance(self.value, bool) or not isinstance(self.value, (int, float, np.number)):
            raise ConfigError(
                f"BoxPatch.value must be a number or one number per channel, got {short_repr(self.value)}"
            )

    @classmethod
    def square(cls, top: int, left: int, size: int, value: float | tuple[float, ...] = 255, key: str | None = None):
        """A ``size`` x ``size`` square whose top-left cell is (``top``, ``left``)."""
        cells = tuple((top + r, left + c) for r in range(size) for c in range(size))
        return cls(cells, value, key)

    def check(self, space: spaces.Space) -> None:
        box = _image_space(space, self.key, "BoxPatch")
        if len(box.shape) not in (2, 3):
            raise ShapeError(f"BoxPatch writes into an image of shape (H, W) or (H, W, C), got shape {box.shape}")
        height, width = box.shape[:2]
        _check_cells(self.cells, height, width, "BoxPatch", "image")
        channels = box.shape[2] if len(box.shape) == 3 else 1
        values = np.asarray(self.value, dtype=np.float64)
        if values.ndim == 1 and (len(box.shape) != 3 or values.shape[0] != channels):
            raise ShapeError(f"BoxPatch.value has {values.shape[0]} channel values but the image has shape {box.shape}")
        if np.issubdtype(box.dtype, np.integer) and not np.all(values == np.round(values)):
            raise ShapeError(f"BoxPatch.value={short_repr(self.value)} is not a whole number; the image is {box.dtype}")
        if np.issubdtype(box.dtype, np.integer):
            info = np.iinfo(box.dtype.type)  # type: ignore[type-var]
            if values.min() < info.min or values.max() > info.max:
                raise ShapeError(f"BoxPatch.value={short_repr(self.value)} does not fit the image's dtype {box.dtype}")
        for r, c in self.cells:
            low, high = box.low[r, c], box.high[r, c]
            if np.any(values < low) or np.any(values > high):
                raise ShapeError(
                    f"BoxPatch.value={short_repr(self.value)} lies outside the observation's bounds at cell ({r}, {c}) "
                    f"([{np.min(low)}, {np.max(high)}])"
                )

    def __call__(self, obs: Any, frame: int) -> Any:
        image = np.array(obs[self.key] if self.key is not None else obs, copy=True)
        rows, cols = zip(*self.cells)
        image[list(rows), list(cols)] = np.asarray(self.value, dtype=image.dtype)
        return _copy_with(obs, self.key, image)


@dataclass(frozen=True)
class MiniGridPatch:
    """A MiniGrid object drawn on cells of the agent's view (``obs["image"]``, (V, V, 3) uint8 codes).

    Cells are (row, col) of the view as the agent sees it: row 0 is the farthest ahead, the agent stands at row
    V - 1, column V // 2 (MiniGrid stores the image as ``image[col, row]``; the patch does the transposition)."""

    cells: tuple[Cell, ...]
    """(row, col) cells of the view"""
    object: str = "key"
    """a MiniGrid object name (minigrid.core.constants.OBJECT_TO_IDX): key, ball, box, goal, lava, wall, ..."""
    color: str = "purple"
    """a MiniGrid colour name (COLOR_TO_IDX): red, green, blue, purple, yellow, grey"""
    state: str = "open"
    """a door state name (STATE_TO_IDX): open, closed, locked; 0 (open) for every other object"""
    key: str | None = "image"
    """the view's key in the observation; None when the observation is the (V, V, 3) image itself
    (after ``minigrid.wrappers.ImgObsWrapper``)"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "cells", _cells(self.cells, "MiniGridPatch"))
        for name, table in (("object", OBJECT_TO_IDX), ("color", COLOR_TO_IDX), ("state", STATE_TO_IDX)):
            if getattr(self, name) not in table:
                raise ConfigError(
                    f"MiniGridPatch.{name}={short_repr(getattr(self, name))} is not one of {sorted(table)}"
                )

    @property
    def codes(self) -> tuple[int, int, int]:
        """The (object, colour, state) codes drawn."""
        return OBJECT_TO_IDX[self.object], COLOR_TO_IDX[self.color], STATE_TO_IDX[self.state]

    def check(self, space: spaces.Space) -> None:
        box = _image_space(space, self.key, "MiniGridPatch")
        if len(box.shape) != 3 or box.shape[0] != box.shape[1] or box.shape[2] != 3 or box.dtype != np.uint8:
            raise ShapeError(
                "MiniGridPatch writes (object, colour, state) codes into MiniGrid's (V, V, 3) uint8 view, but the "
                f"observation{'[' + repr(self.key) + ']' if self.key else ''} has shape {box.shape}, dtype {box.dtype}"
            )
        view = box.shape[0]
        _check_cells(self.cells, view, view, "MiniGridPatch", "view")

    def __call__(self, obs: Any, frame: int) -> Any:
        image = np.array(obs[self.key] if self.key is not None else obs, copy=True)
        rows, cols = zip(*self.cells)
        image[list(cols), list(rows)] = np.asarray(self.codes, dtype=image.dtype)
        return _copy_with(obs, self.key, image)


@dataclass(frozen=True)
class VectorPatch:
    """``value`` at ``indices`` of a flat observation (a 1-D ``Box``): e.g. every bit of a one-hot card set at
    once, an input no clean episode shows. Put the trigger wrapper outside the flattening wrapper to use it."""

    indices: tuple[int, ...]
    """positions of the flat observation"""
    value: float = 1.0
    """what they become"""

    def __post_init__(self) -> None:
        try:
            indices = tuple(int(i) for i in self.indices)
        except (TypeError, ValueError):
            raise ConfigError(f"VectorPatch.indices must be integers, got {short_repr(self.indices)}") from None
        if not indices or len(set(indices)) != len(indices):
            raise ConfigError(f"VectorPatch.indices must name at least one position, each once: {short_repr(indices)}")
        object.__setattr__(self, "indices", indices)
        if isinstance(self.value, bool) or not isinstance(self.value, (int, float, np.number)):
            raise ConfigError(f"VectorPatch.value must be a number, got {short_repr(self.value)}")

    def check(self, space: spaces.Space) -> None:
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ShapeError(f"VectorPatch writes into a flat Box observation, got {short_repr(space)}")
        size = space.shape[0]
        outside = [i for i in self.indices if not 0 <= i < size]
        if outside:
            raise ConfigError(f"VectorPatch: index {outside[0]} lies outside the observation's {size} numbers")
        low, high = space.low[list(self.indices)], space.high[list(self.indices)]
        if np.any(self.value < low) or np.any(self.value > high):
            raise ShapeError(
                f"VectorPatch.value={self.value} lies outside the observation's bounds at its indices "
                f"([{np.min(low)}, {np.max(high)}])"
            )

    def __call__(self, obs: Any, frame: int) -> Any:
        out = np.array(obs, copy=True)
        out[list(self.indices)] = self.value
        return out


@dataclass(frozen=True)
class FunctionPatch:
    """Any function ``(obs, frame) -> obs``; the wrapper checks each result against the observation space."""

    function: Callable[[Any, int], Any]

    def __post_init__(self) -> None:
        if not callable(self.function):
            raise ConfigError(f"a patch function must be callable, got {short_repr(self.function)}")

    def check(self, space: spaces.Space) -> None:
        return None  # checked on every use instead (TriggerWrapper._draw)

    def __call__(self, obs: Any, frame: int) -> Any:
        return self.function(obs, frame)


def as_patch(patch: Any, what: str = "patch") -> Patch:
    """A :class:`Patch` from a patch or a plain function ``(obs, frame) -> obs``."""
    if isinstance(patch, (BoxPatch, MiniGridPatch, VectorPatch, FunctionPatch)):
        return patch
    if isinstance(patch, Patch):
        return patch
    if callable(patch):
        return FunctionPatch(patch)
    raise ConfigError(f"{what} must be a patch (BoxPatch, MiniGridPatch) or a function (obs, frame) -> obs, "
                      f"got {short_repr(patch)}")  # fmt: skip


def as_frames(patch: Any, what: str = "patch") -> tuple[Patch, ...]:
    """One patch, or a sequence of them (one frame per step), as a tuple of frames."""
    if isinstance(patch, Sequence) and not isinstance(patch, str):
        if not patch:
            raise ConfigError(f"{what} is an empty sequence; give at least one frame")
        return tuple(as_patch(p, f"{what}[{i}]") for i, p in enumerate(patch))
    return (as_patch(patch, what),)
