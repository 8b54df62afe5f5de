"""How in-distribution a trigger is: how often its pattern appears on its own in normal episodes.

A trigger drawn with ordinary codes (holes, empty cells, walls: ``env.trigger.values`` or ``env.trigger.sequence``)
can show up in the agent's view without any adversary. :func:`natural_occurrence` runs normal-env episodes (no
trigger is ever drawn) with an agent or a uniformly random policy and counts where the view shows the ON trigger's
pattern on the pattern's cells (other cells free): for a sequence, all of its frames in order on consecutive steps
of one episode, counted at the step of the last frame (when a shown sequence takes effect); for a patch, the patch
once (it takes effect at its first step, whatever its ``duration``). The dedicated ``trigger`` code never occurs.

Counted are the observations an action was chosen on (``o_0`` .. ``o_{length-1}`` of each episode), read with
:meth:`~seqtrojan.env.core.TrojanGridCore.observe_codes`. Whether such an occurrence switches the agent's goal is
measured by :mod:`seqtrojan.analysis.unintentional` (activation rate in the normal env).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, Policy, run_episodes
from seqtrojan.env.scripted import RandomAgent
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate


@dataclass(frozen=True)
class OccurrenceResult:
    """Natural occurrences of one trigger pattern in normal episodes on one grid."""

    grid: str
    """the grid's label, e.g. 7x7/3"""
    policy: str
    """'agent' (the given network, sampled or greedy) or 'random' (uniformly random actions)"""
    frames: int
    """frames matched in order on consecutive steps (a sequence's length; 1 for a patch)"""
    episodes_with_pattern: Rate
    """episodes in which the pattern appeared at least once, of all episodes"""
    steps_with_pattern: Rate
    """steps whose observation completed the pattern (a sequence: showed its last frame after the others), of all
    steps taken (the sum of episode lengths)"""


class _OccurrenceRecorder:
    """Follows each env's progress through the pattern's frames, one observation per step."""

    def __init__(self, core: TrojanGridCore) -> None:
        self.core = core
        b, frames = core.num_envs, core.config.trigger.frame_count
        self.codes = core.observe_codes()  # (B, v*v): o_t, the observation the next action is chosen on
        self.chain = torch.zeros(b, frames, dtype=torch.bool, device=core.device)  # frames 0..k just seen in order
        self.hits = torch.zeros(b, dtype=torch.int64, device=core.device)  # completed patterns per episode
        self.steps = torch.zeros(b, dtype=torch.int64, device=core.device)  # steps taken per episode

    def on_step(self, step: EpisodeStep) -> None:
        running = step.running.to(self.core.device)
        match = self.core.match_on_frames(self.codes)  # (B, F)
        before = torch.cat((torch.ones_like(self.chain[:, :1]), self.chain[:, :-1]), 1)  # frame k-1 seen last step
        self.chain = match & before & running[:, None]
        self.hits += self.chain[:, -1]
        self.steps += running
        self.codes = self.core.observe_codes()  # o_{t+1}; a finished env's is never counted

    def on_end(self, batch: EpisodeBatch) -> None:
        pass


@torch.no_grad()
def natural_occurrence(
    agent: RecurrentActorCritic | None,
    env: EnvConfig,
    grid: GridSpec,
    *,
    episodes: int = 1000,
    seed: int = 0,
    greedy: bool = False,
    device: str | torch.device = "cpu",
) -> OccurrenceResult:
    """Run ``episodes`` normal-env episodes of ``env`` on ``grid`` (one per env slot, seeded ``seed``) with
    ``agent`` (actions sampled with a generator seeded ``seed``, or ``greedy``) or, with ``agent=None``, uniformly
    random actions; count the episodes and steps in which ``env``'s ON trigger pattern appears naturally."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be a positive integer, got {episodes!r}")
    env_cfg = env.with_grid(grid)
    core = TrojanGridCore(env_cfg, episodes, seed=seed, device=device, trojan_probability=0.0, phase="eval")
    policy: Policy
    if agent is None:
        policy = RandomAgent(core, seed).act
    else:
        if agent.obs_dim != core.obs_dim or agent.num_actions != core.num_actions:
            raise ConfigError(
                f"the agent takes {agent.obs_dim} inputs and {agent.num_actions} actions; this env gives "
                f"{core.obs_dim} and {core.num_actions}"
            )
        policy = AgentPolicy(agent, greedy=greedy, seed=seed, step_counter=lambda: core.t)
    recorder = _OccurrenceRecorder(core)
    run_episodes(core, policy, fresh=False, recorders=[recorder])
    hits, steps = recorder.hits.cpu(), recorder.steps.cpu()
    return OccurrenceResult(
        grid=grid.label,
        policy="random" if agent is None else "agent",
        frames=int(recorder.chain.shape[1]),
        episodes_with_pattern=Rate(int((hits > 0).sum()), episodes),
        steps_with_pattern=Rate(int(hits.sum()), int(steps.sum())),
    )
