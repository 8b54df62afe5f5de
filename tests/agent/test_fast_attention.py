"""The Transformer's C++ kernels (band attention, bias + residual + layer norm, bias + ReLU, the one-call rollout
step) equal its PyTorch path: unroll, gradients, steps, gradcheck. Head widths 4 and 8 take the attention kernel's
general path, 16 and 32 its compiled-width one."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.cells import WindowAttentionLayer
from seqtrojan.agent.fast_attention import _AddLayerNorm, add_layer_norm, band_attention, bias_relu
from seqtrojan.agent.state import LSTMState

pytestmark = pytest.mark.skipif(fast_lstm.extension() is None, reason=f"C++ kernels unavailable: {fast_lstm.error()}")


def _layer(heads: int, dtype: torch.dtype, window: int = 4, width: int = 8) -> WindowAttentionLayer:
    layer = WindowAttentionLayer(5, width, window, heads).to(dtype)
    with torch.no_grad():
        layer.position_bias.normal_()  # zero at init: a wrong slot order would go unseen
        for norm in (layer.norm_attention, layer.norm_mlp, layer.norm_out):  # ones and zeros at init
            norm.weight.normal_()
            norm.bias.normal_()
    return layer


def _inputs(layer: WindowAttentionLayer, steps: int, batch: int, dtype: torch.dtype):
    """x, keep with episode starts inside the chunk, and a start cache with an empty slot."""
    x = torch.randn(steps, batch, layer.input_size, dtype=dtype)
    keep = (torch.rand(steps, batch) > 0.25).to(dtype)
    keep[0, 0], keep[1:, 1] = 1, 1
    cache = torch.randn(batch, layer.window - 1, layer.slot_width, dtype=dtype)
    cache[..., -1] = 1.0
    if layer.window > 1:
        cache[0, 0, -1] = 0.0  # the oldest slot of env 0 is empty
    return x, keep, LSTMState(torch.zeros(batch, layer.hidden_size, dtype=dtype), cache.flatten(1))


@pytest.mark.parametrize("steps", [9, 3, 2])  # a chunk longer than the cache, as long, shorter
@pytest.mark.parametrize("heads", [1, 2])
@pytest.mark.parametrize("width", [8, 32])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unroll_and_gradients_equal_the_torch_path(heads, dtype, steps, width):
    torch.manual_seed(heads)
    layer = _layer(heads, dtype, width=width)
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
@pytest.mark.parametrize("width", [8, 32])
@pytest.mark.parametrize(("window", "dtype"), [(4, torch.float32), (4, torch.float64), (1, torch.float32)])
def test_a_step_in_one_kernel_call_equals_the_torch_step(heads, width, window, dtype):
    torch.manual_seed(3)
    layer = _layer(heads, dtype, window=window, width=width)
    x, keep, start = _inputs(layer, 1, 7, dtype)
    keep[0, 2] = 0  # an episode start empties env 2's cache
    tol = {"atol": 1e-6, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-10}
    with torch.no_grad():
        for k in (keep[0], None):
            expected = layer.step(x[0], start, k, False)
            got = layer.step(x[0], start, k, True)
            torch.testing.assert_close(got.h, expected.h, **tol)
            torch.testing.assert_close(got.c, expected.c)
            # and from a cache that is a view into the previous step's buffer (as in a rollout)
            torch.testing.assert_close(layer.step(x[0], got, k, True).h, layer.step(x[0], expected, k, False).h, **tol)


@pytest.mark.parametrize("d", [3, 16])
def test_band_attention_passes_gradcheck_in_float64(d):
    torch.manual_seed(0)
    batch, steps, heads, window = 2, 5, 2, 3
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


@pytest.mark.parametrize("width", [5, 64])
@pytest.mark.parametrize("rows", [(3,), (2, 150)])  # fewer rows than one block of the weight gradients, and more
@pytest.mark.parametrize("with_residual", [False, True])
def test_add_layer_norm_equals_torch_and_its_gradients(width, rows, with_residual):
    torch.manual_seed(width)
    norm = torch.nn.LayerNorm(width)
    with torch.no_grad():
        norm.weight.normal_()
        norm.bias.normal_()
    leaves = [(torch.randn(*rows, width) * 3 + 1).requires_grad_() for _ in range(2)]  # the product, the residual
    bias = torch.randn(width, requires_grad=True)
    grads = torch.randn(*rows, width), torch.randn(*rows, width)  # of the sum's other use and of the normed sum
    results = []
    for fast in (False, True):
        for t in (*leaves, bias, norm.weight, norm.bias):
            t.grad = None
        product = leaves[0] * 1.0  # an intermediate, as a matrix product is: the kernel writes the sum over it
        residual = leaves[1] if with_residual else None
        if fast:
            total, y = add_layer_norm(product, residual, bias, norm)
        else:
            total = product + bias + (residual if residual is not None else 0)
            y = norm(total)
        torch.autograd.backward((total, y), grads)
        found = [total.detach(), y.detach(), leaves[0].grad, bias.grad, norm.weight.grad, norm.bias.grad]
        results.append(found + ([leaves[1].grad] if with_residual else []))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_add_layer_norm_passes_gradcheck_in_float64():
    torch.manual_seed(1)
    product, residual = (torch.randn(4, 3, 6, dtype=torch.float64, requires_grad=True) for _ in range(2))
    bias, weight, norm_bias = (torch.randn(6, dtype=torch.float64, requires_grad=True) for _ in range(3))

    def f(*args):
        total, y = _AddLayerNorm.apply(*args, 1e-5)
        return total.sin(), y  # both outputs, each with its own gradient

    assert torch.autograd.gradcheck(f, (product, residual, bias, weight, norm_bias))
    assert torch.autograd.gradcheck(lambda *a: f(a[0], None, *a[1:])[1], (product, bias, weight, norm_bias))


def test_bias_relu_equals_torch_and_passes_gradcheck():
    torch.manual_seed(2)
    leaf = torch.randn(3, 150, 16, requires_grad=True)
    bias = torch.randn(16, requires_grad=True)
    grad = torch.randn(3, 150, 16)
    results = []
    for fast in (False, True):
        leaf.grad, bias.grad = None, None
        product = leaf * 1.0  # an intermediate, as a matrix product is: the kernel writes over it
        y = bias_relu(product, bias) if fast else torch.relu(product + bias)
        y.backward(grad)
        results.append((y.detach(), leaf.grad, bias.grad))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    x64 = torch.randn(5, 7, dtype=torch.float64, requires_grad=True)
    b64 = torch.randn(7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(bias_relu, (x64, b64))
