"""The first layer's product with a one-hot observation, read from its nonzero entries only
(:func:`seqtrojan.agent.fast_lstm.sparse_project`), equals the dense product: the projection and its weight gradient
alone, and a whole LSTM / peephole LSTM layer unrolled with it against the same layer on the dense kernel."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.network import RecurrentActorCritic

pytestmark = pytest.mark.skipif(
    fast_lstm.extension() is None, reason=f"C++ LSTM kernels unavailable: {fast_lstm.error()}"
)


def one_hot_view(rows: int, cells: int = 25, values: int = 20, ones: int = 3, seed: int = 0) -> torch.Tensor:
    """Rows like MiniGrid's one-hot view: ``cells`` groups of ``values`` numbers, ``ones`` of them set per group
    (some to other values than 1, to check the values are used), and a few all-zero rows."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.zeros(rows, cells * values, dtype=torch.float64)
    for _ in range(ones):
        index = torch.randint(0, values, (rows, cells), generator=generator) + torch.arange(cells) * values
        x.scatter_(1, index, 1.0)
    x[::7, 3] = 2.5
    x[1] = 0.0
    return x


@pytest.mark.parametrize("width", [256, 96, 7])  # whole 64-blocks, a partial last block, a single short block
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_projection_and_its_weight_gradient_equal_the_dense_products(width, dtype):
    x = one_hot_view(97).to(dtype)
    w = torch.randn(width, x.shape[1], dtype=dtype, requires_grad=True)
    out = fast_lstm.sparse_project(x, w)
    d_out = torch.randn_like(out)
    (out * d_out).sum().backward()
    tolerance = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(out, x @ w.detach().T, atol=tolerance, rtol=tolerance)
    assert w.grad is not None
    torch.testing.assert_close(w.grad, d_out.T @ x, atol=tolerance, rtol=tolerance)


def test_the_projection_passes_gradcheck():
    x = one_hot_view(9, cells=4, values=10)
    w = torch.randn(5, x.shape[1], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda weight: fast_lstm.sparse_project(x, weight), (w,))


def test_only_wide_mostly_zero_inputs_without_gradient_take_the_sparse_product():
    view = one_hot_view(8).float()  # 500 inputs, 0.15 of them nonzero (fewer on the all-zero row)
    assert fast_lstm.is_sparse_input(view)
    assert not fast_lstm.is_sparse_input(torch.ones_like(view))  # dense
    assert not fast_lstm.is_sparse_input(view.requires_grad_())  # an encoder's output: its gradient is needed
    narrow = torch.zeros(8, 54)
    narrow[:, 0] = 1.0
    assert not fast_lstm.is_sparse_input(narrow)  # the grid world's observation: one GEMM is cheaper


@pytest.mark.parametrize("cell", ["lstm", "lstm_peephole", "gru"])
def test_a_layer_on_a_one_hot_view_equals_the_dense_kernel_forward_and_backward(cell, monkeypatch):
    """The network's unroll (what PPO trains) with the sparse projection against the same network forced onto the
    dense kernel: outputs, final state and every parameter's gradient."""
    torch.manual_seed(0)
    steps, batch = 6, 20
    net = RecurrentActorCritic(500, 7, (16, 8), cell=cell).double()
    obs = one_hot_view(steps * batch).view(steps, batch, 500)
    starts = torch.zeros(steps, batch, dtype=torch.bool)
    starts[0] = True
    starts[3, ::4] = True
    state = net.initial_state(batch)
    state = type(state)(tuple(type(s)(torch.randn_like(s.h), torch.randn_like(s.c)) for s in state.layers))
    results = []
    for sparse in (True, False):
        monkeypatch.setattr(fast_lstm, "SPARSE_MIN_INPUTS", 128 if sparse else 10**9)
        net.zero_grad()
        out = net.unroll(obs, state, starts)
        (out.logits.square().sum() + out.values.sum() + out.state.layers[0].c.sum()).backward()
        grads = [p.grad.clone() for p in net.parameters() if p.grad is not None]
        results.append((out.logits.detach(), out.values.detach(), out.state.layers[0].c.detach(), grads))
    (logits, values, c, grads), (logits_ref, values_ref, c_ref, grads_ref) = results  # c: the GRU's is empty
    torch.testing.assert_close(logits, logits_ref)
    torch.testing.assert_close(values, values_ref)
    torch.testing.assert_close(c, c_ref)
    assert len(grads) == len(grads_ref) == len(list(net.parameters()))
    for grad, grad_ref in zip(grads, grads_ref):
        torch.testing.assert_close(grad, grad_ref)


@pytest.mark.parametrize("cell", ["lstm", "lstm_peephole", "gru"])
def test_the_sparse_path_is_taken_on_a_one_hot_view(cell, monkeypatch):
    """The network really uses the sparse projection for such an input (so the tests above test what trains)."""
    calls = []
    original = fast_lstm.sparse_project
    monkeypatch.setattr(fast_lstm, "sparse_project", lambda x, w: calls.append(x.shape) or original(x, w))
    net = RecurrentActorCritic(500, 7, (16, 8), cell=cell)
    obs = one_hot_view(4 * 3).float().view(4, 3, 500)
    net.unroll(obs, net.initial_state(3), torch.zeros(4, 3, dtype=torch.bool))
    assert calls == [torch.Size([12, 500])]


@pytest.mark.parametrize("cell", ["lstm", "gru"])
def test_a_rollout_step_on_a_one_hot_view_equals_the_dense_step_and_follows_weight_updates(cell, monkeypatch):
    """The policy's no-grad step (what collects the rollouts) with the projected first layer: the same (h, c) and
    outputs as the dense kernel step, also after the weights change (the cached matrices are rebuilt)."""
    torch.manual_seed(1)
    net = RecurrentActorCritic(500, 7, (16, 8), cell=cell)
    obs = one_hot_view(12).float()
    state = net.initial_state(12)
    keep = torch.ones(12, dtype=torch.bool)
    for _ in range(2):
        outputs = []
        for sparse in (True, False):
            monkeypatch.setattr(fast_lstm, "SPARSE_MIN_INPUTS", 128 if sparse else 10**9)
            with torch.no_grad():
                outputs.append(net.step(obs, state, ~keep))
        (ours, theirs) = outputs
        torch.testing.assert_close(ours.logits, theirs.logits)
        for mine, ref in zip(ours.state.layers, theirs.state.layers):
            torch.testing.assert_close(mine.h, ref.h)
            torch.testing.assert_close(mine.c, ref.c)
        state = ours.state
        with torch.no_grad():
            net.cells[0].weight_ih.add_(0.5)  # an optimizer step: the next step must read the new weights
