"""The fused C++ GRU and peephole LSTM kernels equal plain PyTorch loops: forward, gradients, steps, batch blocks.

The references step one cell at a time with the state multiplied by ``keep[t]`` before step t (episode starts):
torch.nn.GRUCell for the GRU, the peephole equations written out for the peephole LSTM.
"""

from __future__ import annotations

import gc
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest
import torch

from seqtrojan.agent import fast_lstm

pytestmark = pytest.mark.skipif(
    fast_lstm.extension() is None, reason=f"C++ LSTM kernels unavailable: {fast_lstm.error()}"
)

Tensors = tuple[torch.Tensor, ...]


class PeepholeCell(torch.nn.Module):
    """nn.LSTMCell's four tensors plus ``peephole`` (3, H) = rows (p_i, p_f, p_o)."""

    def __init__(self, n_in: int, hidden: int, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        base = torch.nn.LSTMCell(n_in, hidden, dtype=dtype)
        self.weight_ih, self.weight_hh = base.weight_ih, base.weight_hh
        self.bias_ih, self.bias_hh = base.bias_ih, base.bias_hh
        self.peephole = torch.nn.Parameter(torch.randn(3, hidden, dtype=dtype) * 0.5)

    def forward(self, x: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The reference step, written out from the equations."""
        z = x @ self.weight_ih.T + self.bias_ih + h @ self.weight_hh.T + self.bias_hh
        z_i, z_f, z_g, z_o = z.chunk(4, 1)
        p_i, p_f, p_o = self.peephole
        i = torch.sigmoid(z_i + p_i * c)
        f = torch.sigmoid(z_f + p_f * c)
        c = f * c + i * torch.tanh(z_g)
        o = torch.sigmoid(z_o + p_o * c)
        return o * torch.tanh(c), c


def make_gru(n_in: int, hidden: int, dtype: torch.dtype = torch.float32) -> torch.nn.GRUCell:
    return torch.nn.GRUCell(n_in, hidden, dtype=dtype)


def inputs(steps: int, batch: int, n_in: int, hidden: int, dtype: torch.dtype = torch.float32) -> Tensors:
    """x, keep (episode starts at t = 0 and inside the sequence), and nonzero initial states h0, c0."""
    x = torch.randn(steps, batch, n_in, dtype=dtype)
    keep = (torch.rand(steps, batch) > 0.25).to(dtype)
    keep[0, 0] = 0
    keep[steps // 2, batch - 1] = 0
    keep[1:, 1] = 1  # one env that never resets: gradients flow through the whole sequence
    return x, keep, torch.randn(batch, hidden, dtype=dtype), torch.randn(batch, hidden, dtype=dtype)


def gru_reference(cell: torch.nn.GRUCell, x: torch.Tensor, keep: torch.Tensor, h0: torch.Tensor) -> torch.Tensor:
    h, out = h0, []
    for t in range(x.shape[0]):
        h = cell(x[t], h * keep[t, :, None])
        out.append(h)
    return torch.stack(out)


def peephole_reference(cell: PeepholeCell, x: torch.Tensor, keep: torch.Tensor, h0: torch.Tensor, c0: torch.Tensor):
    h, c, hs, cs = h0, c0, [], []
    for t in range(x.shape[0]):
        h, c = cell(x[t], h * keep[t, :, None], c * keep[t, :, None])
        hs.append(h)
        cs.append(c)
    return torch.stack(hs), torch.stack(cs)


def weights(cell: torch.nn.Module) -> Tensors:
    return tuple(p for p in cell.parameters())


def grads_of(loss: torch.Tensor, tensors: Tensors) -> Tensors:
    return torch.autograd.grad(loss, [t for t in tensors if t.requires_grad])


def assert_all_close(a: Tensors, b: Tensors, tol: float) -> None:
    assert len(a) == len(b)
    for u, v in zip(a, b):
        torch.testing.assert_close(u, v, atol=tol, rtol=tol)


@contextmanager
def threads(n: int) -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ---------------------------------------------------------------------------------------------- GRU
def check_gru(steps: int, batch: int, n_in: int, hidden: int, x_grad: bool, dtype=torch.float32) -> None:
    torch.manual_seed(0)
    cell = make_gru(n_in, hidden, dtype)
    x, keep, h0, _ = inputs(steps, batch, n_in, hidden, dtype)
    x.requires_grad_(x_grad)
    h0.requires_grad_()
    probe = torch.randn(steps, batch, hidden, dtype=dtype)  # a loss that weighs every output differently
    fast = fast_lstm.unroll_gru_layer(cell, x, keep, h0, True)
    ref = gru_reference(cell, x, keep, h0)
    torch.testing.assert_close(fast, ref, atol=1e-5, rtol=1e-5)
    leaves = (x, h0, *weights(cell))
    assert_all_close(grads_of((fast * probe).sum(), leaves), grads_of((ref * probe).sum(), leaves), 1e-4)


@pytest.mark.parametrize("x_grad", [True, False])
def test_gru_forward_and_gradients_equal_grucell_loop(x_grad):
    check_gru(steps=9, batch=5, n_in=6, hidden=8, x_grad=x_grad)


def test_gru_in_several_batch_blocks_equals_grucell_loop():
    with threads(2):
        assert fast_lstm.num_chunks(96) > 1  # the batch is really split
        check_gru(steps=6, batch=96, n_in=7, hidden=16, x_grad=True)


def test_gru_passes_gradcheck_in_float64():
    torch.manual_seed(1)
    x, keep, h0, _ = inputs(4, 3, 5, 4, torch.float64)
    params = [p.detach().clone().requires_grad_() for p in weights(make_gru(5, 4, torch.float64))]

    def f(x, h0, w_ih, w_hh, b_ih, b_hh):
        cell = torch.nn.Module()
        cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh = w_ih, w_hh, b_ih, b_hh
        return fast_lstm.unroll_gru_layer(cell, x, keep, h0, False)

    args = (x.requires_grad_(), h0.requires_grad_(), *params)
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gru_step_equals_one_grucell_step(dtype):
    torch.manual_seed(2)
    cell = make_gru(6, 8, dtype)
    x, h = torch.randn(5, 6, dtype=dtype), torch.randn(5, 8, dtype=dtype)
    keep = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0], dtype=dtype)
    with torch.no_grad():
        expected = cell(x, h * keep[:, None])
    torch.testing.assert_close(fast_lstm.step_gru_layer(cell, x, keep, h), expected)


# ---------------------------------------------------------------------------------------------- peephole LSTM
def check_peephole(steps: int, batch: int, n_in: int, hidden: int, x_grad: bool, return_c_seq: bool) -> None:
    torch.manual_seed(0)
    cell = PeepholeCell(n_in, hidden)
    x, keep, h0, c0 = inputs(steps, batch, n_in, hidden)
    x.requires_grad_(x_grad)
    h0.requires_grad_()
    c0.requires_grad_()
    probe_h, probe_c = torch.randn(2, steps, batch, hidden)
    fast_h, fast_c = fast_lstm.unroll_peephole_layer(cell, x, keep, h0, c0, return_c_seq)
    ref_h, ref_c = peephole_reference(cell, x, keep, h0, c0)
    if not return_c_seq:
        ref_c, probe_c = ref_c[-1], probe_c[-1]
    torch.testing.assert_close(fast_h, ref_h, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fast_c, ref_c, atol=1e-5, rtol=1e-5)
    leaves = (x, h0, c0, *weights(cell))
    fast_grads = grads_of((fast_h * probe_h).sum() + (fast_c * probe_c).sum(), leaves)
    ref_grads = grads_of((ref_h * probe_h).sum() + (ref_c * probe_c).sum(), leaves)
    assert_all_close(fast_grads, ref_grads, 1e-4)


@pytest.mark.parametrize("return_c_seq", [True, False])
@pytest.mark.parametrize("x_grad", [True, False])
def test_peephole_forward_and_gradients_equal_reference_loop(x_grad, return_c_seq):
    check_peephole(steps=9, batch=5, n_in=6, hidden=8, x_grad=x_grad, return_c_seq=return_c_seq)


def test_peephole_in_several_batch_blocks_equals_reference_loop():
    with threads(2):
        assert fast_lstm.num_chunks(96) > 1
        check_peephole(steps=6, batch=96, n_in=7, hidden=16, x_grad=True, return_c_seq=True)


@pytest.mark.parametrize("return_c_seq", [True, False])
def test_peephole_passes_gradcheck_in_float64(return_c_seq):
    torch.manual_seed(1)
    x, keep, h0, c0 = inputs(4, 3, 5, 4, torch.float64)
    params = [p.detach().clone().requires_grad_() for p in weights(PeepholeCell(5, 4, torch.float64))]

    def f(x, h0, c0, w_ih, w_hh, b_ih, b_hh, peephole):
        cell = torch.nn.Module()
        cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh = w_ih, w_hh, b_ih, b_hh
        cell.peephole = peephole
        return fast_lstm.unroll_peephole_layer(cell, x, keep, h0, c0, return_c_seq)

    args = (x.requires_grad_(), h0.requires_grad_(), c0.requires_grad_(), *params)
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_peephole_step_equals_one_reference_step(dtype):
    torch.manual_seed(2)
    cell = PeepholeCell(6, 8, dtype)
    x, h, c = torch.randn(5, 6, dtype=dtype), torch.randn(5, 8, dtype=dtype), torch.randn(5, 8, dtype=dtype)
    keep = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0], dtype=dtype)
    with torch.no_grad():
        expected = cell(x, h * keep[:, None], c * keep[:, None])
    assert_all_close(fast_lstm.step_peephole_layer(cell, x, keep, h, c), expected, 1e-6)


def test_peephole_with_zero_peepholes_equals_the_plain_lstm_kernel():
    torch.manual_seed(3)
    cell = PeepholeCell(6, 8)
    with torch.no_grad():
        cell.peephole.zero_()
    x, keep, h0, c0 = inputs(7, 5, 6, 8)
    x.requires_grad_()
    probe = torch.randn(7, 5, 8)
    peep_h, peep_c = fast_lstm.unroll_peephole_layer(cell, x, keep, h0, c0, True)
    plain_h, plain_c = fast_lstm.unroll_layer(cell, x, keep, h0, c0, True)
    torch.testing.assert_close(peep_h, plain_h, atol=0, rtol=0)
    torch.testing.assert_close(peep_c, plain_c, atol=0, rtol=0)
    leaves = (x, *weights(cell)[:4])
    peep_grads = grads_of((peep_h * probe).sum() + peep_c.sum(), leaves)
    assert_all_close(peep_grads, grads_of((plain_h * probe).sum() + plain_c.sum(), leaves), 1e-6)
    with torch.no_grad():
        stepped = fast_lstm.step_peephole_layer(cell, x[0], keep[0], h0, c0)
        (plain,) = fast_lstm.step_stack([cell], x[0], keep[0], [(h0, c0)], {})
    assert_all_close(stepped, plain, 0)


# ---------------------------------------------------------------------------------------------- both cells
CELLS: dict[str, tuple[Callable[[], torch.nn.Module], Callable, Callable]] = {
    "gru": (
        lambda: make_gru(6, 8),
        lambda cell, x, keep, h, c: fast_lstm.unroll_gru_layer(cell, x, keep, h, True),
        lambda cell, x, keep, h, c: (fast_lstm.step_gru_layer(cell, x, keep, h), c),
    ),
    "lstm_peephole": (
        lambda: PeepholeCell(6, 8),
        lambda cell, x, keep, h, c: fast_lstm.unroll_peephole_layer(cell, x, keep, h, c, True)[0],
        lambda cell, x, keep, h, c: fast_lstm.step_peephole_layer(cell, x, keep, h, c),
    ),
}


@pytest.mark.parametrize("name", CELLS)
def test_stepping_equals_the_unroll_and_follows_weight_updates(name):
    torch.manual_seed(4)
    make, unroll, step = CELLS[name]
    cell = make()
    x, keep, h0, c0 = inputs(6, 5, 6, 8)
    for _ in range(2):  # the cached GEMM matrix follows an in-place (optimizer-like) update
        with torch.no_grad():
            expected = unroll(cell, x, keep, h0, c0)
        h, c = h0, c0
        for t in range(x.shape[0]):
            h, c = step(cell, x[t], keep[t], h, c)
            torch.testing.assert_close(h, expected[t], atol=1e-6, rtol=1e-5)
        with torch.no_grad():
            for p in cell.parameters():
                p.add_(0.3 * torch.randn_like(p))


@pytest.mark.parametrize("name", CELLS)
def test_an_unroll_is_freed_without_the_cyclic_gc(name):
    """As the LSTM's: outputs never sit on the autograd context, where they would form a reference cycle."""
    make, unroll, _ = CELLS[name]
    cell = make()
    x, keep, h0, c0 = inputs(5, 4, 6, 8)
    gc.collect()
    gc.disable()
    try:
        h_seq = unroll(cell, x, keep, h0, c0)
        assert h_seq.requires_grad
        ref = weakref.ref(h_seq)
        h_seq.sum().backward()
        del h_seq
        assert ref() is None
    finally:
        gc.enable()


def test_the_build_key_covers_every_kernel_source():
    """A change to any file in csrc must rebuild the extension (its bytes are part of the cache folder's key)."""
    hashed = {p.name for p in fast_lstm._SOURCES + fast_lstm._HEADERS}
    assert hashed == {p.name for p in fast_lstm._CSRC.iterdir() if p.suffix in (".cpp", ".h")}
