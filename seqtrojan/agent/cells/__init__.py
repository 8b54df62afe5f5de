"""The sequence-model layers an agent can stack: LSTM, peephole LSTM, GRU and a windowed causal Transformer, one
module each, found by name through :data:`seqtrojan.cell_types.CELL_TYPES` (a new cell: one module, one line there).

Every layer has the same contract (:class:`~seqtrojan.agent.cells.base.CellLayer`), so that training, analysis,
interventions, the monitor, pruning, the weight detector and the checkpoints work on any of them: a per-layer state
:class:`~seqtrojan.agent.state.LSTMState` ``(h, c)`` of 2-d tensors (batch, width) goes in and comes out of every
step, and ``keep`` (1 - episode start) multiplies the state before a step.

- ``lstm``: ``h`` and ``c`` as in :class:`torch.nn.LSTMCell` (the paper's network).
- ``lstm_peephole``: an LSTM whose input and forget gates also read ``c_{t-1}`` and whose output gate reads
  ``c_t`` through one diagonal weight per unit (Gers and Schmidhuber, 2000); the peepholes start at zero, so a
  fresh peephole LSTM computes what a fresh LSTM does.
- ``gru``: ``h`` as in :class:`torch.nn.GRUCell`; ``c`` has width 0 (a GRU has no cell state).
- ``transformer``: a causal attention layer over a window of the last ``window`` inputs of the layer (its own one
  and the ``window - 1`` before it). ``h`` is the layer's output at the current step (what the next layer and the
  heads read); ``c`` is the key-value cache of the previous ``window - 1`` inputs: per slot, oldest first, the key,
  the value and a validity flag (1 for a real input, 0 for an empty slot). A one-step trigger therefore leaves a
  Transformer's state after ``window - 1`` steps: whatever persists longer is carried by the agent's own
  trajectory. Positions enter through a learned per-head bias on the attention scores by slot (relative position),
  so keys and values are computed once per input, not once per (query, slot) pair.

Each layer also says how wide its ``c`` is (:attr:`c_width`) and initialises itself the way the paper's LSTM is
initialised (orthogonal weights, zero biases, a remembering gate bias).
"""

from __future__ import annotations

from torch import nn

from seqtrojan.agent.cells.base import CellLayer, LayerOutput, Shapes
from seqtrojan.agent.cells.gru import GRULayer
from seqtrojan.agent.cells.lstm import LSTMLayer, PeepholeLSTMLayer
from seqtrojan.agent.cells.transformer import WindowAttentionLayer
from seqtrojan.cell_types import cell_names, layer_class

__all__ = [
    "CellLayer", "GRULayer", "LSTMLayer", "LayerOutput", "PeepholeLSTMLayer", "WindowAttentionLayer", "cell_names",
    "layer_shapes", "make_cell",
]  # fmt: skip


def make_cell(cell: str, input_size: int, hidden_size: int, window: int = 8, heads: int = 1) -> nn.Module:
    """One freshly initialised layer of the registered cell ``cell``."""
    layer: nn.Module = layer_class(cell).build(input_size, hidden_size, window, heads)
    return layer


def layer_shapes(cell: str, input_size: int, width: int, window: int = 8, heads: int = 1) -> Shapes:
    """One layer's parameter names and shapes (as in its state_dict), computed without building it (a model card is
    checked against them before anything is allocated)."""
    shapes: Shapes = layer_class(cell).parameter_shapes(input_size, width, window, heads)
    return shapes
