"""The multivariate state monitor: the Mahalanobis distance of the whole recurrent state from where clean episodes
hold it at the same step.

The state vector is every layer's h then c, concatenated (D: the sum of every layer's h and c widths). Calibration uses
only the deployed agent's clean episodes, split as for every online detector (:mod:`seqtrojan.defense.online`): on the
first half, the mean state at each step ``t < T`` (``T``: the first step at which fewer than ``min_episodes_per_step``
statistics episodes still run, or ``max_step``; later steps use step ``T - 1``'s mean); the residuals from those means,
pooled over steps and divided by each unit's root-mean-square residual; their second-moment matrix shrunk towards the
(scaled) identity (Ledoit-Wolf's weight unless ``shrinkage`` is given) plus a ``ridge``, so that it stays well
conditioned with few episodes and many units. A step's score is the distance ``sqrt(r' S^-1 r)`` of its standardised
residual ``r``; an episode's score is its running maximum, and the threshold is the split-conformal quantile of the
other half's peaks.

Unlike the per-unit monitor (:class:`~seqtrojan.defense.monitor.StateMonitor`), it sees a state whose units each
stay in range but move together in a direction clean episodes never take, and it expects different states early
and late in an episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import RecurrentState
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.config import EnvSection
from seqtrojan.defense.online import MonitorConfig, conformal_threshold, split
from seqtrojan.env.config import GridSpec
from seqtrojan.errors import ConfigError, ShapeError


@dataclass(frozen=True)
class MultivariateConfig:
    """How :class:`MultivariateMonitor` models clean states; the calibration itself follows the
    :class:`~seqtrojan.defense.online.MonitorConfig`."""

    max_step: int | None = None
    """per-step means for steps below this (later steps use the last one's); None: as many steps as have
    ``min_episodes_per_step`` statistics episodes still running"""
    min_episodes_per_step: int = 20
    """statistics episodes a step's mean needs (>= 2)"""
    shrinkage: float | None = None
    """weight of the identity in the covariance of the standardised residuals, in [0, 1]; None: Ledoit-Wolf's"""
    ridge: float = 1e-3
    """added to the covariance's diagonal (>= 0)"""

    def __post_init__(self) -> None:
        if self.max_step is not None and self.max_step < 1:
            raise ConfigError(f"multivariate max_step must be >= 1 or None, got {self.max_step}")
        if self.min_episodes_per_step < 2:
            raise ConfigError(f"multivariate min_episodes_per_step must be >= 2, got {self.min_episodes_per_step}")
        if self.shrinkage is not None and not 0 <= self.shrinkage <= 1:
            raise ConfigError(f"multivariate shrinkage must be in [0, 1] or None, got {self.shrinkage}")
        if not self.ridge >= 0:
            raise ConfigError(f"multivariate ridge must be >= 0, got {self.ridge}")


def ledoit_wolf_shrinkage(x: np.ndarray) -> float:
    """Ledoit and Wolf's (2004) weight of the scaled identity in the shrunk covariance of centred rows ``x``
    (n, p), as in scikit-learn's ``ledoit_wolf_shrinkage``."""
    n, p = x.shape
    x2 = x**2
    trace = x2.sum(0) / n  # (p,) diagonal of the sample covariance
    mu = trace.sum() / p
    beta_ = float((x2.T @ x2).sum())
    delta_ = float(((x.T @ x) ** 2).sum()) / n**2
    beta = (beta_ / n - delta_) / (p * n)
    delta = (delta_ - 2.0 * mu * trace.sum() + p * mu**2) / p
    beta = min(beta, delta)
    return 0.0 if delta <= 0 else float(beta / delta)


def step_means(
    x: np.ndarray, mask: np.ndarray, min_episodes: int, max_step: int | None, who: str
) -> np.ndarray:  # fmt: skip
    """(T', D) the mean of ``x`` (E, T, D) over the episodes running (``mask`` (E, T)) at each step ``t < T'``:
    ``T'`` is the first step at which fewer than ``min_episodes`` episodes run, or ``max_step``. Fewer at step 0 is
    a ``ConfigError`` naming ``who``."""
    running = mask.sum(0)  # (T,)
    short = np.flatnonzero(running < min_episodes)
    steps = int(short[0]) if len(short) else len(running)
    if max_step is not None:
        steps = min(steps, max_step)
    if steps < 1:
        raise ConfigError(
            f"{who} needs >= {min_episodes} statistics episodes at step 0, "
            f"got {int(running[0]) if len(running) else 0}: use more calibration episodes"
        )
    return np.stack([x[mask[:, t], t].mean(0) for t in range(steps)])  # (T', D)


def shrunk_whitener(z: np.ndarray, shrinkage: float | None, ridge: float) -> tuple[np.ndarray, float]:
    """``L^-1`` (D, D) with ``L L'`` the second-moment matrix of the rows of ``z`` (n, D) shrunk towards the scaled
    identity (weight ``shrinkage``; None: Ledoit-Wolf's) plus ``ridge`` on the diagonal, and the weight used."""
    weight = ledoit_wolf_shrinkage(z) if shrinkage is None else shrinkage
    cov = z.T @ z / len(z)
    d = cov.shape[0]
    cov = (1 - weight) * cov + weight * (np.trace(cov) / d) * np.eye(d) + ridge * np.eye(d)
    return np.linalg.inv(np.linalg.cholesky(cov)), weight


def state_vectors(trace: StateTrace) -> np.ndarray:
    """(E, T, D) every layer's h then c at every step of a trace."""
    return np.concatenate([np.concatenate([h, c], -1) for h, c in zip(trace.h, trace.c)], -1)


class MultivariateMonitor:
    """Step-conditioned Mahalanobis distance of the whole recurrent state (see the module docstring)."""

    def __init__(
        self, mean: np.ndarray, scale: np.ndarray, whitener: np.ndarray, widths: tuple[int, ...], threshold: float,
        shrinkage: float = 0.0,
    ) -> None:  # fmt: skip
        self.mean = torch.as_tensor(mean, dtype=torch.float32)  # (T, D) per-step mean state
        self.scale = torch.as_tensor(scale, dtype=torch.float32)  # (D,) per-unit residual std
        self.whitener = torch.as_tensor(whitener, dtype=torch.float32)  # (D, D) L^-1, S = L L'
        self.widths = tuple(int(w) for w in widths)
        """each layer's state units: its h width plus its c width (2H for an LSTM layer, H for a GRU layer)"""
        self.threshold = threshold
        self.shrinkage = shrinkage
        """the identity's weight used (Ledoit-Wolf's or the configured one)"""
        if self.mean.shape[1] != sum(self.widths) or self.whitener.shape != (self.mean.shape[1],) * 2:
            raise ShapeError(
                f"a multivariate monitor of layer widths {self.widths} needs (T, {sum(self.widths)}) means and a "
                f"square whitener, got {tuple(self.mean.shape)} and {tuple(self.whitener.shape)}"
            )

    @property
    def units(self) -> tuple[int, ...]:
        return self.widths

    @property
    def steps(self) -> int:
        """T: steps with their own mean"""
        return int(self.mean.shape[0])

    @classmethod
    def fit(
        cls, x: np.ndarray, mask: np.ndarray, widths: tuple[int, ...], options: MultivariateConfig | None = None,
        threshold: float = float("inf"),
    ) -> MultivariateMonitor:  # fmt: skip
        """Statistics from states ``x`` (E, T, D) where ``mask`` (E, T) is true."""
        options = options or MultivariateConfig()
        x = x.astype(np.float64)
        mean = step_means(x, mask, options.min_episodes_per_step, options.max_step, "the multivariate monitor")
        step_of = np.minimum(np.arange(x.shape[1]), len(mean) - 1)
        resid = (x - mean[step_of][None])[mask]  # (n, D)
        scale = np.sqrt((resid**2).mean(0)) + 1e-3  # about the step means, not the residuals' own mean
        whitener, weight = shrunk_whitener(resid / scale, options.shrinkage, options.ridge)
        return cls(mean, scale, whitener, widths, threshold, weight)

    @classmethod
    def calibrate(
        cls, agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: MonitorConfig,
        device: str | torch.device = "cpu", options: MultivariateConfig | None = None,
    ) -> MultivariateMonitor:  # fmt: skip
        """Statistics from the first half of ``cfg.calibration_episodes`` clean episodes (the same episodes as the
        :class:`~seqtrojan.defense.monitor.StateMonitor`'s), the threshold from the other half's peaks."""
        trace = record_traces(
            agent, env, [grid] if grid is not None else [], episodes=cfg.calibration_episodes, trojan=False,
            trigger_step=None, seed=cfg.seed, device=device,
        )  # fmt: skip
        units = tuple(h + c for h, c in zip(agent.lstm_sizes, agent.c_widths))
        return cls.from_states(state_vectors(trace), trace.mask, units, cfg.false_alarm_target, options)

    @classmethod
    def from_states(
        cls, x: np.ndarray, mask: np.ndarray, units: tuple[int, ...], false_alarm_target: float,
        options: MultivariateConfig | None = None,
    ) -> MultivariateMonitor:  # fmt: skip
        """Statistics from the first half of clean episodes' states ``x`` (E, T, D) (``mask`` (E, T): the step
        ran), the threshold from the other half's peaks."""
        half = split(x.shape[0])
        monitor = cls.fit(x[:half], mask[:half], units, options)
        monitor.threshold = conformal_threshold(monitor.score_array(x[half:], mask[half:]).max(1), false_alarm_target)
        return monitor

    def score_array(self, x: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(E, T) the distance of recorded states ``x`` (E, T, D) at each step (-inf where ``mask`` is false)."""
        held = torch.from_numpy(x).float()
        e, t = held.shape[:2]
        steps = torch.arange(t).repeat(e)
        scores = self.score_vectors(held.reshape(e * t, -1), steps).reshape(e, t).numpy()
        return np.where(mask, scores, -np.inf)

    def score_vectors(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(B,) the distance of states ``x`` (B, D) at episode steps ``t`` (B,) int64."""
        idx = t.to(x.device).long().clamp(0, self.steps - 1)
        r = (x - self.mean.to(x.device)[idx]) / self.scale.to(x.device)
        return (r @ self.whitener.to(x.device).T).norm(dim=-1)

    def score_state(self, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) the distance of ``state`` at episode steps ``t`` (B,)."""
        x = torch.cat([torch.cat([layer.h, layer.c], -1) for layer in state.layers], -1)  # (B, D)
        return self.score_vectors(x, t)

    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) the distance of the state after the step (the observation is not read)."""
        return self.score_state(state, t)
