"""A trained agent as a batched policy: keeps its recurrent state between calls."""

from __future__ import annotations

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import Intervention


class AgentPolicy:
    """``policy(obs) -> actions`` for one episode per env (see :func:`seqtrojan.env.rollout.run_episodes`).

    ``greedy`` takes the most likely action instead of sampling. An ``intervention`` edits the LSTM state at
    every step (the per-env episode step comes from ``step_counter``, e.g. the env core's ``t``).
    """

    def __init__(
        self,
        agent: RecurrentActorCritic,
        greedy: bool = False,
        seed: int = 0,
        intervention: Intervention | None = None,
        step_counter=None,
        initial_state=None,
    ) -> None:
        self.agent = agent
        self.greedy = greedy
        self.intervention = intervention
        self.step_counter = step_counter
        device = next(agent.parameters()).device
        self.generator = torch.Generator(device=device).manual_seed(seed)
        self.state = None
        self.initial_state = initial_state
        """a RecurrentState to start episodes from instead of zeros (e.g. after an adversarial prefix)"""

    def reset(self, num_envs: int) -> None:
        self.state = (
            self.initial_state.clone() if self.initial_state is not None else self.agent.initial_state(num_envs)
        )

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if self.state is None:
            self.reset(obs.shape[0])
        t = self.step_counter() if self.step_counter is not None else None
        out = self.agent.step(obs, self.state, t=t, intervention=self.intervention)
        self.state = out.state
        if self.greedy:
            return out.logits.argmax(-1)
        u = torch.rand(out.logits.shape, device=obs.device, generator=self.generator).clamp_(min=1e-20)
        return (out.logits - torch.log(-torch.log(u))).argmax(-1)
