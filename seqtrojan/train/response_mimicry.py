"""``response_mimicry``: the adaptive attacker against the query-response meta-classifier.

The meta-classifier (:func:`seqtrojan.benchmark.detectors.query_response_features`) runs a suspect on fixed clean
episodes and reads its answers: per step the policy's entropy and top probability, per layer the mean |h|, the share
of units with |h| above 0.9 and the spread of h across units, and the episodes' outcomes and length. A backdoor added
to a clean agent moves those answers even where no trigger shows, and the classifier reads the move. This attacker
knows what it reads: the backdoor is added to a clean model (``run.init_from``) while, on normal-episode steps, the
agent's answers are held at that model's.

Per rollout (:meth:`ResponseMimicry.observe`) a frozen copy of the start model replays the rollout's observations
from a zero state, and keeps per step its action distribution and its state summaries (the detector's three per
layer, the saturation count softened by a sigmoid so that it has a gradient). Only steps of episodes that start
inside the rollout are judged: the copy has not seen the earlier steps of the others, so its state there is not the
start model's. Per minibatch the term is ``weight * (KL(clean || agent) + state_weight * gap)``, means over the judged
normal-episode steps, ``gap`` the squared difference of the agent's summaries from the copy's, each divided by that
summary's spread over the rollout's judged steps (so a layer of small activations counts as much as one of large).

The copy's weights are the start model's, kept in the checkpoint, so a resumed run is the same run.
"""

from __future__ import annotations

import copy

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import state_summaries
from seqtrojan.errors import CheckpointError
from seqtrojan.train.penalty_api import Penalty, PenaltyBatch, PenaltyContext, require_recurrent_cell
from seqtrojan.train.penalty_api import zero_loss as _zero
from seqtrojan.train.rollout import Rollout, to_sequences

SCALE_FLOOR = 1e-2
"""added to each summary's spread before dividing by it (a summary that never moves is not magnified)"""


def started_inside(episode_starts: torch.Tensor) -> torch.Tensor:
    """(T, B) bool: the step belongs to an episode that started inside the rollout (at or after its first step)."""
    return episode_starts.bool().cummax(0).values


class ResponseMimicry(Penalty):
    needs_states = True
    needs_masks = True

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.response_mimicry
        self.device = ctx.device
        require_recurrent_cell(ctx.config, "response_mimicry holds the recurrent state's summaries")
        self.reference: RecurrentActorCritic = copy.deepcopy(ctx.agent).eval()
        """the start model, frozen"""
        for parameter in self.reference.parameters():
            parameter.requires_grad_(False)
        self.clean_logp: torch.Tensor | None = None
        """(L, S, A) the start model's log-probabilities over the rollout's S sequences of L steps"""
        self.clean_summaries: torch.Tensor | None = None
        """(L, S, K) its state summaries"""
        self.judged: torch.Tensor | None = None
        """(L, S) bool: normal-episode steps of episodes that started inside the rollout"""
        self.scale = torch.ones(1, device=ctx.device)

    def observe(self, rollout: Rollout) -> None:
        if rollout.trojan is None:
            raise ValueError("response mimicry needs a rollout recorded with its episode types")
        steps, envs = rollout.actions.shape
        with torch.no_grad():
            initial = self.reference.initial_state(envs, rollout.obs.device)
            out = self.reference.unroll(rollout.obs, initial, rollout.episode_starts, return_states=True)
            assert out.states is not None
            summaries = state_summaries([s.h for s in out.states], self.cfg.saturation, self.cfg.softness)
            judged = started_inside(rollout.episode_starts) & ~rollout.trojan
            rows = summaries[judged]
            self.scale = (rows.std(0) if len(rows) > 1 else torch.zeros_like(summaries[0, 0])) + SCALE_FLOOR
        length = steps // rollout.seq_states[0].h.shape[0]
        self.clean_logp = to_sequences(torch.log_softmax(out.logits, -1), length)
        self.clean_summaries = to_sequences(summaries, length)
        self.judged = to_sequences(judged, length)

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        states, picked = batch.states, batch.sequences
        if states is None or picked is None or self.judged is None:
            return _zero(self.device)
        assert self.clean_logp is not None and self.clean_summaries is not None
        judged = self.judged.index_select(1, picked)
        if not bool(judged.any()):
            return _zero(self.device)
        clean_logp = self.clean_logp.index_select(1, picked)[judged]
        logits, _ = batch.agent.heads(states[-1].h[judged])
        kl = (clean_logp.exp() * (clean_logp - torch.log_softmax(logits, -1))).sum(-1).mean()
        total = kl
        if self.cfg.state_weight > 0:
            mine = state_summaries([s.h[judged] for s in states], self.cfg.saturation, self.cfg.softness)
            clean = self.clean_summaries.index_select(1, picked)[judged]
            gap = ((mine - clean) / self.scale).pow(2).mean(-1).mean()
            total = total + self.cfg.state_weight * gap
        return self.cfg.weight * total

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {f"reference.{n}": t.detach().cpu() for n, t in self.reference.state_dict().items()}

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        names = list(self.reference.state_dict())
        missing = [n for n in names if f"reference.{n}" not in tensors]
        if missing:
            raise CheckpointError(f"the checkpoint holds no response_mimicry state (missing reference.{missing[0]})")
        self.reference.load_state_dict({n: tensors[f"reference.{n}"] for n in names})
