"""The one action sampler: draws follow softmax(logits), greedy is argmax, log-probabilities are log_softmax at the
action, and the random stream is the one every seeded result depends on."""

from __future__ import annotations

import pytest
import torch
from scipy.stats import chi2

from seqtrojan.agent.sampling import greedy_actions, sample_actions, select_actions

PROBS = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.7, 0.1, 0.1, 0.1], [0.25, 0.25, 0.25, 0.25]])


def _counts(actions: torch.Tensor, num_actions: int) -> torch.Tensor:
    return torch.bincount(actions, minlength=num_actions).double()


def _chi_square(counts: torch.Tensor, probs: torch.Tensor) -> float:
    expected = probs.double() * counts.sum()
    return float(((counts - expected) ** 2 / expected).sum())


def test_draws_follow_the_softmax_of_each_row():
    """Pearson's chi-square over 60k draws per row (3 dof), against a 1e-6 tail: a sampler off by a few percent in
    any probability fails it, as the reversed distribution below shows."""
    rows, draws = PROBS.shape[0], 60_000
    logits = (PROBS.log() + 3.0).repeat(draws, 1)  # (draws * rows, A): each distribution in every block of rows
    generator = torch.Generator().manual_seed(1234)
    actions, _ = sample_actions(logits, generator)
    per_row = actions.view(draws, rows)
    critical = chi2.ppf(1 - 1e-6, df=PROBS.shape[1] - 1)
    for r in range(rows):
        counts = _counts(per_row[:, r], PROBS.shape[1])
        assert _chi_square(counts, PROBS[r]) < critical
    # the test has power: the first row's counts are far from the reversed distribution
    assert _chi_square(_counts(per_row[:, 0], 4), PROBS[0].flip(0)) > 100 * critical


def test_one_draw_per_step_over_many_steps_follows_the_softmax():
    """As the episode loops use it: one call per step on a small batch, the generator carrying over."""
    generator = torch.Generator().manual_seed(7)
    logits = PROBS[:1].log().repeat(8, 1)
    actions = torch.cat([sample_actions(logits, generator)[0] for _ in range(4000)])
    assert _chi_square(_counts(actions, 4), PROBS[0]) < chi2.ppf(1 - 1e-6, df=3)


def test_logprobs_are_the_log_softmax_at_the_action():
    logits = torch.randn(64, 5, generator=torch.Generator().manual_seed(0)) * 3
    for actions, logprobs in (sample_actions(logits, torch.Generator().manual_seed(1)), greedy_actions(logits)):
        assert actions.dtype == torch.int64 and actions.shape == (64,) and logprobs.shape == (64,)
        expected = torch.log_softmax(logits, -1)[torch.arange(64), actions]
        assert torch.equal(logprobs, expected)


def test_greedy_is_argmax_and_draws_nothing():
    logits = torch.tensor([[0.0, 2.0, 1.0], [5.0, 5.0, -1.0], [-3.0, -2.0, -1.0]])
    generator = torch.Generator().manual_seed(3)
    before = generator.get_state()
    actions, _ = select_actions(logits, generator, greedy=True)
    assert actions.tolist() == [1, 0, 2]  # ties: the first
    assert torch.equal(generator.get_state(), before)
    assert torch.equal(greedy_actions(logits)[0], actions)


def test_the_random_stream_is_one_uniform_per_logit_gumbel_max():
    """Every seeded result (training, evaluation, traces, the monitor) depends on this stream: one ``torch.rand``
    of the logits' shape per call, clamped, and ``argmax(logits - log(-log(u)))``."""
    logits = torch.randn(32, 4, generator=torch.Generator().manual_seed(5))
    ours, reference = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    for _ in range(20):
        actions, _ = select_actions(logits, ours, greedy=False)
        u = torch.rand(logits.shape, generator=reference).clamp_(min=1e-20)
        assert torch.equal(actions, (logits - torch.log(-torch.log(u))).argmax(-1))
    assert torch.equal(ours.get_state(), reference.get_state())


@pytest.mark.cuda
def test_sampling_on_cuda_uses_the_generator_on_the_logits_device():
    logits = PROBS.log().repeat(20_000, 1).cuda()
    actions, logprobs = sample_actions(logits, torch.Generator(device="cuda").manual_seed(0))
    assert actions.device.type == "cuda" and logprobs.device.type == "cuda"
    counts = _counts(actions.view(20_000, 3)[:, 0].cpu(), 4)
    assert _chi_square(counts, PROBS[0]) < chi2.ppf(1 - 1e-6, df=3)
