"""Choosing actions from policy logits: the one sampler every episode loop uses (training, evaluation, traces,
the monitor), so that a seed means the same random stream everywhere.

Sampling is the Gumbel-max trick: ``argmax(logits + g)`` with ``g = -log(-log(u))`` and ``u`` uniform, which is
a draw from ``softmax(logits)``. One ``torch.rand`` call of the logits' shape per step, from the caller's
generator: changing this changes every seeded result.
"""

from __future__ import annotations

import torch

_TINY = 1e-20
"""``u`` is clamped to at least this, so that ``log(u)`` is finite (``torch.rand`` can return 0)."""


def _logprobs_of(logits: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return torch.log_softmax(logits, -1).gather(-1, actions.unsqueeze(-1)).squeeze(-1)


def sample_actions(logits: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """One draw from softmax(logits) per row; ``logits`` (B, A). Returns actions (B,) int64 and their
    log-probabilities (B,)."""
    u = torch.rand(logits.shape, device=logits.device, generator=generator).clamp_(min=_TINY)  # (B, A)
    actions = (logits - torch.log(-torch.log(u))).argmax(-1)  # (B,)
    return actions, _logprobs_of(logits, actions)


def greedy_actions(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The most likely action per row (the first on ties) and its log-probability: (B,) int64, (B,)."""
    actions = logits.argmax(-1)  # (B,)
    return actions, _logprobs_of(logits, actions)


def select_actions(
    logits: torch.Tensor, generator: torch.Generator, greedy: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`greedy_actions` if ``greedy`` (the generator is then left untouched), else :func:`sample_actions`."""
    return greedy_actions(logits) if greedy else sample_actions(logits, generator)
