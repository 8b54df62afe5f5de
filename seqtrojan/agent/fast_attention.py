"""The windowed Transformer's band attention on the C++ extension (``csrc/band_attention.cpp``).

Why: the PyTorch path (:meth:`seqtrojan.agent.cells.WindowAttentionLayer._band_attention`) computes all T x P scores
of a training chunk and masks all but ``window`` per query, in about a dozen ops (and their backward); the kernel
reads only each query's ``window`` slots, in one pass forward and one backward. It computes the same function
(tested against the PyTorch path, and with gradcheck in float64); the extension is the one of
:mod:`seqtrojan.agent.fast_lstm`, built and loaded there.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from seqtrojan.agent import fast_lstm


class _BandAttention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, kv, allowed, bias, scale: float):
        q, bias = q.contiguous(), bias.contiguous()
        batch, steps, width = q.shape
        heads, window = bias.shape
        out = q.new_empty(batch, steps, width)
        probs = q.new_empty(batch, steps, heads, window)
        ext = fast_lstm.extension()
        assert ext is not None  # callers check fast_lstm.usable first
        ext.band_attention_fwd(q, kv, allowed, bias, out, probs, scale)
        ctx.save_for_backward(q, kv, probs)
        ctx.scale = scale
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        q, kv, probs = ctx.saved_tensors
        batch, _, width = q.shape
        dq = torch.empty_like(q)
        dkv = q.new_empty(batch, kv.shape[1], 2 * width)
        dscores = torch.empty_like(probs)
        ext = fast_lstm.extension()
        assert ext is not None
        ext.band_attention_bwd(grad.contiguous(), q, kv, probs, dq, dkv, dscores, ctx.scale)
        if kv.shape[2] > 2 * width:  # columns after the keys and values (the cache's validity flags)
            dkv = F.pad(dkv, (0, kv.shape[2] - 2 * width))
        return dq, dkv, None, dscores.sum((0, 1)), None


def band_attention(
    q: torch.Tensor, kv: torch.Tensor, allowed: torch.Tensor, bias: torch.Tensor, scale: float
) -> torch.Tensor:
    """Attention of queries ``q`` (B, T, H*d) over the keys and values in ``kv`` (B, T + w - 1, >= 2*H*d; key of
    head h at columns h*d.., value at H*d + h*d..; a strided row layout is read in place), query t reading slots
    j = 0 .. w - 1 (position t + j) where ``allowed`` (B, T, w) is true, with scores ``q . k * scale + bias[h, j]``
    (``bias`` (H, w)). Every query must allow its own position, slot w - 1. Returns (B, T, H*d); differentiable with
    respect to ``q``, ``kv`` and ``bias``."""
    return _BandAttention.apply(q, kv, allowed.contiguous(), bias, scale)
