"""The contract every sequence-model layer keeps (see :mod:`seqtrojan.agent.cells`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar, Protocol

import torch
from torch import nn

from seqtrojan.agent.state import LSTMState

LayerOutput = tuple[torch.Tensor, LSTMState, LSTMState | None]
"""an unroll's h sequence (T, B, H), its final state, and its (h, c) sequences (each (T, B, ·)) when asked"""

Shapes = dict[str, tuple[int, ...]]
"""a layer's parameter names (as in its state_dict) and shapes"""


class CellLayer(Protocol):
    """One layer of the stack. Besides the steps, a layer class answers what the rest of the package asks of any
    cell: its parameter shapes before it is built (a model card is checked against them), how to silence units
    (pruning), and the offline detector's features of its weights."""

    cell: ClassVar[str]
    """its registered name (:data:`seqtrojan.cell_types.CELL_TYPES`)"""
    fused_stack_step: ClassVar[bool]
    """a rollout step of a whole stack of these layers is one kernel call (:func:`~.fast_lstm.step_stack`)"""
    c_is_memory: ClassVar[bool]
    """its ``c`` is a memory the layer writes (an LSTM's cell state), not a copy of recent inputs (a Transformer's
    cache) or empty (a GRU's): studies that edit or watch memory read ``c`` only where this holds"""
    input_size: int
    hidden_size: int

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> CellLayer:
        """A freshly initialised layer (``window`` and ``heads`` mean something to a windowed cell only)."""
        ...

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        """What :meth:`build` would hold, computed without allocating it."""
        ...

    @staticmethod
    def weight_features(
        tensors: Mapping[str, torch.Tensor], prefix: str, tag: str, feats: dict[str, torch.Tensor]
    ) -> torch.Tensor:
        """Put the detector's features of the layer whose parameters are ``tensors[prefix + name]`` into ``feats``
        (names ``<group>/<tag>.<...>``); return the weights that read the layer's input (rows: units or gates)."""
        ...

    @property
    def c_width(self) -> int: ...

    def init_weights(self, forget_bias: float) -> None: ...

    def silence_units(self, units: torch.Tensor) -> None:
        """Edit the weights in place so that the ``units`` (int64 indices) output 0 at every step (pruning)."""
        ...

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        """One step from ``state``, multiplied by ``keep`` (B,) first when given (0: an episode starts)."""
        ...

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput: ...


def orthogonal_gates(weight_ih: torch.Tensor, weight_hh: torch.Tensor, *biases: torch.Tensor) -> None:
    """The paper's initialisation of a gated layer: orthogonal weights, zero biases."""
    nn.init.orthogonal_(weight_ih)
    nn.init.orthogonal_(weight_hh)
    for b in biases:
        nn.init.zeros_(b)


def gate_shapes(gates: int, input_size: int, width: int) -> Shapes:
    """The four tensors of a gated layer with ``gates`` blocks of ``width`` rows (as torch's LSTMCell / GRUCell)."""
    rows = gates * width
    return {"weight_ih": (rows, input_size), "weight_hh": (rows, width), "bias_ih": (rows,), "bias_hh": (rows,)}


def silence_gate_rows(layer: nn.Module, gates: int, hidden: int, units: torch.Tensor) -> None:
    """Zero the ``units``' rows of every gate block (``hidden`` rows each) of a gated layer (weights and biases)."""
    rows = torch.cat([units + g * hidden for g in range(gates)])
    with torch.no_grad():
        for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            getattr(layer, name)[rows] = 0.0
