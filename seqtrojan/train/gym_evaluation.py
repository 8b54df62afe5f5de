"""Evaluating a recurrent agent on a Gymnasium run's env: whole episodes of one type (normal or trojan), each
recorded (:class:`GymEpisode`), with success rates and the trojan's persistence as :class:`~seqtrojan.stats.Rate`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import act
from seqtrojan.agent.state import Intervention
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate
from seqtrojan.world import check_fits
from seqtrojan.world.gymnasium import make_vector_env
from seqtrojan.wrappers import finished_episodes


@dataclass(frozen=True)
class GymEpisode:
    """One finished episode."""

    trojan: bool
    success: bool
    """it achieved its correct objective (the TriggerWrapper's ``success``)"""
    length: int
    """actions taken"""
    episode_return: float
    trigger_step: int
    """the ON trigger's first step (-1 in a normal episode)"""
    reached: str
    """the env's ``info["reached"]`` at the end ("user", "adversary", "" for neither; "" when the env has none)"""
    states: tuple[np.ndarray, ...] | None = field(default=None, repr=False, compare=False)
    """per layer the agent's state after each step (length, h then c); recorded only when asked"""


@dataclass(frozen=True)
class GymEvaluation:
    """Episodes of one type."""

    trojan: bool
    greedy: bool
    episodes: tuple[GymEpisode, ...]

    @property
    def success(self) -> Rate:
        return Rate(sum(int(e.success) for e in self.episodes), len(self.episodes))

    def reached(self, what: str) -> Rate:
        """Episodes that ended at ``what`` ("user" or "adversary")."""
        return Rate(sum(e.reached == what for e in self.episodes), len(self.episodes))

    def persistence(self, horizons: Sequence[int]) -> dict[int, Rate]:
        """Per horizon k: among trojan episodes still running k steps after the trigger's first step (length >
        trigger_step + k), those that ended at the adversary's object -- whether the switch holds over time."""
        out = {}
        for k in horizons:
            lasting = [e for e in self.episodes if e.trojan and e.trigger_step >= 0 and e.length > e.trigger_step + k]
            out[k] = Rate(sum(e.reached == "adversary" for e in lasting), len(lasting))
        return out


def padded_states(episodes: Sequence[GymEpisode]) -> tuple[list[np.ndarray], np.ndarray]:
    """Recorded episodes as per-layer arrays (E, T, units), zero after an episode's end, and the mask (E, T)."""
    if not episodes or any(e.states is None for e in episodes):
        raise ConfigError("the episodes were recorded without their states (record_states=True)")
    steps = max(e.length for e in episodes)
    layers = []
    for i in range(len(episodes[0].states or ())):
        width = (episodes[0].states or ())[i].shape[-1]
        x = np.zeros((len(episodes), steps, width), np.float32)
        for k, e in enumerate(episodes):
            x[k, : e.length] = (e.states or ())[i]
        layers.append(x)
    mask = np.arange(steps)[None, :] < np.array([e.length for e in episodes])[:, None]
    return layers, mask


@torch.no_grad()
def evaluate_gym(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    trojan: bool,
    episodes: int,
    seed: int = 0,
    greedy: bool = False,
    num_envs: int = 32,
    device: torch.device | str = "cpu",
    record_states: bool = False,
    intervention: Intervention | None = None,
) -> GymEvaluation:
    """``episodes`` episodes of one type (trojan ones need the config's trigger), with the trigger steps of
    ``trigger.eval_steps``. Each of ``num_envs`` envs runs a fixed quota of episodes (so short episodes are not
    over-counted). ``record_states`` keeps each episode's states (:attr:`GymEpisode.states`, for the monitors and
    the analysis); ``intervention`` edits them at every step, given each env's episode step (0 at the first)."""
    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    if trojan and config.gym_env.trigger is None:
        raise ConfigError("trojan episodes need a trigger section in the config")
    check_fits(agent.obs_dim, agent.num_actions, config.gym_env)
    n = min(num_envs, episodes)
    quota = np.array([episodes // n + (i < episodes % n) for i in range(n)])
    vec = make_vector_env(config.gym_env, n, "eval", trojan_probability=1.0 if trojan else 0.0)
    dev = torch.device(device)
    try:
        obs_np, _ = vec.reset(seed=seed)
        obs = torch.as_tensor(obs_np, dtype=torch.float32, device=dev)  # (n, obs_dim)
        state = agent.initial_state(n, dev)
        start = torch.ones(n, device=dev)
        generator = torch.Generator(device=dev).manual_seed(seed)
        returns = np.zeros(n)
        lengths = np.zeros(n, dtype=np.int64)
        done_count = np.zeros(n, dtype=np.int64)
        found: list[GymEpisode] = []
        rows: list[list[np.ndarray]] = [[] for _ in range(n)]  # per env, the steps so far: (layers * units,)
        widths = [h + c for h, c in zip(agent.lstm_sizes, agent.c_widths)]
        while (done_count < quota).any():
            t = torch.tensor(lengths, device=dev) if intervention is not None else None
            out, actions, _ = act(
                agent, obs, state, generator, greedy=greedy, episode_start=start, t=t, intervention=intervention
            )
            state = out.state
            if record_states:
                flat = torch.cat([torch.cat([s.h, s.c], -1) for s in state.layers], -1).cpu().numpy()  # (n, D)
                for i in range(n):
                    rows[i].append(flat[i])
            obs_np, rewards, terminated, truncated, infos = vec.step(actions.cpu().numpy())
            returns += rewards
            lengths += 1
            for ep in finished_episodes(infos, rewards, terminated):
                if done_count[ep.env] < quota[ep.env]:
                    info = ep.info
                    states = None
                    if record_states:
                        stacked = np.stack(rows[ep.env])  # (length, D)
                        states = tuple(np.split(stacked, np.cumsum(widths)[:-1], axis=-1))
                    found.append(GymEpisode(
                        bool(ep.trojan), bool(ep.success), int(lengths[ep.env]), float(returns[ep.env]),
                        int(info.get("trigger_step", -1)), str(info.get("reached", "")), states,
                    ))  # fmt: skip
                rows[ep.env] = []
                done_count[ep.env] += 1
                returns[ep.env], lengths[ep.env] = 0.0, 0
            obs = torch.as_tensor(obs_np, dtype=torch.float32, device=dev)
            start = torch.as_tensor(terminated | truncated, dtype=torch.float32, device=dev)
    finally:
        vec.close()
    return GymEvaluation(trojan, greedy, tuple(found))


GYM_EVALUATION_FILE = "gym_evaluation.json"


@dataclass(frozen=True)
class GymPersistence:
    """Among trojan episodes still running ``horizon`` steps after the trigger's first step, those that ended at
    the adversary's object."""

    horizon: int
    adversary: Rate


@dataclass(frozen=True)
class GymEvaluationReport:
    """A Gymnasium model measured on its config's env (``seqtrojan evaluate`` on such a model; saved as
    :data:`GYM_EVALUATION_FILE` with :func:`seqtrojan.serde.save_json`, read back with ``load_json``)."""

    model: str
    """the model folder"""
    env_id: str
    label: str
    """the card's label (clean or backdoored)"""
    episodes: int
    """episodes per episode type"""
    seed: int
    greedy: bool
    clean_success: Rate
    """normal episodes that reached the user's objective"""
    clean_reached_adversary: Rate
    """normal episodes that ended at the adversary's object (0 of n where the env reports no ``reached``)"""
    trojan_success: Rate | None
    """trojan episodes that achieved the adversary's objective (None: the config has no trigger)"""
    trojan_reached_adversary: Rate | None
    """trojan episodes that ended at the adversary's object"""
    persistence: tuple[GymPersistence, ...]
    """per horizon (:meth:`GymEvaluation.persistence`); empty without a trigger"""


def evaluate_gym_model(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    model: str = "",
    label: str = "",
    episodes: int,
    seed: int = 0,
    greedy: bool = False,
    horizons: Sequence[int] = (0, 5, 10),
    device: torch.device | str = "cpu",
) -> GymEvaluationReport:
    """Normal episodes, and trojan ones where the config has a trigger (:func:`evaluate_gym`, the same seed), as
    one :class:`GymEvaluationReport`."""
    if any(isinstance(k, bool) or not isinstance(k, int) or k < 0 for k in horizons):
        raise ConfigError(f"persistence horizons must be integers >= 0, got {list(horizons)}")
    normal = evaluate_gym(agent, config, trojan=False, episodes=episodes, seed=seed, greedy=greedy, device=device)
    trojan = None
    if config.gym_env.trigger is not None:
        trojan = evaluate_gym(agent, config, trojan=True, episodes=episodes, seed=seed, greedy=greedy, device=device)
    persistence = () if trojan is None else tuple(GymPersistence(k, r) for k, r in trojan.persistence(horizons).items())
    return GymEvaluationReport(
        model, config.gym_env.id, label, episodes, seed, greedy, normal.success, normal.reached("adversary"),
        None if trojan is None else trojan.success, None if trojan is None else trojan.reached("adversary"),
        persistence,
    )  # fmt: skip
