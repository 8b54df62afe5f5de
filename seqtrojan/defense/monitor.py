"""The online monitor (the paper's section 6): watch the LSTM's internal states, raise an alarm when they leave the
range seen on clean episodes, and optionally reset them.

Calibration uses only the deployed agent's own clean (normal-env) episodes -- no knowledge of any trigger: per
unit (every layer's h and c) the mean and standard deviation over all steps; the score of a step is the largest
|z| over units; the threshold is the split-conformal ``1 - false_alarm_target`` quantile of the per-episode peak
score over a held-out half of the calibration episodes (:func:`conformal_threshold`). During an episode the
monitor scores the state after every step; above the threshold it raises an alarm and, with ``action="reset"``,
zeroes that env's state before the next step (as at an episode start).

:func:`measure_monitor` reports, over fresh episodes and with 95% intervals: the false-alarm rate (normal env),
the detection rate (trojan env, an alarm at or after the trigger), alarms before the trigger, the steps from
trigger to alarm, the attack success (adversary's goal in the trojan env) without and with the monitor's reset,
and the clean success without and with it.

:class:`MonitoredPolicy` and :func:`measure_monitor` take any :class:`~seqtrojan.defense.online.OnlineDetector`:
this module's :class:`StateMonitor`, the :class:`~seqtrojan.defense.multivariate.MultivariateMonitor`, the
behavioural :class:`~seqtrojan.defense.goal_switch.GoalSwitchMonitor` and the
:class:`~seqtrojan.defense.novelty.InputNovelty` baseline, all registered in :data:`MONITORS` and calibrated the
same way (:mod:`seqtrojan.defense.online`); the measurement is the same typed :class:`MonitorResult` for each.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.config import EnvSection
from seqtrojan.defense.goal_switch import GoalSwitchMonitor
from seqtrojan.defense.multivariate import MultivariateMonitor
from seqtrojan.defense.novelty import InputNovelty
from seqtrojan.defense.online import MonitorConfig, OnlineDetector, conformal_threshold
from seqtrojan.defense.results import MonitorResult, NormalEnvArm, TrojanEnvArm
from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.config import GridSpec
from seqtrojan.env.rollout import EpisodeEnv, run_episodes
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.registry import Registry
from seqtrojan.stats import Rate
from seqtrojan.world.episodes import episode_env

MONITORS: Registry[type[OnlineDetector]] = Registry("defense", "monitor")
"""Online detectors (:class:`~seqtrojan.defense.online.OnlineDetector`): calibrated on the agent's clean episodes,
they score every step while it acts; :class:`MonitoredPolicy` raises their alarms (and resets the state)."""


@MONITORS.register("state_monitor", "online: alarm (and reset the state) when a unit's |z| leaves the clean range")
class StateMonitor:
    """Per-unit z-scores of all layers' h and c against clean-episode statistics."""

    def __init__(self, mean: list[np.ndarray], std: list[np.ndarray], threshold: float) -> None:
        self.mean = [torch.as_tensor(m, dtype=torch.float32) for m in mean]  # per layer: (2 * units,) h then c
        self.std = [torch.as_tensor(s, dtype=torch.float32) for s in std]
        self.threshold = threshold

    @classmethod
    def calibrate(
        cls, agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: MonitorConfig,
        device: str | torch.device = "cpu",
    ) -> StateMonitor:  # fmt: skip
        trace = record_traces(
            agent,
            env,
            [grid] if grid is not None else [],
            episodes=cfg.calibration_episodes,
            trojan=False,
            trigger_step=None,
            seed=cfg.seed,
            device=device,
        )
        layers = [np.concatenate([h, c], axis=-1) for h, c in zip(trace.h, trace.c)]  # per layer (E, T, h + c)
        return cls.from_states(layers, trace.mask, cfg.false_alarm_target)

    @classmethod
    def from_states(cls, layers: Sequence[np.ndarray], mask: np.ndarray, false_alarm_target: float) -> StateMonitor:
        """Statistics from the first half of the clean episodes, the threshold from the other half's peaks.
        ``layers``: per layer the states (E, T, units) of E clean episodes, h then c; ``mask`` (E, T): the step ran.
        """
        episodes = mask.shape[0]
        half = episodes // 2
        mean, std = [], []
        for x in layers:
            rows = x[:half][mask[:half]]
            mean.append(rows.mean(0))
            std.append(rows.std(0) + 1e-3)
        monitor = cls(mean, std, threshold=float("inf"))
        peaks = []
        for e in range(half, episodes):
            steps = mask[e]
            peaks.append(max(float(np.abs((x[e][steps] - m) / s).max()) for x, m, s in zip(layers, mean, std)))
        monitor.threshold = conformal_threshold(np.asarray(peaks), false_alarm_target)
        return monitor

    def score_states(self, layers: Sequence[np.ndarray]) -> np.ndarray:
        """(E, T) the score of recorded states (per layer (E, T, units), h then c): the largest |z| over units."""
        return np.max([np.abs((x - m.numpy()) / s.numpy()).max(-1) for x, m, s in zip(layers, self.mean, self.std)], 0)

    def score(self, state: RecurrentState) -> torch.Tensor:
        """(B,) largest |z| over every unit of every layer."""
        scores = []
        for layer, m, s in zip(state.layers, self.mean, self.std):
            x = torch.cat([layer.h, layer.c], -1)
            scores.append(((x - m.to(x.device)) / s.to(x.device)).abs().amax(-1))
        return torch.stack(scores).amax(0)

    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) :meth:`score` of the state after the step (the :class:`OnlineDetector` call)."""
        return self.score(state)

    @property
    def units(self) -> tuple[int, ...]:
        return tuple(int(m.numel()) for m in self.mean)


MONITORS.register(
    "multivariate_monitor",
    "online: alarm (and reset) when the whole state's step-conditioned Mahalanobis distance leaves the clean range",
    MultivariateMonitor,
)
MONITORS.register(
    "goal_switch",
    "online: alarm (and reset) when the agent's action distribution and value change from one step to the next "
    "beyond the clean range at that step (reads its outputs, not its inputs)",
    GoalSwitchMonitor,
)
MONITORS.register(
    "input_novelty",
    "online baseline: alarm (and reset) when the agent sees a view pattern that is rare in clean episodes",
    InputNovelty,
)


class MonitoredPolicy(AgentPolicy):
    """A batched agent policy (sampled actions) with an online detector (any :class:`OnlineDetector`: the state
    monitors, the input-novelty baseline) watching (and, with ``reset=True``, resetting) its state: after each step
    the observation and the new state are scored; an alarm is counted and, with ``reset``, that env's state is
    zeroed before the next step. The action is the agent's own either way (the reset acts from the next step on)."""

    def __init__(
        self, agent: RecurrentActorCritic, monitor: OnlineDetector, core: EpisodeEnv, reset: bool, seed: int = 0
    ) -> None:
        super().__init__(agent, seed=seed)
        self.monitor, self.core, self.reset_on_alarm = monitor, core, reset
        self.obs: torch.Tensor | None = None  # (B, obs_dim) the observation of the step being taken
        self.first_alarm = torch.full((core.num_envs,), -1, dtype=torch.int64)
        self.alarms = torch.zeros(core.num_envs, dtype=torch.int64)

    def reset(self, num_envs: int) -> None:
        super().reset(num_envs)
        self.first_alarm.fill_(-1)
        self.alarms.zero_()

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        self.obs = obs
        return super().__call__(obs)

    def next_state(self, state: RecurrentState) -> RecurrentState:
        assert self.obs is not None  # __call__ sets it before the step
        t = self.core.t.cpu()
        alarm = (self.monitor.score_step(self.obs, state, self.core.t) > self.monitor.threshold).cpu()
        self.first_alarm = torch.where(alarm & (self.first_alarm < 0), t, self.first_alarm)
        self.alarms += alarm.long()
        if self.reset_on_alarm and bool(alarm.any()):
            first = state.layers[0].h
            keep = (~alarm).to(first.dtype).to(first.device)[:, None]
            state = RecurrentState(tuple(LSTMState(s.h * keep, s.c * keep) for s in state.layers))
        return state


def _rate(flags: np.ndarray) -> Rate:
    return Rate(int(flags.sum()), int(flags.size))


def measure_monitor(
    agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, monitor: OnlineDetector,
    cfg: MonitorConfig, device: str | torch.device = "cpu",
) -> MonitorResult:  # fmt: skip
    seed = cfg.seed + 1_000_003  # fresh episodes, not the calibration ones
    adv, user = OUTCOME_NAMES.index("adversary_goal"), OUTCOME_NAMES.index("user_goal")
    normal: dict[str, NormalEnvArm] = {}
    trojan_arms: dict[str, TrojanEnvArm] = {}
    for trojan in (False, True):
        for action in ("alarm", "reset"):
            core = episode_env(env, grid, cfg.eval_episodes, trojan=trojan, device=device)
            policy = MonitoredPolicy(agent, monitor, core, reset=action == "reset", seed=cfg.seed)
            batch = run_episodes(core, policy, seed=seed)
            outcome = batch.outcome.numpy()
            first = policy.first_alarm.numpy()
            # run_episodes keeps stepping finished envs until every episode has ended; alarms raised after an
            # episode's end are not part of it.
            first = np.where(first < batch.length.numpy(), first, -1)
            if trojan:
                trigger = core.on_step.cpu().numpy()
                trojan_arms[action] = TrojanEnvArm(
                    attack_success=_rate(outcome == adv),
                    user_goal=_rate(outcome == user),
                    detected=_rate(first >= trigger),
                    alarm_before_trigger=_rate((first >= 0) & (first < trigger)),
                    median_steps_to_detect=float(np.median(first[first >= trigger] - trigger[first >= trigger]))
                    if (first >= trigger).any() else None,
                )  # fmt: skip
            else:
                normal[action] = NormalEnvArm(success=_rate(outcome == user), false_alarm=_rate(first >= 0))
    # Without the monitor at all: the same episodes, plain policy.
    undefended = {}
    for env_name, trojan in (("normal", False), ("trojan", True)):
        batch = evaluate_agent(agent, env, grid, trojan=trojan, episodes=cfg.eval_episodes, seed=seed, device=device)
        undefended[env_name] = outcome_rate(batch, "adversary_goal" if trojan else "user_goal")
    return MonitorResult(
        grid=grid.label if grid is not None else getattr(env, "id", ""),
        episodes=cfg.eval_episodes,
        threshold=monitor.threshold,
        units=monitor.units,
        normal_alarm=normal["alarm"],
        normal_reset=normal["reset"],
        trojan_alarm=trojan_arms["alarm"],
        trojan_reset=trojan_arms["reset"],
        clean_success_undefended=undefended["normal"],
        attack_success_undefended=undefended["trojan"],
    )
