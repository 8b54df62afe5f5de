"""The episode loop: run exactly one episode per env slot and collect outcomes (no autoreset, so no bias toward
short episodes). Evaluation, traces, replays, searches and the online monitor all run episodes through
:func:`run_episodes`; whatever they record per step, they record through an :class:`EpisodeRecorder`.

Training does not: its collector runs a fixed number of steps with autoreset and keeps sequence start states
(:mod:`seqtrojan.train.rollout`); it shares the per-step policy call and the action sampler instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import torch

from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.core import StepResult, TrojanGridCore
from seqtrojan.stats import wilson_interval

if TYPE_CHECKING:
    from seqtrojan.agent.state import RecurrentState

Policy = Callable[[torch.Tensor], torch.Tensor]
"""``policy(obs) -> actions``: obs (B, obs_dim) float32 -> (B,) int64. Optional members the loop uses: ``reset
(num_envs)``, called before the first step; ``output``, the network's last step output (logits, value, state,
e.g. :class:`seqtrojan.agent.policy.AgentPolicy`), handed to recorders."""


@dataclass(frozen=True)
class EpisodeBatch:
    """Outcomes of one episode per env: all tensors (B,)."""

    outcome: torch.Tensor  # int64 outcome code
    success: torch.Tensor  # bool
    length: torch.Tensor  # int64
    trojan: torch.Tensor  # bool
    returns: torch.Tensor | None = None
    """float32: each episode's summed reward (the objective in force: the env's own, or the adversary's after the
    trigger); None where the batch was built without them"""

    def rate(self, name: str) -> float:
        return float((self.outcome == OUTCOME_NAMES.index(name)).float().mean())

    @property
    def success_rate(self) -> float:
        return float(self.success.float().mean())

    def success_interval(self, confidence: float = 0.95) -> tuple[float, float]:
        return wilson_interval(int(self.success.sum()), int(self.success.numel()), confidence)


class EpisodeStep(NamedTuple):
    """One step of the loop, for every env (B of them), as an :class:`EpisodeRecorder` sees it."""

    t: int
    """loop step: the number of actions each env had taken before this one (for episodes that start together)"""
    obs: torch.Tensor  # (B, obs_dim) float32: the observation the action was chosen on
    cells: torch.Tensor  # (B, 2) int64: the agent's (row, col) on its grid before the action
    action: torch.Tensor  # (B,) int64
    result: StepResult  # the env's step (no autoreset: a finished env stays finished)
    running: torch.Tensor  # (B,) bool: the env's episode had not ended before this step
    state: RecurrentState | None  # the policy's state after its update at this step (the state that chose the action)
    logits: torch.Tensor | None  # (B, A) the policy's logits at this step; None for a policy without ``output``


class EpisodeEnv(Protocol):
    """What :func:`run_episodes` steps: a batched env that can run without autoreset and says, per env, its
    episode's type, step and (where it has one) the agent's cell -- the grid core, or a Gymnasium env behind the
    seam (:class:`seqtrojan.world.gymnasium.GymnasiumBatchedEnv`)."""

    num_envs: int
    device: torch.device
    config: Any
    """the env section the slots run (the grid world's :class:`~seqtrojan.env.config.EnvConfig`, or a Gymnasium
    env's)"""

    @property
    def episode_limit(self) -> int: ...

    @property
    def trojan(self) -> torch.Tensor:
        """(B,) bool: each slot's episode is a trojan one"""
        ...

    @property
    def t(self) -> torch.Tensor:
        """(B,) int64: actions taken in each slot's episode"""
        ...

    @property
    def on_step(self) -> torch.Tensor:
        """(B,) int64: each slot's trigger step (-1: none)"""
        ...

    def reset(self, seed: int | Sequence[int] | None = None) -> torch.Tensor: ...

    def observe(self) -> torch.Tensor: ...

    def step(self, actions: torch.Tensor, autoreset: bool = True, check: bool = True) -> StepResult: ...

    def agent_cells(self) -> torch.Tensor:
        """(B, 2) int64 the agent's (row, col), or zeros where the env has no grid of cells."""
        ...


class EpisodeRecorder(Protocol):
    """Hooks of :func:`run_episodes`: ``on_step`` after every env step, ``on_end`` once with the outcomes."""

    def on_step(self, step: EpisodeStep) -> None: ...

    def on_end(self, batch: EpisodeBatch) -> None: ...


def agent_cells(core: TrojanGridCore) -> torch.Tensor:
    """(B, 2) int64: every env's agent position as (row, col) on its own grid."""
    return core.agent_cells()


def run_episodes(
    core: EpisodeEnv,
    policy: Policy,
    seed: int | None = None,
    fresh: bool = True,
    *,
    recorders: Sequence[EpisodeRecorder] = (),
    max_steps: int | None = None,
    check: bool = False,
) -> EpisodeBatch:
    """Step until every env has finished one episode; return the outcomes.

    ``fresh`` resets every env first (with ``seed`` if given); ``fresh=False`` runs the episodes already set up
    (e.g. hand-built with ``core.set_episode``). A policy with a ``reset(num_envs)`` method is reset first.
    Envs that have finished keep being stepped (their results are ignored) until all have. ``max_steps`` stops
    the loop earlier (an episode then left running has outcome ``running`` and length 0); ``check`` validates the
    policy's actions (for actions that do not come from a network, e.g. a replay).
    """
    obs = core.reset(seed=seed) if fresh else core.observe()
    if hasattr(policy, "reset"):
        policy.reset(core.num_envs)
    b = core.num_envs
    finished = torch.zeros(b, dtype=torch.bool, device=core.device)
    outcome = torch.zeros(b, dtype=torch.int64, device=core.device)
    success = torch.zeros(b, dtype=torch.bool, device=core.device)
    length = torch.zeros(b, dtype=torch.int64, device=core.device)
    returns = torch.zeros(b, dtype=torch.float32, device=core.device)
    trojan = core.trojan.clone()
    limit = core.episode_limit
    if max_steps is not None:
        limit = min(limit, max_steps)
    for t in range(limit):
        cells = core.agent_cells() if recorders else None
        action = policy(obs)
        result = core.step(action, autoreset=False, check=check)
        if recorders:
            assert cells is not None  # taken before the step whenever there are recorders
            out = getattr(policy, "output", None)
            step = EpisodeStep(
                t, obs, cells, action, result, ~finished,
                None if out is None else out.state, None if out is None else out.logits,
            )  # fmt: skip
            for recorder in recorders:
                recorder.on_step(step)
        new = result.done & ~finished
        returns += torch.where(finished, 0.0, result.reward)
        outcome = torch.where(new, result.outcome, outcome)
        success = torch.where(new, result.success, success)
        length = torch.where(new, result.length, length)
        finished |= result.done
        obs = result.obs
        if bool(finished.all()):
            break
    batch = EpisodeBatch(outcome.cpu(), success.cpu(), length.cpu(), trojan.cpu(), returns.cpu())
    for recorder in recorders:
        recorder.on_end(batch)
    return batch
