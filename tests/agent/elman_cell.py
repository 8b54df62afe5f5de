"""A cell written the way a user adds one: this one module (an Elman RNN layer, :class:`torch.nn.RNNCell`) plus one
``CELL_TYPES.register`` line (in tests/agent/test_cells.py). Nothing else in the package knows it."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from seqtrojan.agent.cells.base import LayerOutput, Shapes, gate_shapes, orthogonal_gates, silence_gate_rows
from seqtrojan.agent.state import LSTMState


def elman_features(
    tensors: Mapping[str, torch.Tensor], prefix: str, tag: str, feats: dict[str, torch.Tensor]
) -> torch.Tensor:
    w_ih, w_hh = tensors[prefix + "weight_ih"].double(), tensors[prefix + "weight_hh"].double()
    for block, w in (("ih", w_ih), ("hh", w_hh)):
        feats[f"gate_stats/{tag}.{block}.mean"] = w.mean()
        feats[f"gate_stats/{tag}.{block}.rms"] = w.pow(2).mean().sqrt()
    return w_ih


class ElmanLayer(nn.RNNCell):
    """h_t = tanh(W_ih x + b_ih + W_hh h_{t-1} + b_hh); no cell state."""

    cell = "elman"
    fused_stack_step = False
    c_is_memory = False
    weight_features = staticmethod(elman_features)

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> ElmanLayer:
        return cls(input_size, width)

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        return gate_shapes(1, input_size, width)

    @property
    def c_width(self) -> int:
        return 0

    def init_weights(self, forget_bias: float) -> None:
        orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)

    def silence_units(self, units: torch.Tensor) -> None:
        silence_gate_rows(self, 1, self.hidden_size, units)

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        h = state.h if keep is None else state.h * keep[:, None]
        return LSTMState(self(x, h), state.c)

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput:
        h, hs = state.h, []
        for k in range(x.shape[0]):
            h = self(x[k], h * keep[k, :, None])
            hs.append(h)
        h_seq = torch.stack(hs)
        seq = LSTMState(h_seq, state.c.new_zeros(*h_seq.shape[:2], 0)) if return_states else None
        return h_seq, LSTMState(h_seq[-1], state.c), seq
