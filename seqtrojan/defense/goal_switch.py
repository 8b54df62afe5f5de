"""The behavioural goal-switch monitor: an alarm when the agent's own outputs (its action distribution and its value
estimate) change from one step to the next in a way clean episodes never show at that step, whatever the trigger
looked like.

A backdoor in a recurrent agent switches its goal: from the trigger on, the policy commits to other actions and the
value estimate follows another goal. Both are outputs of the network, so this monitor never reads the observation
or the recurrent state as such: each step it takes the policy's log-probabilities (floored at ``prob_floor``) and the
value, ``x_t`` (F,), computed by the agent's own heads from the state it acts on (``agent.heads`` of the last layer's
h: exactly the step's logits and value).

Calibration, as for every online detector (:mod:`seqtrojan.defense.online`), on the deployed agent's clean episodes
only, the first half for the statistics: the mean output ``m_t`` at each step ``t < T`` (``T`` as the multivariate
monitor's: the first step with fewer than ``min_episodes_per_step`` statistics episodes, or ``max_step``; later
steps use step ``T - 1``'s); a linear prediction of each step's residual ``r_t = x_t - m_t`` from the previous one's,
``r_t ~ [r_{t-1}, 1] B``, least squares over every transition of the statistics episodes; the prediction errors
``e_t``, divided by each feature's RMS error, and their second-moment matrix shrunk towards the scaled identity
(Ledoit-Wolf's weight unless ``shrinkage`` is given) plus a ``ridge``. A step's score is the Mahalanobis distance of
its standardised error (the surprise of the transition ``x_{t-1} -> x_t`` given where the outputs were and the
step); step 0 has no previous outputs and scores 0. The threshold is the split-conformal quantile of the other
half's per-episode peaks.

The monitor keeps the previous step's outputs of every env (one batch of episodes at a time, from step 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import RecurrentState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.config import EnvSection
from seqtrojan.defense.multivariate import shrunk_whitener, step_means
from seqtrojan.defense.online import MonitorConfig, conformal_threshold, split
from seqtrojan.env.config import GridSpec
from seqtrojan.errors import ConfigError

Reads = Literal["both", "policy", "value"]
READS: tuple[Reads, ...] = ("both", "policy", "value")


@dataclass(frozen=True)
class GoalSwitchConfig:
    """How :class:`GoalSwitchMonitor` models clean output transitions; calibration follows the
    :class:`~seqtrojan.defense.online.MonitorConfig`."""

    reads: Reads = "both"
    """which outputs: the action distribution's log-probabilities and the value (``both``), or one of them"""
    prob_floor: float = 1e-6
    """log-probabilities are of ``p + prob_floor`` (> 0), so a near-certain policy's rare actions stay finite"""
    max_step: int | None = None
    """per-step means for steps below this (later steps use the last one's); None: as many steps as have
    ``min_episodes_per_step`` statistics episodes still running"""
    min_episodes_per_step: int = 20
    """statistics episodes a step's mean needs (>= 2)"""
    shrinkage: float | None = None
    """weight of the identity in the covariance of the standardised prediction errors, in [0, 1]; None:
    Ledoit-Wolf's"""
    ridge: float = 1e-3
    """added to the covariance's diagonal (>= 0)"""

    def __post_init__(self) -> None:
        if self.reads not in READS:
            raise ConfigError(f"goal_switch reads must be one of {', '.join(READS)}, got {self.reads!r}")
        if not self.prob_floor > 0:
            raise ConfigError(f"goal_switch prob_floor must be > 0, got {self.prob_floor}")
        if self.max_step is not None and self.max_step < 2:
            raise ConfigError(f"goal_switch max_step must be >= 2 or None, got {self.max_step}")
        if self.min_episodes_per_step < 2:
            raise ConfigError(f"goal_switch min_episodes_per_step must be >= 2, got {self.min_episodes_per_step}")
        if self.shrinkage is not None and not 0 <= self.shrinkage <= 1:
            raise ConfigError(f"goal_switch shrinkage must be in [0, 1] or None, got {self.shrinkage}")
        if not self.ridge >= 0:
            raise ConfigError(f"goal_switch ridge must be >= 0, got {self.ridge}")


def output_features(agent: RecurrentActorCritic, h: torch.Tensor, options: GoalSwitchConfig) -> torch.Tensor:
    """(..., F) what the monitor reads of the agent's outputs from its last layer's h (..., H): the log of each
    action's probability plus ``prob_floor`` (A features) and/or the value (1)."""
    logits, value = agent.heads(h)
    parts = []
    if options.reads in ("both", "policy"):
        parts.append(torch.log(torch.softmax(logits, -1) + options.prob_floor))
    if options.reads in ("both", "value"):
        parts.append(value.unsqueeze(-1))
    return torch.cat(parts, -1)


def _with_bias(r: np.ndarray) -> np.ndarray:
    return np.concatenate([r, np.ones((*r.shape[:-1], 1))], -1)


class GoalSwitchMonitor:
    """Surprise of the agent's output transition at each step, against clean episodes (see the module docstring)."""

    def __init__(
        self, agent: RecurrentActorCritic, mean: np.ndarray, coef: np.ndarray, scale: np.ndarray,
        whitener: np.ndarray, threshold: float, options: GoalSwitchConfig | None = None, shrinkage: float = 0.0,
    ) -> None:  # fmt: skip
        self.agent = agent
        self.options = options or GoalSwitchConfig()
        self.mean = torch.as_tensor(mean, dtype=torch.float32)  # (T, F) per-step mean output
        self.coef = torch.as_tensor(coef, dtype=torch.float32)  # (F + 1, F) previous residual (and 1) -> residual
        self.scale = torch.as_tensor(scale, dtype=torch.float32)  # (F,) per-feature RMS prediction error
        self.whitener = torch.as_tensor(whitener, dtype=torch.float32)  # (F, F) L^-1, S = L L'
        self.threshold = threshold
        self.shrinkage = shrinkage
        """the identity's weight used (Ledoit-Wolf's or the configured one)"""
        self.previous: torch.Tensor | None = None
        """(B, F) the outputs of each env's previous step (None before the first step)"""

    @property
    def units(self) -> tuple[int, ...]:
        """(): it reads the agent's outputs, not its units"""
        return ()

    @property
    def steps(self) -> int:
        """T: steps with their own mean"""
        return int(self.mean.shape[0])

    @classmethod
    def fit(
        cls, agent: RecurrentActorCritic, x: np.ndarray, mask: np.ndarray, options: GoalSwitchConfig | None = None,
        threshold: float = float("inf"),
    ) -> GoalSwitchMonitor:  # fmt: skip
        """Statistics from clean outputs ``x`` (E, T, F) where ``mask`` (E, T) is true."""
        options = options or GoalSwitchConfig()
        x = x.astype(np.float64)
        mean = step_means(x, mask, options.min_episodes_per_step, options.max_step, "the goal-switch monitor")
        resid = x - mean[np.minimum(np.arange(x.shape[1]), len(mean) - 1)][None]  # (E, T, F)
        moves = mask[:, 1:]  # (E, T - 1): a transition t-1 -> t (a running step has a running previous one)
        if int(moves.sum()) <= x.shape[-1] + 1:
            raise ConfigError(
                f"the goal-switch monitor needs more than {x.shape[-1] + 1} clean step transitions, got "
                f"{int(moves.sum())}: use more calibration episodes"
            )
        before, after = _with_bias(resid[:, :-1][moves]), resid[:, 1:][moves]  # (n, F + 1), (n, F)
        coef = np.linalg.lstsq(before, after, rcond=None)[0]  # (F + 1, F)
        error = after - before @ coef
        scale = np.sqrt((error**2).mean(0)) + 1e-3
        whitener, weight = shrunk_whitener(error / scale, options.shrinkage, options.ridge)
        return cls(agent, mean, coef, scale, whitener, threshold, options, weight)

    @classmethod
    def calibrate(
        cls, agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: MonitorConfig,
        device: str | torch.device = "cpu", options: GoalSwitchConfig | None = None,
    ) -> GoalSwitchMonitor:  # fmt: skip
        """Statistics from the first half of ``cfg.calibration_episodes`` clean episodes (the same episodes as the
        state monitors'), the threshold from the other half's peaks."""
        options = options or GoalSwitchConfig()
        trace = record_traces(
            agent, env, [grid] if grid is not None else [], episodes=cfg.calibration_episodes, trojan=False,
            trigger_step=None, seed=cfg.seed, device=device,
        )  # fmt: skip
        with torch.no_grad():
            x = output_features(agent, torch.from_numpy(trace.h[-1]).to(device), options).cpu().numpy()  # (E, T, F)
        return cls.from_outputs(agent, x, trace.mask, cfg.false_alarm_target, options)

    @classmethod
    def from_outputs(
        cls, agent: RecurrentActorCritic, x: np.ndarray, mask: np.ndarray, false_alarm_target: float,
        options: GoalSwitchConfig | None = None,
    ) -> GoalSwitchMonitor:  # fmt: skip
        """Statistics from the first half of clean episodes' outputs ``x`` (E, T, F) (``mask`` (E, T): the step
        ran), the threshold from the other half's peaks."""
        half = split(x.shape[0])
        monitor = cls.fit(agent, x[:half], mask[:half], options)
        peaks = monitor.score_outputs(x[half:], mask[half:]).max(1)
        monitor.threshold = conformal_threshold(peaks, false_alarm_target)
        return monitor

    def distance(self, x: torch.Tensor, previous: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(B,) the surprise of outputs ``x`` (B, F) at episode steps ``t`` (B,) >= 1 after ``previous`` (B, F)."""
        mean = self.mean.to(x.device)
        last = self.steps - 1
        t = t.to(x.device).long()
        r_now = x - mean[t.clamp(0, last)]
        r_before = previous - mean[(t - 1).clamp(0, last)]
        coef = self.coef.to(x.device)
        error = r_now - (r_before @ coef[:-1] + coef[-1])
        return ((error / self.scale.to(x.device)) @ self.whitener.to(x.device).T).norm(dim=-1)

    def score_outputs(self, x: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(E, T) the score of recorded outputs ``x`` (E, T, F) at each step: 0 at step 0, -inf where ``mask`` is
        false."""
        held = torch.from_numpy(x).float()
        e, t = held.shape[:2]
        scores = np.zeros((e, t))
        if t > 1:
            steps = torch.arange(1, t).repeat(e)
            now, before = held[:, 1:].reshape(-1, held.shape[-1]), held[:, :-1].reshape(-1, held.shape[-1])
            scores[:, 1:] = self.distance(now, before, steps).reshape(e, t - 1).numpy()
        return np.where(mask, scores, -np.inf)

    @torch.no_grad()
    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) the surprise of this step's outputs after the previous step's (the observation is not read; a
        step 0 scores 0)."""
        x = output_features(self.agent, state.layers[-1].h, self.options)  # (B, F)
        t = t.to(x.device).long()
        previous = self.previous if self.previous is not None and self.previous.shape == x.shape else None
        if previous is None:
            score = torch.zeros(x.shape[0], device=x.device)
        else:
            score = torch.where(t > 0, self.distance(x, previous.to(x.device), t), torch.zeros((), device=x.device))
        self.previous = x
        return score
