"""A trained agent as a batched policy: keeps its recurrent state between calls.

:func:`act` is the per-step policy call every loop shares (the episode loop through :class:`AgentPolicy`, and
training's rollout collector): one network step, then the action from :mod:`seqtrojan.agent.sampling`.
"""

from __future__ import annotations

import torch

from seqtrojan.agent.network import RecurrentActorCritic, StepOutput
from seqtrojan.agent.sampling import select_actions
from seqtrojan.agent.state import Intervention, RecurrentState


def act(
    agent: RecurrentActorCritic,
    obs: torch.Tensor,
    state: RecurrentState,
    generator: torch.Generator,
    *,
    greedy: bool = False,
    episode_start: torch.Tensor | None = None,
    t: torch.Tensor | None = None,
    intervention: Intervention | None = None,
) -> tuple[StepOutput, torch.Tensor, torch.Tensor]:
    """One step of ``agent`` on ``obs`` (B, obs_dim) from ``state`` and the action it takes: returns the step's
    output (logits, value, new state), the actions (B,) int64 and their log-probabilities (B,). ``greedy`` takes
    the most likely action; otherwise one draw from ``generator`` (:func:`seqtrojan.agent.sampling.sample_actions`).
    ``episode_start``, ``t`` and ``intervention`` go to :meth:`RecurrentActorCritic.step`."""
    out = agent.step(obs, state, episode_start, t=t, intervention=intervention)
    actions, logprobs = select_actions(out.logits, generator, greedy)
    return out, actions, logprobs


class AgentPolicy:
    """``policy(obs) -> actions`` for one episode per env (see :func:`seqtrojan.env.rollout.run_episodes`).

    ``greedy`` takes the most likely action instead of sampling. An ``intervention`` edits the LSTM state at
    every step (the per-env episode step comes from ``step_counter``, e.g. the env core's ``t``). After a call,
    ``output`` holds the network's step output (what recorders of the episode loop read) and ``state`` the state
    the next call starts from (:meth:`next_state` of the output's state).
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
        self.state: RecurrentState | None = None
        self.output: StepOutput | None = None
        self.initial_state = initial_state
        """a RecurrentState to start episodes from instead of zeros (e.g. after an adversarial prefix)"""

    def reset(self, num_envs: int) -> None:
        self.state = (
            self.initial_state.clone() if self.initial_state is not None else self.agent.initial_state(num_envs)
        )

    def next_state(self, state: RecurrentState) -> RecurrentState:
        """The state the next step starts from, given this step's; the identity here (the monitor resets in it)."""
        return state

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if self.state is None:
            self.reset(obs.shape[0])
        assert self.state is not None  # reset() sets it
        t = self.step_counter() if self.step_counter is not None else None
        self.output, actions, _ = act(
            self.agent, obs, self.state, self.generator, greedy=self.greedy, t=t, intervention=self.intervention
        )
        self.state = self.next_state(self.output.state)
        return actions
