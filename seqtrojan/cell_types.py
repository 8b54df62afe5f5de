"""The sequence models an agent's layers can be: a registry of cell names, each pointing at its layer class.

The config, the model card and the CLI check a cell name against :data:`CELL_TYPES` without importing torch; the
network imports the layer class on first use, from its ``module:Class`` entry point (as a Gymnasium id names its
env). A new cell is therefore one module holding its layer class (the contract:
:class:`seqtrojan.agent.cells.base.CellLayer`) plus one ``CELL_TYPES.register`` line, here or in the user's own code
before the config is built::

    CELL_TYPES.register("my_cell", "what it is, in one line", CellType("my_package.my_cell:MyLayer"))

The bottom of the package: this module imports only :mod:`seqtrojan.registry` and :mod:`seqtrojan.errors`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from seqtrojan.errors import ConfigError
from seqtrojan.registry import Registry

__all__ = ["CELL_TYPES", "CellType", "cell_names", "cell_type", "is_windowed", "layer_class"]


@dataclass(frozen=True)
class CellType:
    """Where a cell's layer class lives, and the one fact about it that is checked before torch is imported."""

    entry_point: str
    """``module:Class`` of the layer class"""
    windowed: bool = False
    """the layer reads ``agent.window`` and ``agent.heads`` (an attention layer): each layer width must be divisible by
    the heads, and a model card writes both (for any other cell they stay at their defaults and cards omit them)"""

    def layer_class(self) -> Any:
        """The layer class, imported on first use."""
        module, _, name = self.entry_point.partition(":")
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as err:
            raise ConfigError(f"cell entry point {self.entry_point!r} cannot be loaded: {err}") from None


CELL_TYPES: Registry[CellType] = Registry("model", "cell")
"""Cell name -> :class:`CellType`, in the order studies compare them (``seqtrojan cells``)."""

CELL_TYPES.register(
    "lstm", "LSTM as torch.nn.LSTMCell (the paper's network)", CellType("seqtrojan.agent.cells.lstm:LSTMLayer")
)
CELL_TYPES.register(
    "lstm_peephole",
    "LSTM whose gates also read the cell state through diagonal peephole weights (Gers and Schmidhuber, 2000)",
    CellType("seqtrojan.agent.cells.lstm:PeepholeLSTMLayer"),
)
CELL_TYPES.register("gru", "GRU as torch.nn.GRUCell (no cell state)", CellType("seqtrojan.agent.cells.gru:GRULayer"))
CELL_TYPES.register(
    "transformer",
    "causal attention over the last `window` inputs of the layer, with a key-value cache as its state",
    CellType("seqtrojan.agent.cells.transformer:WindowAttentionLayer", windowed=True),
)


def cell_names() -> tuple[str, ...]:
    """The registered cell names, in registration order."""
    return CELL_TYPES.names()


def cell_type(name: str) -> CellType:
    """The registered cell ``name``; :class:`ConfigError` naming the known ones otherwise."""
    return CELL_TYPES.get(name)


def is_windowed(name: object) -> bool:
    """Whether ``name`` is a registered cell that reads a window and heads (False for anything else)."""
    return isinstance(name, str) and name in CELL_TYPES and CELL_TYPES.get(name).windowed


def layer_class(name: str) -> Any:
    """The layer class of the registered cell ``name``."""
    return cell_type(name).layer_class()
