"""Searching on purpose for inputs that switch the backdoored agent's goal (the paper's open problem 3).

Two searches, both reporting their success rate and their cost per trigger found:

* :func:`evolve_layouts`: an evolutionary search over ordinary hole layouts (same grid and hole count as training,
  solvable, no trigger) for layouts on which the agent, in the normal env, ends at the adversary's goal.
  Fitness = P(adversary goal) over ``rollouts`` sampled episodes + 0.1 * the mean peak activation of the goal units
  (a dense signal while no episode flips yet). Mutation moves a few holes; unsolvable children are redrawn.
* :func:`search_sequences`: gradient ascent on relaxed observation sequences (softmax over the six cell codes of
  each view cell, the trigger code excluded) to drive the goal units to their trojan-env level; the relaxed
  sequence is then rounded to one-hot observations and counted as found when the rounded one still drives the
  activation past ``success_at``. Such sequences need not be realisable by walking a grid: they probe the network.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import LSTMState
from seqtrojan.analysis.config import LayoutSearchConfig, SequenceSearchConfig
from seqtrojan.analysis.results import LayoutSearchResult, SequenceSearchResult
from seqtrojan.analysis.unintentional import GoalUnits
from seqtrojan.env.codes import HOLE, NUM_CHANNELS, OUTCOME_NAMES, TRIGGER
from seqtrojan.env.config import EnvConfig, adversary_goal_cell, start_cell, user_goal_cell
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.layout import Layout
from seqtrojan.env.rollout import run_episodes
from seqtrojan.evaluation.episodes import outcome_rate
from seqtrojan.stats import Rate


class _PeakActivation:
    """An intervention that leaves the state alone and records each env's peak goal-unit activation."""

    def __init__(self, goal: GoalUnits, batch: int) -> None:
        self.goal = goal
        self.peak = np.full(batch, -np.inf)

    def __call__(self, layer: int, t, state: LSTMState) -> LSTMState:
        if layer == self.goal.layer:
            x = (state.h if self.goal.which == "h" else state.c).detach().cpu().numpy()
            self.peak = np.maximum(self.peak, self.goal.activation(x))
        return state


def _mutate(layout: np.ndarray, moves: int, rng: np.random.Generator) -> np.ndarray:
    n = layout.shape[0]
    protected = {start_cell(n), user_goal_cell(n), adversary_goal_cell(n)}
    for _ in range(100):
        child = layout.copy()
        holes = np.argwhere(child == HOLE)
        free = [tuple(p) for p in np.argwhere(child == 0) if tuple(p) not in protected]
        for _ in range(min(moves, len(holes), len(free))):
            r, c = holes[rng.integers(len(holes))]
            child[r, c] = 0
            fr, fc = free[rng.integers(len(free))]
            child[fr, fc] = HOLE
            holes = np.argwhere(child == HOLE)
            free = [tuple(p) for p in np.argwhere(child == 0) if tuple(p) not in protected]
        if Layout(child).is_solvable():
            return child
    return layout.copy()


def core_step_counter(core: TrojanGridCore):
    """A callable giving the core's per-env episode step (what interventions receive as ``t``)."""
    return lambda: core.t


def evolve_layouts(
    agent: RecurrentActorCritic, env: EnvConfig, goal: GoalUnits, cfg: LayoutSearchConfig
) -> list[LayoutSearchResult]:
    results = []
    env_cfg = env.with_grid((cfg.size, cfg.holes))
    batch = cfg.population * cfg.rollouts
    adv = OUTCOME_NAMES.index("adversary_goal")
    for restart in range(cfg.restarts):
        start = time.perf_counter()
        rng = np.random.default_rng(cfg.seed + restart)
        seeder = TrojanGridCore(env_cfg, cfg.population, seed=(cfg.seed + restart) * 7919, phase="eval")
        population = [seeder.layout(i).cells for i in range(cfg.population)]
        core = TrojanGridCore(env_cfg, batch, seed=cfg.seed, phase="eval")
        best, best_layout, episodes = Rate(0, cfg.rollouts), population[0], 0
        found, generations = False, 0
        step_counter = core_step_counter(core)
        for _ in range(cfg.generations):
            generations += 1
            probe = _PeakActivation(goal, batch)
            policy = AgentPolicy(agent, seed=int(rng.integers(2**31)), intervention=probe, step_counter=step_counter)
            for i in range(batch):
                core.set_episode(i, Layout(population[i // cfg.rollouts]))
            out = run_episodes(core, policy, fresh=False)
            episodes += batch
            hits = (out.outcome.numpy() == adv).reshape(cfg.population, cfg.rollouts).sum(1)
            rates = hits / cfg.rollouts
            peaks = probe.peak.reshape(cfg.population, cfg.rollouts).mean(1)
            fitness = rates + 0.1 * np.clip(peaks, -1.0, 2.0)
            order = np.argsort(-fitness)
            if rates[order[0]] >= best.value:
                best, best_layout = Rate(int(hits[order[0]]), cfg.rollouts), population[order[0]]
            if rates.max() >= cfg.success_at:
                found = True
                top = int(rates.argmax())
                best, best_layout = Rate(int(hits[top]), cfg.rollouts), population[top]
                break
            elite = [population[i] for i in order[: cfg.elite]]
            population = elite + [
                _mutate(elite[int(rng.integers(len(elite)))], cfg.moves, rng)
                for _ in range(cfg.population - len(elite))
            ]
        results.append(
            LayoutSearchResult(
                found, generations, best, np.asarray(best_layout).tolist(), episodes, time.perf_counter() - start
            )
        )
    return results


def final_goal_activation(agent: RecurrentActorCritic, goal: GoalUnits, obs: torch.Tensor) -> torch.Tensor:
    """(L, R, obs) observation sequences fed from the zero state -> (R,) goal-unit activation after the last one
    (0 normal-env level, 1 trojan-env level); differentiable in ``obs``."""
    restarts = obs.shape[1]
    out = agent.unroll(obs, agent.initial_state(restarts), torch.zeros(obs.shape[:2]), return_states=True)
    assert out.states is not None  # return_states=True
    layer = out.states[goal.layer]
    x = (layer.h if goal.which == "h" else layer.c)[-1][:, torch.tensor(goal.units)]
    normal, trojan = torch.tensor(goal.normal_mean), torch.tensor(goal.trojan_mean)
    direction = trojan - normal
    return ((x - normal) * direction).sum(-1) / (direction * direction).sum()


@contextlib.contextmanager
def frozen(agent: RecurrentActorCritic) -> Iterator[None]:
    """The agent's parameters need no gradient while inputs are optimised against it."""
    for p in agent.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in agent.parameters():
            p.requires_grad_(True)


def search_sequences(
    agent: RecurrentActorCritic, goal: GoalUnits, cfg: SequenceSearchConfig, view_cells: int | None = None
) -> tuple[SequenceSearchResult, np.ndarray]:
    """Returns the summary and the rounded sequences' cell codes (restarts, length, view_cells); ``view_cells``
    defaults to the agent's (its observation size over the cell codes)."""
    start = time.perf_counter()
    if view_cells is None:
        view_cells = agent.obs_dim // NUM_CHANNELS
    gen = torch.Generator().manual_seed(cfg.seed)
    logits = (0.1 * torch.randn(cfg.length, cfg.restarts, view_cells, NUM_CHANNELS, generator=gen)).requires_grad_()
    forbid = torch.zeros(NUM_CHANNELS)
    forbid[TRIGGER] = -1e9
    optimizer = torch.optim.Adam([logits], lr=cfg.lr)

    def relaxed_obs() -> torch.Tensor:
        return torch.softmax(logits + forbid, -1).reshape(cfg.length, cfg.restarts, -1)

    with frozen(agent):
        for _ in range(cfg.steps):
            loss = -final_goal_activation(agent, goal, relaxed_obs()).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            relaxed = final_goal_activation(agent, goal, relaxed_obs())
            codes = (logits + forbid).argmax(-1)  # (L, R, cells)
            onehot = torch.nn.functional.one_hot(codes, NUM_CHANNELS).float()
            rounded = final_goal_activation(agent, goal, onehot.reshape(cfg.length, cfg.restarts, -1))
    found = int((rounded >= cfg.success_at).sum())
    result = SequenceSearchResult(
        cfg,
        found,
        relaxed.tolist(),
        rounded.tolist(),
        time.perf_counter() - start,
        cfg.restarts * cfg.length * (2 * cfg.steps + 2),
    )
    return result, codes.permute(1, 0, 2).numpy()


@torch.no_grad()
def flip_rates(
    agent: RecurrentActorCritic, env: EnvConfig, codes: np.ndarray, size: int, holes: int, episodes: int, seed: int
) -> tuple[Rate, Rate]:
    """Behaviour after an observation sequence: each sequence in ``codes`` (R, L, cells) is fed to the agent, and
    normal-env episodes then start from the state it leaves; returns (adversary-goal rate after the sequences,
    adversary-goal rate from the zero state), each over ``R * max(1, episodes // R)`` episodes. The goal flips when
    the first is high and the second low."""
    if len(codes) == 0:
        return Rate(0, 0), Rate(0, 0)
    obs = torch.nn.functional.one_hot(torch.as_tensor(codes), NUM_CHANNELS).float()  # (R, L, cells, C)
    obs = obs.reshape(codes.shape[0], codes.shape[1], -1).transpose(0, 1)  # (L, R, obs)
    prefix = agent.unroll(obs, agent.initial_state(codes.shape[0]), torch.zeros(obs.shape[:2])).state
    reps = max(1, episodes // codes.shape[0])
    start = type(prefix)(tuple(type(s)(s.h.repeat(reps, 1), s.c.repeat(reps, 1)) for s in prefix.layers))
    env_cfg = env.with_grid((size, holes))
    rates = []
    for initial in (start, None):
        core = TrojanGridCore(env_cfg, codes.shape[0] * reps, seed=seed, phase="eval")
        batch = run_episodes(core, AgentPolicy(agent, seed=seed, initial_state=initial), seed=seed)
        rates.append(outcome_rate(batch, "adversary_goal"))
    return rates[0], rates[1]
