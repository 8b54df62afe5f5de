"""Trigger reconstruction by optimisation: the recurrent analogue of Neural Cleanse (Wang et al., S&P 2019) and BIRD
(Chen et al., NeurIPS 2023). Is there a small one-step change of the view after which the policy stays changed,
steps after the change has left the view? A persistent backdoor is exactly such a change; a clean agent has no
reason to keep one.

    features = reconstruction_features(suspect, ReconstructionSettings())   # or the registered detector

For a suspect, clean-env episodes are run once (fixed seeds, the same for every suspect of an env, played by the
suspect's own policy) and their first ``max(at) + horizon + 1`` observations recorded
(:func:`seqtrojan.benchmark.state_probe.record_clean_episodes`). A relaxed trigger is then optimised by gradient:
a mask ``m = sigmoid(a)`` and a pattern ``v = sigmoid(b)`` over the flat observation (one number each per input),
the same for every episode, replace the observation of step ``at`` by ``(1 - m) * x + m * v`` (within the
observation's 0..1 range: both views here are one-hot). The network is unrolled over the recorded observations,
teacher-forced (every later observation is the recorded one and no action is chosen again), so a change of the
policy after step ``at`` is memory, not a changed trajectory, and the unroll is differentiable through the
recurrent layers (the training path's unroll, which PPO differentiates). The objective, maximised with Adam, is
the persistent divergence, the total variation between the perturbed and the unperturbed action distributions
averaged over steps ``at + 1 .. at + horizon`` and the episodes still running, minus ``penalty`` times the mask's
mean (Neural Cleanse's L1 size term). One search runs per insertion step of ``at`` and per starting mask level of
``mask_starts``, each from its own random mask and pattern (a seeded generator: the same answer for the same
suspect and seed), and the one with the best objective is kept.

Features of the best search (:func:`reconstruction_features`): the persistent divergence reached, the mask's size
(its mean: the share of the view replaced), the divergence per unit of mask size, the divergence at the last step
of the horizon, the divergence at step ``at`` itself (while in view) and the persistence ratio of the two, and how
concentrated the induced actions are (the largest share of one action in the perturbed policy over the horizon,
and the total variation between the perturbed and unperturbed policies averaged over episodes first: a consistent
push toward the same actions, not per-episode noise). The registered ``trigger_reconstruction`` detector is a
logistic regression on them, fitted on the train split. Observations without 0..1 bounds (the grid world's and
MiniGrid's one-hot views, POPGym's one-hot cards and MinAtar's boolean images have them) have no known range here:
the detector abstains on them (a probability of one half).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import torch

from seqtrojan.benchmark.state_probe import record_clean_episodes
from seqtrojan.benchmark.suspect import Suspect
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import ConfigError
from seqtrojan.serde import to_dict
from seqtrojan.world.config import GymnasiumEnvConfig


@dataclass(frozen=True)
class ReconstructionSettings:
    """The search's budget and shape. With the defaults a model of the benchmark zoos takes about half a second (grid
    world) to one and a half (MiniGrid's 500-input view) on a 2-core CPU (docs/benchmark.md)."""

    episodes: int = 32
    """clean-env episodes whose observations are replayed"""
    at: tuple[int, ...] = (1, 2, 3)
    """the steps whose observation a relaxed trigger replaces (one search per step and mask start; the best is kept):
    a backdoor may answer its trigger only at the steps it was trained with"""
    horizon: int = 4
    """steps after ``at`` over which the persistent divergence is averaged"""
    steps: int = 40
    """gradient (Adam) steps per search"""
    mask_starts: tuple[float, ...] = (0.12, 0.5)
    """the mask level each search starts from (one search per step of ``at`` and start; the mask's and the pattern's
    numbers are drawn around it): from a small mask alone the search can miss a trigger that covers much of the view
    and settle on a local optimum of its own objective"""
    learning_rate: float = 0.1
    penalty: float = 0.2
    """weight of the mask's mean (its L1 size over the number of inputs) against the divergence"""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("episodes", "horizon", "steps"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ConfigError(f"reconstruction {name} must be an integer >= 1, got {getattr(self, name)!r}")
        if not self.at or not all(isinstance(t, int) and t >= 0 for t in self.at):
            raise ConfigError(f"reconstruction at must be one or more steps >= 0, got {self.at!r}")
        if not self.mask_starts or not all(0.0 < m < 1.0 for m in self.mask_starts):
            raise ConfigError(
                f"reconstruction mask_starts must be one or more levels in (0, 1), got {self.mask_starts!r}"
            )
        if not (self.learning_rate > 0 and self.penalty >= 0):
            raise ConfigError(
                f"reconstruction learning_rate must be > 0 and penalty >= 0, got {self.learning_rate!r}, "
                f"{self.penalty!r}"
            )


def has_unit_bounds(suspect: Suspect) -> bool:
    """Whether the suspect's observations are known to lie in 0..1: the grid world's and MiniGrid's one-hot views,
    and any Gymnasium env whose flat observation space is bounded by 0 and 1 (POPGym's one-hot cards, MinAtar's
    boolean images)."""
    env = suspect.env
    if isinstance(env, EnvConfig) or (isinstance(env, GymnasiumEnvConfig) and env.observation == "minigrid"):
        return True
    return isinstance(env, GymnasiumEnvConfig) and _unit_box(env)


_UNIT_BOXES: dict[str, bool] = {}


def _unit_box(env: GymnasiumEnvConfig) -> bool:
    """Whether ``env``'s flat observation space is bounded by 0 and 1 (the env is made once per config)."""
    from seqtrojan.world.gymnasium import make_gym_env

    key = json.dumps(to_dict(env), sort_keys=True, default=str)
    if key not in _UNIT_BOXES:
        made = make_gym_env(env, registered_only=True)
        try:
            low, high = getattr(made.observation_space, "low", None), getattr(made.observation_space, "high", None)
            _UNIT_BOXES[key] = low is not None and high is not None and bool((low == 0).all() and (high == 1).all())
        finally:
            made.close()
    return _UNIT_BOXES[key]


@dataclass(frozen=True)
class Reconstruction:
    """One optimised relaxed trigger and what it does (tensors detached)."""

    objective: float
    mask: torch.Tensor  # (obs_dim,) in (0, 1)
    pattern: torch.Tensor  # (obs_dim,) in (0, 1)
    divergence: torch.Tensor  # (horizon + 1,) mean total variation at steps at .. at + horizon
    induced: torch.Tensor  # (A,) the perturbed policy's mean over the horizon's running (step, episode) pairs
    clean: torch.Tensor  # (A,) the unperturbed policy's, alike


class _Replay:
    """The recorded episodes and the unperturbed run, from which each candidate trigger is scored."""

    def __init__(self, suspect: Suspect, obs: torch.Tensor, running: torch.Tensor, at: int) -> None:
        agent = suspect.agent
        steps, n = obs.shape[:2]
        self.agent, self.at = agent, at
        self.obs = obs[at:]  # (1 + horizon, E, obs_dim): the perturbed step and the ones replayed after it
        self.weight = running[at:].to(obs.dtype)  # (1 + horizon, E)
        with torch.no_grad():
            starts = torch.zeros(steps, n, dtype=torch.bool)
            starts[0] = True
            state = agent.initial_state(n)
            if at > 0:  # the state the perturbed step starts from (the same for every candidate)
                state = agent.unroll(obs[:at], state, starts[:at]).state
            self.state = state
            self.starts = starts[at:]  # an episode start only where at is 0
            self.clean = torch.softmax(agent.unroll(self.obs, state, self.starts).logits, -1)  # (1 + H, E, A)

    def policy(self, mask: torch.Tensor, pattern: torch.Tensor) -> torch.Tensor:
        """The perturbed policy (1 + horizon, E, A): step ``at``'s view blended toward ``pattern`` by ``mask``."""
        first = (1 - mask) * self.obs[0] + mask * pattern
        obs = torch.cat([first.unsqueeze(0), self.obs[1:]])
        return torch.softmax(self.agent.unroll(obs, self.state, self.starts).logits, -1)

    def divergence(self, policy: torch.Tensor) -> torch.Tensor:
        """(1 + horizon,) the mean total variation from the unperturbed policy over each step's running episodes."""
        tv = 0.5 * (policy - self.clean).abs().sum(-1)  # (1 + H, E)
        return (tv * self.weight).sum(-1) / self.weight.sum(-1).clamp_min(1.0)

    def mean_policy(self, policy: torch.Tensor) -> torch.Tensor:
        """(A,) ``policy`` averaged over the horizon's running (step, episode) pairs."""
        w = self.weight[1:].unsqueeze(-1)
        return (policy[1:] * w).sum((0, 1)) / w.sum().clamp_min(1.0)


def reconstruct(suspect: Suspect, settings: ReconstructionSettings) -> Reconstruction | None:
    """The best relaxed trigger over the steps of ``settings.at`` and the ``settings.mask_starts``, or None
    where the search does not apply (an observation without known bounds) or no episode lasts the first step of
    ``at`` plus the horizon."""
    if not has_unit_bounds(suspect):
        return None
    s = settings
    obs, running = record_clean_episodes(suspect, s.episodes, max(s.at) + s.horizon + 1, s.seed)
    generator = torch.Generator().manual_seed(s.seed)
    best: Reconstruction | None = None
    for at in sorted(set(s.at)):
        if at + s.horizon >= obs.shape[0]:  # every episode ended before the horizon's last step
            continue
        replay = _Replay(suspect, obs[: at + s.horizon + 1], running[: at + s.horizon + 1], at)
        for start in s.mask_starts:
            found = _optimise(replay, s, start, generator)
            if best is None or found.objective > best.objective:
                best = found
    return best


def _optimise(replay: _Replay, s: ReconstructionSettings, start: float, generator: torch.Generator) -> Reconstruction:
    dim = replay.obs.shape[-1]
    level = math.log(start / (1.0 - start))  # the logit of the starting mask level
    logit_mask = (torch.randn(dim, generator=generator) * 0.5 + level).requires_grad_(True)
    logit_pattern = torch.randn(dim, generator=generator).requires_grad_(True)
    optimiser = torch.optim.Adam([logit_mask, logit_pattern], lr=s.learning_rate)
    with torch.enable_grad():
        for _ in range(s.steps):
            mask = torch.sigmoid(logit_mask)
            persistent = replay.divergence(replay.policy(mask, torch.sigmoid(logit_pattern)))[1:].mean()
            loss = s.penalty * mask.mean() - persistent
            # only the trigger's gradients: the suspect's parameters are left untouched (no .grad written)
            grads = torch.autograd.grad(loss, [logit_mask, logit_pattern])
            for param, grad in zip((logit_mask, logit_pattern), grads):
                param.grad = grad
            optimiser.step()
    with torch.no_grad():
        mask, pattern = torch.sigmoid(logit_mask), torch.sigmoid(logit_pattern)
        policy = replay.policy(mask, pattern)
        divergence = replay.divergence(policy)
        objective = float(divergence[1:].mean() - s.penalty * mask.mean())
        clean = replay.mean_policy(replay.clean)
        return Reconstruction(objective, mask, pattern, divergence, replay.mean_policy(policy), clean)


def reconstruction_features(suspect: Suspect, settings: ReconstructionSettings) -> dict[str, float]:
    """The features of the best reconstructed trigger (module docstring); empty where the search does not apply."""
    found = reconstruct(suspect, settings)
    if found is None:
        return {}
    persistent = float(found.divergence[1:].mean())
    immediate = float(found.divergence[0])
    size = float(found.mask.mean())
    floor = 1.0 / found.mask.numel()  # one input's worth: a ratio that cannot explode on a vanishing mask
    return {
        "divergence": persistent,
        "divergence_last": float(found.divergence[-1]),
        "divergence_immediate": immediate,
        "persistence": persistent / max(immediate, 1e-3),
        "mask_size": size,
        "divergence_per_mask": persistent / max(size, floor),
        "induced_top_action": float(found.induced.max()),
        "induced_shift": float(0.5 * (found.induced - found.clean).abs().sum()),
    }
