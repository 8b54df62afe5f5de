"""The GRU layer (:class:`torch.nn.GRUCell`), with the C++ kernels of ``csrc/gru.cpp``."""

from __future__ import annotations

import torch
from torch import nn

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.cells.base import LayerOutput, Shapes, gate_shapes, orthogonal_gates, silence_gate_rows
from seqtrojan.agent.state import LSTMState
from seqtrojan.agent.weight_stats import gated_layer_features


class GRULayer(nn.GRUCell):
    """:class:`torch.nn.GRUCell` with the layer contract; its ``c`` is empty (width 0).

    Initialised like the LSTM: orthogonal weights, zero biases, and the update gate's input bias at
    ``forget_bias`` (an update gate near 1 keeps the previous h, as a forget gate near 1 keeps c)."""

    cell = "gru"
    fused_stack_step = False
    c_is_memory = False
    weight_features = staticmethod(gated_layer_features)

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> GRULayer:
        return cls(input_size, width)

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        return gate_shapes(3, input_size, width)

    def silence_units(self, units: torch.Tensor) -> None:
        """Zero rows of every gate keep the units' h at 0 (h = n / 2 + h_prev / 2 with n = 0)."""
        silence_gate_rows(self, 3, self.hidden_size, units)

    @property
    def c_width(self) -> int:
        return 0

    def init_weights(self, forget_bias: float) -> None:
        orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)
        with torch.no_grad():
            self.bias_ih[self.hidden_size : 2 * self.hidden_size] = forget_bias  # gate order r, z, n

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        if fast and not torch.is_grad_enabled():
            keep = torch.ones(x.shape[0], dtype=x.dtype) if keep is None else keep
            return LSTMState(fast_lstm.step_gru_layer(self, x, keep.contiguous(), state.h), state.c)
        h = state.h if keep is None else state.h * keep[:, None]
        return LSTMState(self(x, h), state.c)

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput:
        empty = state.c
        if fast:
            h_seq = fast_lstm.unroll_gru_layer(self, x, keep.contiguous(), state.h, return_states)
        else:
            h_seq = self._unroll_torch(x, state.h, keep)
        seq = LSTMState(h_seq, empty.new_zeros(*h_seq.shape[:2], 0)) if return_states else None
        return h_seq, LSTMState(h_seq[-1], empty), seq

    def _unroll_torch(self, x: torch.Tensor, h: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        steps, hidden = x.shape[0], self.hidden_size
        projected = torch.addmm(self.bias_ih, x.reshape(-1, x.shape[-1]), self.weight_ih.t())
        gates_x = projected.view(steps, -1, 3 * hidden).unbind(0)
        keeps = keep.unsqueeze(-1).unbind(0)
        w_hh = self.weight_hh.t()
        hs = []
        for k in range(steps):
            h = h * keeps[k]
            xr, xz, xn = gates_x[k].chunk(3, 1)
            hr, hz, hn = torch.addmm(self.bias_hh, h, w_hh).chunk(3, 1)
            r = torch.sigmoid(xr + hr)
            z = torch.sigmoid(xz + hz)
            n = torch.tanh(xn + r * hn)
            h = (1 - z) * n + z * h
            hs.append(h)
        return torch.stack(hs)
