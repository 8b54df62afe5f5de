"""The windowed Transformer's C++ kernels (``csrc/``; the extension of :mod:`seqtrojan.agent.fast_lstm`, built and
loaded there), each the same function as the PyTorch path of :class:`seqtrojan.agent.cells.WindowAttentionLayer`
(tested against it, and with gradcheck in float64):

- :func:`band_attention` (``band_attention.cpp``): the PyTorch path computes all T x P scores of a training chunk
  and masks all but ``window`` per query, in about a dozen ops (and their backward), after copies that assemble the
  queries, keys and values; the kernel reads each query's ``window`` slots where they lie (the layer's [q | k | v]
  projection of the chunk and the cached positions before it) in one pass forward and one backward, and hands the
  gradients back in that same layout.
- :func:`add_layer_norm` (``layer_norm.cpp``) and :func:`bias_relu` (``bias_relu.cpp``): a linear layer's bias, the
  residual add and the layer norm after it, or the bias and the MLP's ReLU, in one pass forward and one backward
  (with the bias gradient). At a policy's widths (32, 64) PyTorch's CPU layer norm costs about as much as a matrix
  product of the same rows, and each bias, add and activation is a further pass over the chunk.
- :func:`window_step` (``window_step.cpp``): a rollout step of a whole layer in one call (the five products as BLAS
  calls on one block of envs per thread, the norms, and per env the new cache written and attended over while it
  is in cache), where the PyTorch path is about twenty ops per layer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch.autograd.function import once_differentiable

from seqtrojan.agent import fast_lstm

if TYPE_CHECKING:  # cells imports this module
    from seqtrojan.agent.cells import WindowAttentionLayer


class _BandAttention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, qkv, prefix, allowed, bias, scale: float):
        bias = bias.contiguous()
        batch, steps, width3 = qkv.shape
        heads, window = bias.shape
        out = qkv.new_empty(batch, steps, width3 // 3)
        probs = qkv.new_empty(batch, steps, heads, window)
        ext = fast_lstm.extension()
        assert ext is not None  # callers check fast_lstm.usable first
        ext.band_attention_fwd(qkv, prefix, allowed, bias, out, probs, scale)
        ctx.save_for_backward(qkv, prefix, probs)
        ctx.scale = scale
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        qkv, prefix, probs = ctx.saved_tensors
        dqkv = torch.empty_like(qkv, memory_format=torch.contiguous_format)
        dprefix = qkv.new_empty(prefix.shape)  # zero after the keys and values (the cache's validity flags)
        dscores = torch.empty_like(probs)
        ext = fast_lstm.extension()
        assert ext is not None
        ext.band_attention_bwd(grad.contiguous(), qkv, prefix, probs, dqkv, dprefix, dscores, ctx.scale)
        return dqkv, dprefix, None, dscores.sum((0, 1)), None


def band_attention(
    qkv: torch.Tensor, prefix: torch.Tensor, allowed: torch.Tensor, bias: torch.Tensor, scale: float
) -> torch.Tensor:
    """Attention of a chunk's queries over the ``w`` positions ending at each: ``qkv`` (B, T, 3*H*d) is the chunk's
    [q | k | v] (head h at columns h*d within each part), ``prefix`` (B, w - 1, >= 2*H*d) the keys and values
    [k | v | ...] of the w - 1 positions before the chunk (read in place, any row and batch strides). Query t reads
    slots j = 0 .. w - 1 (position t + j of the w - 1 + T) where ``allowed`` (B, T, w) is true, with scores
    ``q . k * scale + bias[h, j]`` (``bias`` (H, w)); every query must allow its own position, slot w - 1. Returns
    (B, T, H*d); differentiable with respect to ``qkv``, ``prefix`` and ``bias``."""
    return _BandAttention.apply(qkv, prefix, allowed.contiguous(), bias, scale)


def _writable(ctx, product: torch.Tensor) -> torch.Tensor:
    """``product`` itself where a kernel may write over it (an autograd intermediate, such as a matrix product:
    marked dirty), else a contiguous copy (a leaf, or strided)."""
    if product.is_contiguous() and not product.is_leaf:
        ctx.mark_dirty(product)
        return product
    return product.clone(memory_format=torch.contiguous_format)


class _AddLayerNorm(torch.autograd.Function):
    @staticmethod
    def forward(ctx, product, residual, bias, weight, norm_bias, eps: float):
        ctx.set_materialize_grads(False)
        total = _writable(ctx, product)  # the sum is written over it
        y, mean, rstd = torch.empty_like(total), total.new_empty(total.shape[:-1]), total.new_empty(total.shape[:-1])
        ext = fast_lstm.extension()
        assert ext is not None  # callers check fast_lstm.usable first
        ext.layer_norm_fwd(total, bias, None if residual is None else residual.contiguous(), weight, norm_bias, eps, y,
                           mean, rstd)  # fmt: skip
        ctx.save_for_backward(total, weight, mean, rstd)
        ctx.has_residual = residual is not None
        return total, y

    @staticmethod
    @once_differentiable
    def backward(ctx, dtotal, dy):
        total, weight, mean, rstd = ctx.saved_tensors
        if dy is None:  # only the sum was used
            dy = torch.zeros_like(total)
        dx = torch.empty_like(total)
        dweight, dnorm_bias, dbias = (torch.empty_like(weight) for _ in range(3))
        ext = fast_lstm.extension()
        assert ext is not None
        extra = None if dtotal is None else dtotal.contiguous()
        ext.layer_norm_bwd(dy.contiguous(), extra, total, mean, rstd, weight, dx, dweight, dnorm_bias, dbias)
        return dx, dx if ctx.has_residual else None, dbias, dweight, dnorm_bias, None


def add_layer_norm(
    product: torch.Tensor, residual: torch.Tensor | None, bias: torch.Tensor, norm: torch.nn.LayerNorm
) -> tuple[torch.Tensor, torch.Tensor]:
    """``x = product + bias (+ residual)`` and ``norm(x)`` in one pass of the C++ kernel: a linear layer's output
    (``product`` its matrix product without the bias) added to the block's residual stream and normed. Returns
    ``(x, norm(x))``; differentiable with respect to all inputs. Saves the linear layer's bias copy, the residual
    add, and backward the gradient sum and the bias reduction."""
    return _AddLayerNorm.apply(product, residual, bias, norm.weight, norm.bias, norm.eps)


class _BiasReLU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, product, bias):
        y = _writable(ctx, product)
        ext = fast_lstm.extension()
        assert ext is not None  # callers check fast_lstm.usable first
        ext.bias_relu_fwd(y, bias)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (y,) = ctx.saved_tensors
        dx, dbias = torch.empty_like(y), y.new_empty(y.shape[-1])
        ext = fast_lstm.extension()
        assert ext is not None
        ext.bias_relu_bwd(grad.contiguous(), y, dx, dbias)
        return dx, dbias


def bias_relu(product: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``relu(product + bias)`` in one pass of the C++ kernel, ``product`` a linear layer's matrix product without
    its bias (overwritten where it is an autograd intermediate); differentiable with respect to both."""
    return _BiasReLU.apply(product, bias)


def window_step_params(layer: WindowAttentionLayer) -> list[torch.Tensor]:
    """A windowed Transformer layer's 17 tensors in the order ``csrc/window_step.cpp`` reads them."""
    names = ("input", "norm_attention", "qkv", "out", "norm_mlp", "mlp_in", "mlp_out", "norm_out")
    tensors = [t for name in names for t in (getattr(layer, name).weight, getattr(layer, name).bias)]
    return [*tensors, layer.position_bias]


@torch.no_grad()
def window_step(
    layer: WindowAttentionLayer, x: torch.Tensor, keep: torch.Tensor, cache: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One no-grad step of a windowed Transformer layer (``WindowAttentionLayer.step``) in one call of the C++
    kernel (``csrc/window_step.cpp``): ``x`` (B, I), ``keep`` (B,) multiplies the cache first, ``cache`` (B, (w - 1)
    * S) the layer's state c. Returns (h, the next cache): the cache is a view of a fresh (B, w * S) buffer."""
    batch, slot = x.shape[0], layer.slot_width
    h = x.new_empty(batch, layer.hidden_size)
    slots = x.new_empty(batch, layer.window * slot)
    norms = (layer.norm_attention, layer.norm_mlp, layer.norm_out)
    ext = fast_lstm.extension()
    assert ext is not None  # callers check fast_lstm.usable first
    ext.window_layer_step(
        x.contiguous(), keep.contiguous(), cache, window_step_params(layer), [float(n.eps) for n in norms], h, slots,
        fast_lstm.num_chunks(batch),
    )  # fmt: skip
    return h, slots[:, slot:]
