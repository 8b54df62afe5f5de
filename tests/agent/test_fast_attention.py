"""The C++ band attention equals the Transformer layer's PyTorch path: unroll, gradients, steps, gradcheck."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.cells import WindowAttentionLayer
from seqtrojan.agent.fast_attention import band_attention
from seqtrojan.agent.state import LSTMState

pytestmark = pytest.mark.skipif(fast_lstm.extension() is None, reason=f"C++ kernels unavailable: {fast_lstm.error()}")


def _layer(heads: int, dtype: torch.dtype, window: int = 4) -> WindowAttentionLayer:
    layer = WindowAttentionLayer(5, 8, window, heads).to(dtype)
    with torch.no_grad():
        layer.position_bias.normal_()  # zero at init: a wrong slot order would go unseen
    return layer


def _inputs(layer: WindowAttentionLayer, steps: int, batch: int, dtype: torch.dtype):
    """x, keep with episode starts inside the chunk, and a start cache with an empty slot."""
    x = torch.randn(steps, batch, layer.input_size, dtype=dtype)
    keep = (torch.rand(steps, batch) > 0.25).to(dtype)
    keep[0, 0], keep[1:, 1] = 1, 1
    cache = torch.randn(batch, layer.window - 1, layer.slot_width, dtype=dtype)
    cache[..., -1] = 1.0
    cache[0, 0, -1] = 0.0  # the oldest slot of env 0 is empty
    return x, keep, LSTMState(torch.zeros(batch, layer.hidden_size, dtype=dtype), cache.flatten(1))


@pytest.mark.parametrize("steps", [9, 2])  # a chunk longer and one shorter than the cache
@pytest.mark.parametrize("heads", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unroll_and_gradients_equal_the_torch_path(heads, dtype, steps):
    torch.manual_seed(heads)
    layer = _layer(heads, dtype)
    x, keep, start = _inputs(layer, steps, 6, dtype)
    results = []
    for fast in (False, True):
        layer.zero_grad()
        h_seq, final, states = layer.unroll(x, start, keep, True, fast)
        (h_seq.sin().sum() + final.c.cos().sum()).backward()
        results.append((h_seq.detach(), states.c.detach(), [p.grad.clone() for p in layer.parameters()]))
    (h_a, c_a, g_a), (h_b, c_b, g_b) = results
    tol = {"atol": 1e-5, "rtol": 1e-4} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-10}
    torch.testing.assert_close(h_a, h_b, **tol)
    torch.testing.assert_close(c_a, c_b, **tol)
    assert layer.position_bias.grad.abs().sum() > 0
    for a, b in zip(g_a, g_b):
        torch.testing.assert_close(a, b, **tol)
    with torch.no_grad():  # without every step's state, the final cache comes from the chunk's last positions
        _, final, _ = layer.unroll(x, start, keep, False, True)
    torch.testing.assert_close(final.c, c_a[-1], **tol)


@pytest.mark.parametrize("heads", [1, 2])
def test_a_step_reads_the_cache_in_place_and_equals_the_torch_step(heads):
    torch.manual_seed(3)
    layer = _layer(heads, torch.float32)
    x, keep, start = _inputs(layer, 1, 7, torch.float32)
    keep[0, 2] = 0  # an episode start empties env 2's cache
    with torch.no_grad():
        expected = layer.step(x[0], start, keep[0], False)
        got = layer.step(x[0], start, keep[0], True)
    torch.testing.assert_close(got.h, expected.h, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(got.c, expected.c)


def test_band_attention_passes_gradcheck_in_float64():
    torch.manual_seed(0)
    batch, steps, heads, d, window = 2, 5, 2, 3, 3
    qkv = torch.randn(batch, steps, 3 * heads * d, dtype=torch.float64, requires_grad=True)
    # the cached positions with a validity column after the keys and values, as the layer's cache holds them
    prefix = torch.randn(batch, window - 1, 2 * heads * d + 1, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(heads, window, dtype=torch.float64, requires_grad=True)
    allowed = torch.rand(batch, steps, window) > 0.3
    allowed[..., -1] = True
    assert torch.autograd.gradcheck(lambda a, b, c: band_attention(a, b, allowed, c, 0.7), (qkv, prefix, bias))


def test_mismatched_shapes_are_refused_in_one_line():
    qkv = torch.randn(2, 5, 12)
    with pytest.raises(RuntimeError, match="the prefix does not match qkv and the window"):
        band_attention(qkv, torch.randn(2, 5, 8), torch.ones(2, 5, 3, dtype=torch.bool), torch.zeros(1, 3), 1.0)
