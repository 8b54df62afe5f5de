"""The recurrent actor-critic: state in and out, masks at episode starts, step == unroll, interventions."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState

needs_cpp = pytest.mark.skipif(
    fast_lstm.extension() is None, reason=f"C++ LSTM kernels unavailable: {fast_lstm.error()}"
)
BACKENDS = ["torch", pytest.param("cpp", marks=needs_cpp)]


def make(seed: int = 0, backend: str = "torch") -> RecurrentActorCritic:
    torch.manual_seed(seed)
    net = RecurrentActorCritic(54, 4, (64, 32)).double()
    net.set_lstm_backend(backend)
    return net


def random_state(batch: int) -> RecurrentState:
    return RecurrentState(
        tuple(LSTMState(torch.randn(batch, w).double(), torch.randn(batch, w).double()) for w in (64, 32))
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_stepping_t_times_equals_one_unroll_with_resets(backend):
    net = make(backend=backend)
    steps, batch = 12, 5
    obs = torch.randn(steps, batch, 54).double()
    starts = (torch.rand(steps, batch) < 0.2).double()
    state0 = random_state(batch)
    out = net.unroll(obs, state0, starts, return_states=True)
    state = state0
    for t in range(steps):
        with torch.no_grad():  # the no-grad step is the rollout path (fused kernel for cpp)
            step = net.step(obs[t], state, starts[t])
        state = step.state
        torch.testing.assert_close(step.logits, out.logits[t])
        torch.testing.assert_close(step.value, out.values[t])
        for layer, seq in zip(state.layers, out.states):
            torch.testing.assert_close(layer.h, seq.h[t])
            torch.testing.assert_close(layer.c, seq.c[t])
    for a, b in zip(state.layers, out.state.layers):
        torch.testing.assert_close(a.h, b.h)
        torch.testing.assert_close(a.c, b.c)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_of_fast_unroll_equal_stepwise_unroll(backend):
    net = make(backend=backend)
    obs = torch.randn(9, 4, 54).double()
    starts = (torch.rand(9, 4) < 0.3).double()
    state0 = random_state(4)
    grads = []
    for stepwise in (False, True):
        net.zero_grad()
        identity = (lambda layer, t, s: s) if stepwise else None
        out = net.unroll(obs, state0, starts, intervention=identity)
        (out.logits.logsumexp(-1).sum() + out.values.sum()).backward()
        grads.append([p.grad.clone() for p in net.parameters()])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)


def test_episode_start_resets_exactly_the_finished_envs():
    net = make()
    obs = torch.randn(3, 54).double()
    state = random_state(3)
    starts = torch.tensor([0.0, 1.0, 0.0]).double()
    out = net.step(obs, state, starts)
    fresh = net.step(obs[1:2], net.initial_state(1))
    torch.testing.assert_close(out.logits[1:2], fresh.logits)
    kept = net.step(obs[[0, 2]], state.index(torch.tensor([0, 2])))
    torch.testing.assert_close(out.logits[[0, 2]], kept.logits)


def test_state_is_never_kept_inside_the_module():
    net = make()
    obs = torch.randn(2, 54).double()
    state = random_state(2)
    a = net.step(obs, state)
    b = net.step(obs, state)
    torch.testing.assert_close(a.logits, b.logits)
    assert not any(isinstance(v, torch.Tensor) for v in vars(net).values())


def test_intervention_sees_every_layer_and_step_and_changes_the_output():
    net = make()
    obs = torch.randn(6, 3, 54).double()
    starts = torch.zeros(6, 3).double()
    t = torch.arange(6).repeat(3, 1).T
    calls = []

    def set_units(layer, t_now, s):
        calls.append((layer, int(t_now[0])))
        if layer == 1 and int(t_now[0]) >= 3:
            c = s.c.clone()
            c[:, :4] = 5.0
            return LSTMState(s.h, c)
        return s

    base = net.unroll(obs, net.initial_state(3), starts)
    edited = net.unroll(obs, net.initial_state(3), starts, intervention=set_units, t=t, return_states=True)
    assert calls == [(layer, step) for step in range(6) for layer in (0, 1)]
    torch.testing.assert_close(edited.logits[:3], base.logits[:3])
    assert not torch.allclose(edited.logits[4:], base.logits[4:])
    assert bool((edited.states[1].c[3:, :, :4] == 5.0).all())


@needs_cpp
def test_cpp_kernels_pass_gradcheck_against_all_inputs():
    torch.manual_seed(0)
    cell = torch.nn.LSTMCell(3, 4).double()
    x = torch.randn(6, 5, 3, dtype=torch.float64, requires_grad=True)
    keep = (torch.rand(6, 5) > 0.3).double()
    keep[0, 0] = 0
    h0 = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    c0 = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    weights = [p.detach().clone().requires_grad_() for p in cell.parameters()]

    def f(x, h0, c0, w_ih, w_hh, b_ih, b_hh):
        fake = torch.nn.Module()
        fake.weight_ih, fake.weight_hh, fake.bias_ih, fake.bias_hh = w_ih, w_hh, b_ih, b_hh
        return fast_lstm.unroll_layer(fake, x, keep, h0, c0, True)

    assert torch.autograd.gradcheck(f, (x, h0, c0, *weights), eps=1e-6, atol=1e-6, rtol=1e-5)


@needs_cpp
def test_cpp_and_torch_backends_agree_in_float32():
    torch.manual_seed(0)
    obs = torch.randn(32, 256, 54)
    starts = (torch.rand(32, 256) < 0.05).float()
    results = []
    for backend in ("torch", "cpp"):
        torch.manual_seed(1)
        net = RecurrentActorCritic(54, 4, (64, 32))
        net.set_lstm_backend(backend)
        out = net.unroll(obs, net.initial_state(256), starts)
        (out.logits.logsumexp(-1).sum() + out.values.sum()).backward()
        results.append((out.logits.detach(), [p.grad for p in net.parameters()]))
    torch.testing.assert_close(results[0][0], results[1][0], atol=2e-5, rtol=1e-4)
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b, atol=2e-3, rtol=2e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_unroll_with_states_is_freed_without_the_cyclic_gc(backend):
    """The states of a training unroll (state camouflage reads them) must die with their last reference: a
    reference cycle through the autograd context kept every update's buffers until 22 GB had piled up."""
    import gc
    import weakref

    net = make(backend=backend).float()
    obs, starts = torch.randn(8, 4, 54), torch.zeros(8, 4)
    gc.collect()
    gc.disable()
    try:
        out = net.unroll(obs, net.initial_state(4), starts, return_states=True)
        assert out.states is not None and out.states[0].c.requires_grad  # the path with an autograd graph
        c_seq = weakref.ref(out.states[0].c)
        (out.states[0].c.sum() + out.logits.sum()).backward()
        del out
        assert c_seq() is None
    finally:
        gc.enable()
