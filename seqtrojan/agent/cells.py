"""The sequence-model layers an agent can stack: LSTM, peephole LSTM, GRU and a windowed causal Transformer.

Every layer has the same contract, so that training, analysis, interventions, the monitor and the checkpoints work
on any of them: a per-layer state :class:`~seqtrojan.agent.state.LSTMState` ``(h, c)`` of 2-d tensors (batch, width)
goes in and comes out of every step, and ``keep`` (1 - episode start) multiplies the state before a step.

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

import math
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import nn

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.fast_attention import add_layer_norm, band_attention, bias_relu, window_step
from seqtrojan.agent.state import LSTMState
from seqtrojan.config import CELLS

__all__ = ["CELLS", "CellLayer", "layer_shapes", "make_cell"]

LayerOutput = tuple[torch.Tensor, LSTMState, LSTMState | None]
"""an unroll's h sequence (T, B, H), its final state, and its (h, c) sequences (each (T, B, ·)) when asked"""


class CellLayer(Protocol):
    """One layer of the stack (see the module docstring)."""

    cell: str
    input_size: int
    hidden_size: int

    @property
    def c_width(self) -> int: ...

    def init_weights(self, forget_bias: float) -> None: ...

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        """One step from ``state``, multiplied by ``keep`` (B,) first when given (0: an episode starts)."""
        ...

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput: ...


# ---------------------------------------------------------------------------------------------- LSTM
def _orthogonal_gates(weight_ih: torch.Tensor, weight_hh: torch.Tensor, *biases: torch.Tensor) -> None:
    nn.init.orthogonal_(weight_ih)
    nn.init.orthogonal_(weight_hh)
    for b in biases:
        nn.init.zeros_(b)


class LSTMLayer(nn.LSTMCell):
    """:class:`torch.nn.LSTMCell` (same parameters, names and random draws) with the layer contract."""

    cell = "lstm"

    @property
    def c_width(self) -> int:
        return self.hidden_size

    def init_weights(self, forget_bias: float) -> None:
        _orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)
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

    @property
    def c_width(self) -> int:
        return self.hidden_size

    def init_weights(self, forget_bias: float) -> None:
        _orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh, self.peephole)
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


# ---------------------------------------------------------------------------------------------- GRU
class GRULayer(nn.GRUCell):
    """:class:`torch.nn.GRUCell` with the layer contract; its ``c`` is empty (width 0).

    Initialised like the LSTM: orthogonal weights, zero biases, and the update gate's input bias at
    ``forget_bias`` (an update gate near 1 keeps the previous h, as a forget gate near 1 keeps c)."""

    cell = "gru"

    @property
    def c_width(self) -> int:
        return 0

    def init_weights(self, forget_bias: float) -> None:
        _orthogonal_gates(self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)
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


# ---------------------------------------------------------------------------------------------- Transformer
class WindowAttentionLayer(nn.Module):
    """A pre-norm Transformer block over the last ``window`` layer inputs, causal by construction.

    For the current input ``x``: ``e = input(x)``; its query attends over the keys and values of the current input
    and of the ``window - 1`` before it (``heads`` heads; scores plus a learned bias per head and slot; only valid
    slots of the same episode); ``y = e + out(attention)``; ``y = y + mlp(norm(y))``; ``h = norm(y)``.

    The state ``c`` is the key-value cache of the ``window - 1`` previous inputs: per slot (oldest first) the key,
    the value and a validity flag (0 for an empty slot), so that a step computes one new key and value, not
    ``window`` of them. As with an LSTM's stored state, a training unroll starts from the cache the rollout
    recorded (computed with the weights of that time); inside the unroll everything is recomputed.
    """

    cell = "transformer"

    def __init__(self, input_size: int, hidden_size: int, window: int, heads: int) -> None:
        super().__init__()
        if hidden_size % heads:
            raise ValueError(f"a transformer layer's width ({hidden_size}) must be divisible by its heads ({heads})")
        self.input_size = input_size
        self.hidden_size = hidden_size
        self.window = window
        self.heads = heads
        self.input = nn.Linear(input_size, hidden_size)
        self.norm_attention = nn.LayerNorm(hidden_size)
        self.qkv = nn.Linear(hidden_size, 3 * hidden_size)
        self.out = nn.Linear(hidden_size, hidden_size)
        self.norm_mlp = nn.LayerNorm(hidden_size)
        self.mlp_in = nn.Linear(hidden_size, hidden_size)
        self.mlp_out = nn.Linear(hidden_size, hidden_size)
        self.norm_out = nn.LayerNorm(hidden_size)
        self.position_bias = nn.Parameter(torch.zeros(heads, window))
        """added to the attention scores of each slot (0 the oldest, window - 1 the current step)"""
        self.init_weights(0.0)

    @property
    def slot_width(self) -> int:
        """one cached input: its key, its value and its validity flag"""
        return 2 * self.hidden_size + 1

    @property
    def c_width(self) -> int:
        return (self.window - 1) * self.slot_width

    def init_weights(self, forget_bias: float) -> None:
        """Orthogonal linear weights, zero biases and position biases (``forget_bias`` has no analogue here)."""
        for layer in (self.input, self.qkv, self.out, self.mlp_in, self.mlp_out):
            nn.init.orthogonal_(layer.weight)
            nn.init.zeros_(layer.bias)
        nn.init.zeros_(self.position_bias)
        for norm in (self.norm_attention, self.norm_mlp, self.norm_out):
            norm.reset_parameters()

    def _project(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Embeddings ``e`` (..., W), queries (..., heads, d) and the cache slots [key | value | 1] (..., 2W + 1)."""
        e = self.input(x)
        q, kv = self.qkv(self.norm_attention(e)).split((self.hidden_size, 2 * self.hidden_size), -1)
        slots = torch.cat([kv, kv.new_ones(*kv.shape[:-1], 1)], -1)
        return e, q.unflatten(-1, (self.heads, self.hidden_size // self.heads)), slots

    def _finish(self, e: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        """The rest of the block after attention: residual, MLP, output norm."""
        y = e + self.out(attended)
        y = y + self.mlp_out(F.relu(self.mlp_in(self.norm_mlp(y))))
        return self.norm_out(y)

    def _finish_fast(self, e: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        """:meth:`_finish` with each residual add, bias and norm in one pass of the C++ kernel."""
        y, normed = add_layer_norm(attended @ self.out.weight.t(), e, self.out.bias, self.norm_mlp)
        hidden = bias_relu(normed @ self.mlp_in.weight.t(), self.mlp_in.bias)
        return add_layer_norm(hidden @ self.mlp_out.weight.t(), y, self.mlp_out.bias, self.norm_out)[1]

    def step(self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor | None, fast: bool) -> LSTMState:
        batch, w, width = x.shape[0], self.window, self.slot_width
        if fast:  # the whole layer in one call of the C++ kernel (it reads the cache in place)
            h, cache = window_step(self, x, x.new_ones(batch) if keep is None else keep, state.c)
            return LSTMState(h, cache)
        e = self.input(x)
        qkv = self.qkv(self.norm_attention(e))  # (B, 3W): [q | k | v]
        q, kv = qkv.split((self.hidden_size, 2 * self.hidden_size), -1)
        # one buffer of all window slots; the next state is a view of its newest w - 1 (no second copy)
        slots = x.new_empty(batch, w, width)
        cache = state.c.reshape(batch, w - 1, width)
        if keep is None:
            slots[:, : w - 1] = cache
        elif torch.is_grad_enabled():
            slots[:, : w - 1] = cache * keep.view(batch, 1, 1)
        else:  # the rollout: mask while copying, one pass over the cache
            torch.mul(cache, keep.view(batch, 1, 1), out=slots[:, : w - 1])
        slots[:, -1, :-1] = kv
        slots[:, -1, -1] = 1.0
        heads, d, width_h = self.heads, self.hidden_size // self.heads, self.hidden_size
        keys = slots[..., :width_h].unflatten(-1, (heads, d)).transpose(1, 2)  # (B, heads, w, d), strided views
        values = slots[..., width_h : 2 * width_h].unflatten(-1, (heads, d)).transpose(1, 2)
        scores = (keys @ q.unflatten(-1, (heads, d)).unsqueeze(-1)).squeeze(-1) / math.sqrt(d)  # (B, heads, w)
        scores = (scores + self.position_bias).masked_fill((slots[..., -1] <= 0).unsqueeze(1), float("-inf"))
        attended = (torch.softmax(scores, -1).unsqueeze(-2) @ values).flatten(1)  # (B, W)
        return LSTMState(self._finish(e, attended), slots.view(batch, w * width)[:, width:])

    def unroll(
        self, x: torch.Tensor, state: LSTMState, keep: torch.Tensor, return_states: bool, fast: bool
    ) -> LayerOutput:
        # Computed batch-major (B, T, .): the attention products need no permuted copies, and a stacked layer
        # reads the one below in that layout (h_seq is returned as a time-major view of it).
        steps, batch = x.shape[:2]
        w, width, slot = self.window, self.hidden_size, self.slot_width
        if fast:  # the input layer's bias and the norm in one pass of the C++ kernel
            e, normed = add_layer_norm(x.transpose(0, 1) @ self.input.weight.t(), None, self.input.bias,
                                       self.norm_attention)  # fmt: skip
        else:
            e = self.input(x.transpose(0, 1))  # (B, T, W)
            normed = self.norm_attention(e)
        qkv = self.qkv(normed)  # (B, T, 3W): [q | k | v]
        prefix = state.c.reshape(batch, w - 1, slot) * keep[0].view(batch, 1, 1)  # emptied by an episode start
        valid = torch.cat([prefix[..., -1] > 0, qkv.new_ones(batch, steps, dtype=torch.bool)], 1)  # (B, P)
        # episode of each position: the prefix is episode 0, and every episode start inside the chunk opens the next
        episode = torch.cat([keep.new_zeros(batch, w - 1), torch.cumsum(1 - keep.t(), 1)], 1)  # (B, P)
        kv = None
        if fast:  # the kernel reads q, k and v where they lie: no (B, P, 2W) copy
            # slot j of query t is position t + j: readable if valid and of the query's episode
            window_episodes = episode.unfold(1, w, 1)  # (B, T, w) views
            allowed = valid.unfold(1, w, 1) & (window_episodes == window_episodes[..., -1:])
            attended = band_attention(qkv, prefix, allowed, self.position_bias, 1 / math.sqrt(width // self.heads))
        else:
            kv = torch.cat([prefix[..., :-1], qkv[..., width:]], 1)  # (B, P, 2W), P = w - 1 + T
            attended = self._band_attention(qkv[..., :width], kv, valid, episode)
        h_seq = (self._finish_fast if fast else self._finish)(e, attended).transpose(0, 1)  # (T, B, W) view
        # the state after each step: the newest w - 1 slots, emptied where they precede an episode start
        if return_states:
            kv = torch.cat([prefix[..., :-1], qkv[..., width:]], 1) if kv is None else kv
            caches = self._caches(kv, valid, episode, range(1, steps + 1))
        else:  # only the last one: the newest w - 1 positions (the prefix's last ones, then the chunk's)
            new = qkv[:, max(0, steps - (w - 1)) :, width:]
            tail = torch.cat([
                torch.cat([prefix[:, steps:, :-1], (prefix[:, steps:, -1:] > 0).to(qkv.dtype)], -1),
                torch.cat([new, new.new_ones(*new.shape[:-1], 1)], -1),
            ], 1)  # (B, w - 1, S) [key | value | valid]  # fmt: skip
            same = (episode[:, steps:] == episode[:, -1:]).unsqueeze(-1)  # of the newest position's episode
            caches = (tail * same).flatten(1).unsqueeze(0)
        final = LSTMState(h_seq[-1], caches[-1])
        return h_seq, final, LSTMState(h_seq, caches) if return_states else None

    def _band_attention(
        self, q: torch.Tensor, kv: torch.Tensor, valid: torch.Tensor, episode: torch.Tensor
    ) -> torch.Tensor:
        """Attention of T queries (B, T, W) over the P = w - 1 + T keys and values ``kv`` (B, P, 2W), each query
        reading the window of positions ending at its own (a band), valid and of its episode: one batched matrix
        product over all positions, whose backward is far cheaper than that of per-window views. (B, T, W)."""
        steps, w, heads = q.shape[1], self.window, self.heads
        d, width = self.hidden_size // heads, self.hidden_size

        def split(t: torch.Tensor) -> torch.Tensor:  # (B, n, W) -> (B, heads, n, d); one head: a view, no copy
            return t.unsqueeze(1) if heads == 1 else t.unflatten(-1, (heads, d)).transpose(1, 2)

        qh, keys, values = split(q), split(kv[..., :width]), split(kv[..., width:])
        offset = torch.arange(kv.shape[1], device=q.device)[None, :] - torch.arange(steps, device=q.device)[:, None]
        band = (offset >= 0) & (offset < w)  # (T, P): the slot of key p for query t is p - t
        bias = self.position_bias[:, offset.clamp(0, w - 1)]  # (heads, T, P)
        allowed = band & valid[:, None, :] & (episode[:, None, :] == episode[:, w - 1 :, None])  # (B, T, P)
        scores = (qh @ keys.transpose(-1, -2)) / math.sqrt(d) + bias  # (B, heads, T, P)
        scores = scores.masked_fill(~allowed[:, None], float("-inf"))
        attended = torch.softmax(scores, -1) @ values  # (B, heads, T, d)
        return attended.squeeze(1) if heads == 1 else attended.transpose(1, 2).flatten(-2)

    def _caches(self, kv: torch.Tensor, valid: torch.Tensor, episode: torch.Tensor, starts: range) -> torch.Tensor:
        """The stored caches (len(starts), B, c_width): positions s .. s + window - 2 as [key | value | valid]
        slots, each kept only if it belongs to the episode of the cache's newest position."""
        w = self.window
        if w == 1:
            return kv.new_zeros(len(starts), kv.shape[0], 0)
        index = torch.tensor([list(range(s, s + w - 1)) for s in starts], device=kv.device)  # (N, w - 1)
        same = (episode[:, index] == episode[:, index[:, -1:]]).unsqueeze(-1)  # (B, N, w - 1, 1)
        slots = torch.cat([kv[:, index], valid[:, index].unsqueeze(-1).to(kv.dtype)], -1) * same  # (B, N, w - 1, S)
        return slots.transpose(0, 1).flatten(2)


def make_cell(cell: str, input_size: int, hidden_size: int, window: int = 8, heads: int = 1) -> nn.Module:
    """One layer of the named cell (see :data:`CELLS`)."""
    if cell == "lstm":
        return LSTMLayer(input_size, hidden_size)
    if cell == "lstm_peephole":
        return PeepholeLSTMLayer(input_size, hidden_size)
    if cell == "gru":
        return GRULayer(input_size, hidden_size)
    if cell == "transformer":
        return WindowAttentionLayer(input_size, hidden_size, window, heads)
    raise ValueError(f"unknown cell {cell!r}; known: {', '.join(CELLS)}")


def layer_shapes(cell: str, input_size: int, width: int, window: int = 8, heads: int = 1) -> dict[str, tuple[int, ...]]:
    """One layer's parameter names and shapes (as in its state_dict), computed without building it (a model card is
    checked against them before anything is allocated)."""
    if cell in ("lstm", "lstm_peephole", "gru"):
        rows = (3 if cell == "gru" else 4) * width
        shapes = {"weight_ih": (rows, input_size), "weight_hh": (rows, width), "bias_ih": (rows,), "bias_hh": (rows,)}
        if cell == "lstm_peephole":
            shapes["peephole"] = (3, width)
        return shapes
    if cell == "transformer":
        linears = {"input": (width, input_size), "qkv": (3 * width, width), "out": (width, width),
                   "mlp_in": (width, width), "mlp_out": (width, width)}  # fmt: skip
        shapes = {}
        for name, (rows, cols) in linears.items():
            shapes[f"{name}.weight"], shapes[f"{name}.bias"] = (rows, cols), (rows,)
        for norm in ("norm_attention", "norm_mlp", "norm_out"):
            shapes[f"{norm}.weight"], shapes[f"{norm}.bias"] = (width,), (width,)
        shapes["position_bias"] = (heads, window)
        return shapes
    raise ValueError(f"unknown cell {cell!r}; known: {', '.join(CELLS)}")
