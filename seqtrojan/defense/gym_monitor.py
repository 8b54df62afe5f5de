"""The state monitors on a Gymnasium env's model (``seqtrojan defend`` on such a model): the per-unit and the
multivariate monitor, calibrated on the model's own clean episodes of its config's env exactly as on the grid world
(first half: statistics; second half: the split-conformal threshold at the false-alarm target), then measured on fresh
episodes: false alarms in normal episodes, detection (an alarm at or after the trigger's first step) in trojan ones.

The monitors only raise alarms here (they do not reset the state): the measurement runs on recorded episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.defense.monitor import StateMonitor
from seqtrojan.defense.multivariate import MultivariateMonitor
from seqtrojan.defense.online import MonitorConfig
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate
from seqtrojan.train.gym_evaluation import GymEpisode, evaluate_gym, padded_states

GYM_MONITOR_FILE = "gym_monitor.json"
GYM_MONITORS = ("state_monitor", "multivariate_monitor")


@dataclass(frozen=True)
class GymMonitorArm:
    monitor: str
    threshold: float
    false_alarm: Rate
    """normal episodes with an alarm at any step"""
    detection: Rate
    """trojan episodes with an alarm at or after the trigger's first step"""


@dataclass(frozen=True)
class GymMonitorReport:
    """``gym_monitor.json``."""

    model: str
    env_id: str
    label: str
    calibration_episodes: int
    episodes: int
    false_alarm_target: float
    arms: tuple[GymMonitorArm, ...]


def monitor_gym_model(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    cfg: MonitorConfig,
    *,
    model: str = "",
    label: str = "",
    device: torch.device | str = "cpu",
) -> GymMonitorReport:
    """Calibrate both state monitors on clean episodes, then measure them on fresh normal and trojan episodes."""
    if config.gym_env.trigger is None:
        raise ConfigError("the gym config has no trigger section: there are no trojan episodes to detect")

    def record(trojan: bool, count: int, seed: int) -> tuple[GymEpisode, ...]:
        return evaluate_gym(agent, config, trojan=trojan, episodes=count, seed=seed, device=device,
                            record_states=True).episodes  # fmt: skip

    layers, mask = padded_states(record(False, cfg.calibration_episodes, cfg.seed))
    units = tuple(x.shape[-1] for x in layers)
    per_unit = StateMonitor.from_states(layers, mask, cfg.false_alarm_target)
    joint = MultivariateMonitor.from_states(np.concatenate(layers, -1), mask, units, cfg.false_alarm_target)
    fresh = cfg.seed + 1_000_003  # not the calibration episodes
    normal, trojan = record(False, cfg.eval_episodes, fresh), record(True, cfg.eval_episodes, fresh)
    arms = []
    for name, monitor in (("state_monitor", per_unit), ("multivariate_monitor", joint)):
        rates = []
        for episodes, after_trigger in ((normal, False), (trojan, True)):
            layers, mask = padded_states(episodes)
            if isinstance(monitor, StateMonitor):
                scores = np.where(mask, monitor.score_states(layers), -np.inf)
            else:
                scores = monitor.score_array(np.concatenate(layers, -1), mask)
            if after_trigger:
                first = np.array([max(e.trigger_step, 0) for e in episodes])
                scores = np.where(np.arange(scores.shape[1])[None, :] >= first[:, None], scores, -np.inf)
            rates.append(Rate(int((scores.max(1) > monitor.threshold).sum()), len(episodes)))
        arms.append(GymMonitorArm(name, float(monitor.threshold), rates[0], rates[1]))
    return GymMonitorReport(model, config.gym_env.id, label, cfg.calibration_episodes, cfg.eval_episodes,
                            cfg.false_alarm_target, tuple(arms))  # fmt: skip
