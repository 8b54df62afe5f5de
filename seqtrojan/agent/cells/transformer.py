"""The windowed causal Transformer layer, with the C++ kernels of :mod:`seqtrojan.agent.fast_attention`."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from seqtrojan.agent.cells.base import LayerOutput, Shapes
from seqtrojan.agent.fast_attention import add_layer_norm, band_attention, bias_relu, window_step
from seqtrojan.agent.state import LSTMState
from seqtrojan.agent.weight_stats import attention_layer_features


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
    fused_stack_step = False
    c_is_memory = False
    weight_features = staticmethod(attention_layer_features)

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

    @classmethod
    def build(cls, input_size: int, width: int, window: int, heads: int) -> WindowAttentionLayer:
        return cls(input_size, width, window, heads)

    @staticmethod
    def parameter_shapes(input_size: int, width: int, window: int, heads: int) -> Shapes:
        linears = {"input": (width, input_size), "qkv": (3 * width, width), "out": (width, width),
                   "mlp_in": (width, width), "mlp_out": (width, width)}  # fmt: skip
        shapes: Shapes = {}
        for name, (rows, cols) in linears.items():
            shapes[f"{name}.weight"], shapes[f"{name}.bias"] = (rows, cols), (rows,)
        for norm in ("norm_attention", "norm_mlp", "norm_out"):
            shapes[f"{norm}.weight"], shapes[f"{norm}.bias"] = (width,), (width,)
        shapes["position_bias"] = (heads, window)
        return shapes

    def silence_units(self, units: torch.Tensor) -> None:
        """Zero the output norm's weight and bias of the units: those output features are 0."""
        with torch.no_grad():
            for p in (self.norm_out.weight, self.norm_out.bias):
                p[units] = 0.0

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
