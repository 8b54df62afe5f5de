"""What every online detector shares: the :class:`OnlineDetector` protocol that
:class:`~seqtrojan.defense.monitor.MonitoredPolicy` and :func:`~seqtrojan.defense.monitor.measure_monitor` accept,
the calibration settings (:class:`MonitorConfig`), the split-conformal threshold (:func:`conformal_threshold`) and
the recording of the deployed agent's own clean episodes that every detector calibrates on.

An online detector scores every step of an episode from what the deployed agent saw (the observation) and what it
holds (its recurrent state after the step's update); an episode's score is its running maximum, and the detector
raises an alarm at the first step whose score exceeds its ``threshold``. Every detector calibrates the same way,
with no knowledge of any trigger: ``calibration_episodes`` clean (normal-env) episodes of the agent, the first half
to learn what is normal, the other half's per-episode peak scores to set the threshold at their split-conformal
``1 - false_alarm_target`` quantile.

The detectors: :class:`~seqtrojan.defense.monitor.StateMonitor` (per-unit z-scores),
:class:`~seqtrojan.defense.multivariate.MultivariateMonitor` (step-conditioned Mahalanobis distance of the whole
state), :class:`~seqtrojan.defense.goal_switch.GoalSwitchMonitor` (surprise of the agent's own output transition:
its action distribution and value) and :class:`~seqtrojan.defense.novelty.InputNovelty` (rarity of the observation
itself, a baseline).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import RecurrentState
from seqtrojan.config import EnvSection
from seqtrojan.env.codes import NUM_CHANNELS
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, run_episodes
from seqtrojan.errors import ConfigError


@dataclass(frozen=True)
class MonitorConfig:
    calibration_episodes: int = 1000
    """clean episodes of the deployed agent used to calibrate (half for statistics, half for the threshold). Few
    episodes make the per-unit statistics noisy and the threshold conservative: on the smoke agents 200 gave a
    detection rate of 0.02, 1000 gave 0.99 (both under 1% false alarms). Episodes are batched, so this is cheap"""
    false_alarm_target: float = 0.01
    """per-episode false-alarm rate the threshold is set for"""
    eval_episodes: int = 1000
    """fresh episodes per measurement"""
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.false_alarm_target < 1:
            raise ConfigError(f"false_alarm_target must be in (0, 1), got {self.false_alarm_target}")
        if self.calibration_episodes < 20:
            raise ConfigError(f"calibration_episodes must be >= 20, got {self.calibration_episodes}")
        held_out = self.calibration_episodes - self.calibration_episodes // 2
        if held_out + 1 < 1.0 / self.false_alarm_target - 1e-9:
            raise ConfigError(
                f"calibration_episodes={self.calibration_episodes} holds out {held_out} episodes for the threshold, "
                f"too few for false_alarm_target={self.false_alarm_target:g} (needs at least "
                f"{int(np.ceil(1 / self.false_alarm_target)) - 1})"
            )


def conformal_threshold(peaks: np.ndarray, false_alarm_target: float) -> float:
    """The split-conformal threshold: the ceil((n + 1)(1 - target))-th smallest of n held-out clean peaks. When
    deployment episodes are exchangeable with the calibration ones, an episode's false-alarm probability, averaged
    over calibrations, is at most ``target`` (a plain empirical quantile undershoots it for small n). With too few
    peaks for the target (n + 1 < 1 / target) no finite threshold guarantees it: a clear error."""
    n = len(peaks)
    k = int(np.ceil((n + 1) * (1.0 - false_alarm_target)))
    if k > n:
        raise ConfigError(
            f"{n} held-out calibration episodes cannot give a {false_alarm_target:g} false-alarm rate; "
            f"use calibration_episodes >= {2 * int(np.ceil(1 / false_alarm_target - 1))}"
        )
    return float(np.sort(peaks)[k - 1])


class OnlineDetector(Protocol):
    """An online detector: scores each step of a batch of episodes; an alarm is a score above ``threshold``."""

    threshold: float
    """alarm above this (the split-conformal quantile of held-out clean per-episode peaks)"""

    @property
    def units(self) -> tuple[int, ...]:
        """recurrent units watched per layer (h and c together); () for a detector that reads only the input"""
        ...

    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) the score of one step: ``obs`` (B, obs_dim) the one-hot observation the agent acted on, ``state``
        its state after the step's update, ``t`` (B,) int64 each env's episode step."""
        ...

    @classmethod
    def calibrate(
        cls, agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: MonitorConfig,
        device: str | torch.device = "cpu",
    ) -> OnlineDetector:  # fmt: skip
        """Fit on ``cfg.calibration_episodes`` clean episodes of ``agent`` on ``grid`` (a Gymnasium env section:
        on its env; ``grid`` None) seeded ``cfg.seed``."""
        ...


def monitor_applies(detector: type, env: EnvSection) -> bool:
    """Whether an online detector class can watch an agent of ``env`` (a detector that reads the grid world's
    view codes says so with a class attribute ``grid_only = True``)."""
    return isinstance(env, EnvConfig) or not getattr(detector, "grid_only", False)


def view_codes(obs: torch.Tensor) -> torch.Tensor:
    """(B, cells) int64: the cell code of every view cell of one-hot observations ``obs`` (B, cells * 6)."""
    return obs.view(obs.shape[0], -1, NUM_CHANNELS).argmax(-1)


def split(episodes: int) -> int:
    """How many of ``episodes`` calibration episodes go to the statistics (the rest set the threshold)."""
    return episodes // 2


@dataclass
class CleanCodes:
    """The view codes of clean episodes: ``codes`` (E, T, cells) int64, ``mask`` (E, T) bool (the step ran)."""

    codes: np.ndarray
    mask: np.ndarray


class _CodeRecorder:
    def __init__(self, episodes: int, limit: int, cells: int) -> None:
        self.codes = np.zeros((episodes, limit, cells), np.int64)
        self.mask = np.zeros((episodes, limit), bool)
        self.steps = 0

    def on_step(self, step: EpisodeStep) -> None:
        self.codes[:, step.t] = view_codes(step.obs).cpu().numpy()
        self.mask[:, step.t] = step.running.cpu().numpy()
        self.steps = step.t + 1

    def on_end(self, batch: EpisodeBatch) -> None:
        pass


@torch.no_grad()
def record_clean_codes(
    agent: RecurrentActorCritic, env: EnvConfig, grid: GridSpec, *, episodes: int, seed: int,
    device: str | torch.device = "cpu",
) -> CleanCodes:  # fmt: skip
    """The observations of ``episodes`` normal-env episodes of ``agent`` (sampled actions): the same episodes, seed
    for seed, as :func:`seqtrojan.analysis.traces.record_traces` with ``trojan=False`` records states of."""
    core = TrojanGridCore(env.with_grid(grid), episodes, seed=seed, device=device, trojan_probability=0.0, phase="eval")
    limit = max(g.time_limit for g in core.grids)
    recorder = _CodeRecorder(episodes, limit, core.view_size**2)
    policy = AgentPolicy(agent, seed=seed, step_counter=lambda: core.t)
    run_episodes(core, policy, fresh=False, recorders=[recorder])
    return CleanCodes(recorder.codes[:, : recorder.steps], recorder.mask[:, : recorder.steps])
