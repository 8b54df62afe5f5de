"""LSTM layers: the paper's (:class:`torch.nn.LSTMCell`) and one with peephole connections, sharing one PyTorch
reference unroll and the C++ kernels of :mod:`seqtrojan.agent.fast_lstm`."""

from __future__ import annotations

import torch
from torch import nn

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.cells.base import LayerOutput, Shapes, gate_shapes, orthogonal_gates, silence_gate_rows
from seqtrojan.agent.state import LSTMState
from seqtrojan.agent.weight_stats import gated_layer_features


class LSTMLayer(nn.LSTMCell):
    """:class:`torch.nn.LSTMCell` (same parameters, names and random draws) with the layer contract."""

    cell = "lstm"
    fused_stack_step = True
    c_is_memory = True
    weight_features = staticmethod(gated_layer_features)

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> LSTMLayer:
        return cls(input_size, width)

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        return gate_shapes(4, input_size, width)

    def silence_units(self, units: torch.Tensor) -> None:
        """Zero rows of every gate keep the units' c and h at 0."""
        silence_gate_rows(self, 4, self.hidden_size, units)

    @property
    def c_width(self) -> int:
        return self.hidden_size

    def init_weights(self, forget_bias: float) -> None:
        orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)
        with torch.no_grad():
            self.bias_ih[self.hidden_size : 2 * self.hidden_size] = forget_bias  # gate order i, f, g, o

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        if keep is not None:
            state = LSTMState(state.h * keep[:, None], state.c * keep[:, None])
        h, c = self(x, (state.h, state.c))
        return LSTMState(h, c)

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput:
        if fast:
            h_seq, c_out = fast_lstm.unroll_layer(self, x, keep.contiguous(), state.h, state.c, return_states)
            return _kernel_output(h_seq, c_out, return_states)
        return _gated_unroll(self, x, state, keep, return_states, peephole=None)


class PeepholeLSTMLayer(nn.Module):
    """An LSTM layer with peephole connections: ``peephole`` (3, H) rows are the input, forget and output gates'
    diagonal weights on the cell state (``c_{t-1}`` for input and forget, ``c_t`` for output)."""

    cell = "lstm_peephole"
    fused_stack_step = False
    c_is_memory = True
    weight_features = staticmethod(gated_layer_features)

    def __init__(self, input_size: int, hidden_size: int) -> None:
        super().__init__()
        self.input_size = input_size
        self.hidden_size = hidden_size
        self.weight_ih = nn.Parameter(torch.empty(4 * hidden_size, input_size))
        self.weight_hh = nn.Parameter(torch.empty(4 * hidden_size, hidden_size))
        self.bias_ih = nn.Parameter(torch.empty(4 * hidden_size))
        self.bias_hh = nn.Parameter(torch.empty(4 * hidden_size))
        self.peephole = nn.Parameter(torch.empty(3, hidden_size))
        self.init_weights(0.0)

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> PeepholeLSTMLayer:
        return cls(input_size, width)

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        return {**gate_shapes(4, input_size, width), "peephole": (3, width)}

    def silence_units(self, units: torch.Tensor) -> None:
        """Zero gate rows and peepholes keep the units' c and h at 0."""
        silence_gate_rows(self, 4, self.hidden_size, units)
        with torch.no_grad():
            self.peephole[:, units] = 0.0

    @property
    def c_width(self) -> int:
        return self.hidden_size

    def init_weights(self, forget_bias: float) -> None:
        orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh, self.peephole)
        with torch.no_grad():
            self.bias_ih[self.hidden_size : 2 * self.hidden_size] = forget_bias

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        keep = torch.ones(x.shape[0], dtype=x.dtype, device=x.device) if keep is None else keep
        if fast and not torch.is_grad_enabled():
            h, c = fast_lstm.step_peephole_layer(self, x, keep.contiguous(), state.h, state.c)
            return LSTMState(h, c)
        _, final, _ = _gated_unroll(self, x.unsqueeze(0), state, keep.unsqueeze(0), False, peephole=self.peephole)
        return final

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput:
        if fast:
            h_seq, c_out = fast_lstm.unroll_peephole_layer(self, x, keep.contiguous(), state.h, state.c, return_states)
            return _kernel_output(h_seq, c_out, return_states)
        return _gated_unroll(self, x, state, keep, return_states, peephole=self.peephole)


def _kernel_output(h_seq: torch.Tensor, c_out: torch.Tensor, return_states: bool) -> LayerOutput:
    """A fused LSTM kernel's (h_seq, c_seq or final c) as a layer's output."""
    if return_states:
        return h_seq, LSTMState(h_seq[-1], c_out[-1]), LSTMState(h_seq, c_out)
    return h_seq, LSTMState(h_seq[-1], c_out), None


def _gated_unroll(
    cell: LSTMLayer | PeepholeLSTMLayer,
    x: torch.Tensor,
    state: LSTMState,
    keep: torch.Tensor,
    return_states: bool,
    peephole: torch.Tensor | None,
) -> LayerOutput:
    """The PyTorch reference of an (optionally peephole) LSTM layer over T steps; ``keep`` (T, B) zeroes the
    state before a step where it is 0."""
    steps = x.shape[0]
    keeps = keep.unsqueeze(-1).unbind(0)  # T x (B, 1)
    hidden = cell.hidden_size
    bias = cell.bias_ih + cell.bias_hh
    projected = torch.addmm(bias, x.reshape(-1, x.shape[-1]), cell.weight_ih.t())  # (T*B, 4H)
    # unbind, not projected[k]: indexing would make every step's backward build a full-size zero tensor (O(T^2)).
    gates_x = projected.view(steps, -1, 4 * hidden).unbind(0)
    w_hh = cell.weight_hh.t()
    h, c = state.h, state.c
    hs, cs = [], []
    for k in range(steps):
        h = h * keeps[k]
        c = c * keeps[k]
        i, f, g, o = torch.addmm(gates_x[k], h, w_hh).chunk(4, 1)
        if peephole is not None:
            i = i + peephole[0] * c
            f = f + peephole[1] * c
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        if peephole is not None:
            o = o + peephole[2] * c
        h = torch.sigmoid(o) * torch.tanh(c)
        hs.append(h)
        if return_states:
            cs.append(c)
    h_seq = torch.stack(hs)
    seq = LSTMState(h_seq, torch.stack(cs)) if return_states else None
    return h_seq, LSTMState(h, c), seq
