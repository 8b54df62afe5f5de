"""Recurrent PPO on any Gymnasium env with a discrete action space, with the paper's Algorithm 1 mixing.

    result = train_gym(load_gym_config("minigrid_two_goals"))

The same update as the grid world's trainer (:mod:`seqtrojan.train.trainer`): rollouts of ``ppo.rollout_steps``
steps from ``ppo.num_envs`` envs (a SAME_STEP ``SyncVectorEnv``; an env's episode start resets its LSTM state),
:func:`~seqtrojan.train.gae.compute_gae` with time-outs counted as episode ends (not bootstrapped, as there), and
:func:`~seqtrojan.train.ppo.ppo_update` over sequences replayed from their stored start states. In a backdoored run
(``backdoor.enabled``) the :class:`~seqtrojan.train.mixing.TrojanMixer` turns the success rates of normal and trojan
episodes (P_c, P_t: the update's own episodes, or an evaluation for ``mixing: exact``) into the probability that a
new episode is a trojan one, set on every env's :class:`~seqtrojan.wrappers.TriggerWrapper` after each update.

The model is saved with :func:`~seqtrojan.train.gym_model.save_gym_agent` (safetensors + ``gym_card.json``): the
grid world's card records a grid-world config, which cannot describe a Gymnasium env. No checkpoints or resume.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from gymnasium.vector import SyncVectorEnv

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import act
from seqtrojan.agent.state import LSTMState
from seqtrojan.config import PPOConfig
from seqtrojan.errors import ConfigError
from seqtrojan.serde import to_dict
from seqtrojan.train.gae import compute_gae
from seqtrojan.train.gym_config import GymTrainConfig
from seqtrojan.train.gym_env import check_spaces, make_gym_env, make_vector_env
from seqtrojan.train.gym_evaluation import GymEvaluation, evaluate_gym
from seqtrojan.train.gym_model import build_gym_agent, save_gym_agent
from seqtrojan.train.mixing import MIXING_RULES, TrojanMixer
from seqtrojan.train.ppo import ppo_update
from seqtrojan.train.rollout import Rollout
from seqtrojan.wrappers import finished_episodes, set_trojan_probability

UpdateCallback = Callable[[dict[str, Any]], bool]
"""Called after every update with its scalars; returning True stops training (benchmarks use it)."""


@dataclass(frozen=True)
class GymUpdateLog:
    """One update's figures."""

    update: int
    env_steps: int
    normal_episodes: int
    normal_successes: int
    trojan_episodes: int
    trojan_successes: int
    p_clean: float
    """P_c the mixer holds after the update"""
    p_trojan: float
    """P_t the mixer holds after the update"""
    trojan_probability: float
    """the probability set on the envs for the next episodes"""
    steps_per_second: float


@dataclass(frozen=True)
class GymTrainResult:
    run_dir: Path
    model_dir: Path
    env_steps: int
    wall_seconds: float
    normal: GymEvaluation | None
    """final evaluation on normal episodes (None when run.eval_episodes is 0)"""
    trojan: GymEvaluation | None
    """final evaluation on trojan episodes (None without a trigger, or when run.eval_episodes is 0)"""
    history: tuple[GymUpdateLog, ...]
    stopped_early: bool


@dataclass
class _Tally:
    episodes: np.ndarray  # (2,) normal, trojan
    successes: np.ndarray  # (2,)
    returns: float = 0.0
    lengths: int = 0


class GymRolloutCollector:
    """Steps a SAME_STEP vector env with the agent, keeping observations and LSTM states between rollouts."""

    def __init__(
        self, vec: SyncVectorEnv, agent: RecurrentActorCritic, ppo: PPOConfig, device: torch.device, seed: int
    ) -> None:
        self.vec, self.agent, self.ppo, self.device = vec, agent, ppo, device
        b = vec.num_envs
        obs, _ = vec.reset(seed=seed)
        self.obs = torch.as_tensor(obs, dtype=torch.float32, device=device)  # (B, obs_dim)
        self.episode_start = torch.ones(b, device=device)
        self.state = agent.initial_state(b, device)
        self.generator = torch.Generator(device=device).manual_seed(seed)
        self.returns = np.zeros(b)
        self.lengths = np.zeros(b, dtype=np.int64)

    @torch.no_grad()
    def collect(self) -> tuple[Rollout, _Tally]:
        agent, steps, length, b, dev = (
            self.agent,
            self.ppo.rollout_steps,
            self.ppo.sequence_length,
            self.vec.num_envs,
            self.device,
        )
        obs_buf = torch.empty((steps, b, agent.obs_dim), device=dev)
        actions = torch.empty((steps, b), dtype=torch.int64, device=dev)
        logprobs = torch.empty((steps, b), device=dev)
        values = torch.empty((steps, b), device=dev)
        rewards = torch.empty((steps, b), device=dev)
        dones = torch.empty((steps, b), device=dev)
        starts = torch.empty((steps, b), device=dev)
        seq_h: list[list[torch.Tensor]] = [[] for _ in agent.lstm_sizes]
        seq_c: list[list[torch.Tensor]] = [[] for _ in agent.lstm_sizes]
        tally = _Tally(np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64))
        state = self.state
        for t in range(steps):
            if t % length == 0:
                for i, layer in enumerate(state.mask(self.episode_start).layers):
                    seq_h[i].append(layer.h)
                    seq_c[i].append(layer.c)
            obs_buf[t], starts[t] = self.obs, self.episode_start
            out, action, logprob = act(agent, self.obs, state, self.generator, episode_start=self.episode_start)
            state = out.state
            obs, reward, terminated, truncated, infos = self.vec.step(action.cpu().numpy())
            done = terminated | truncated
            actions[t], logprobs[t], values[t] = action, logprob, out.value
            rewards[t] = torch.as_tensor(reward, dtype=torch.float32, device=dev)
            dones[t] = torch.as_tensor(done, dtype=torch.float32, device=dev)
            self.returns += reward
            self.lengths += 1
            for ep in finished_episodes(infos, reward, terminated):
                kind = int(ep.trojan)
                tally.episodes[kind] += 1
                tally.successes[kind] += int(ep.success)
                tally.returns += float(self.returns[ep.env])
                tally.lengths += int(self.lengths[ep.env])
            self.returns[done] = 0.0
            self.lengths[done] = 0
            self.obs = torch.as_tensor(obs, dtype=torch.float32, device=dev)
            self.episode_start = dones[t].clone()
        last_value = agent.step(self.obs, state, self.episode_start).value
        self.state = state
        seq_states = tuple(LSTMState(torch.stack(h), torch.stack(c)) for h, c in zip(seq_h, seq_c))
        return Rollout(obs_buf, actions, logprobs, values, rewards, dones, starts, seq_states, last_value), tally


def train_gym(config: GymTrainConfig, callback: UpdateCallback | None = None) -> GymTrainResult:
    """Train a clean or a backdoored recurrent agent on ``config.env`` (see the module docstring)."""
    cfg, ppo = config, config.ppo
    MIXING_RULES.get(cfg.backdoor.mixing)  # an unknown rule is refused before anything is built
    probe = make_gym_env(cfg)
    try:
        obs_dim, num_actions = check_spaces(probe, cfg.env.id)
    finally:
        probe.close()
    device = torch.device(cfg.run.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"run.device={cfg.run.device!r} but no CUDA device is available")
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)
    run_dir = _new_run_dir(cfg)

    torch.manual_seed(cfg.run.seed)
    agent = build_gym_agent(cfg, obs_dim, num_actions).to(device)
    agent.set_lstm_backend(cfg.run.lstm_backend)
    optimizer = torch.optim.Adam(agent.parameters(), lr=ppo.learning_rate, eps=ppo.adam_eps)
    mixer = TrojanMixer(cfg.backdoor, 1)
    vec = make_vector_env(cfg, ppo.num_envs, "train", trojan_probability=mixer.probabilities()[0])
    update_generator = torch.Generator().manual_seed(cfg.run.seed + 1)
    history: list[GymUpdateLog] = []
    env_steps, update, stopped_early = 0, 0, False
    start = time.perf_counter()
    try:
        collector = GymRolloutCollector(vec, agent, ppo, device, cfg.run.seed)
        with (run_dir / "metrics.jsonl").open("w") as log:
            while env_steps < ppo.total_steps:
                t0 = time.perf_counter()
                for group in optimizer.param_groups:
                    group["lr"] = _learning_rate(ppo, env_steps)
                agent.eval()
                rollout, tally = collector.collect()
                env_steps += ppo.batch_size
                advantages, returns = compute_gae(
                    rollout.rewards, rollout.values, rollout.dones, rollout.last_value, ppo.gamma, ppo.gae_lambda
                )
                agent.train()
                losses = ppo_update(agent, optimizer, rollout, advantages, returns, ppo, update_generator)
                agent.eval()
                update += 1
                if cfg.backdoor.enabled:
                    _mix(mixer, cfg, tally, agent, device, update)
                    set_trojan_probability(vec, mixer.probabilities()[0])
                entry = GymUpdateLog(
                    update, env_steps, int(tally.episodes[0]), int(tally.successes[0]), int(tally.episodes[1]),
                    int(tally.successes[1]), mixer.p_clean[0], mixer.p_trojan[0], mixer.probabilities()[0],
                    ppo.batch_size / (time.perf_counter() - t0),
                )  # fmt: skip
                history.append(entry)
                scalars = {**to_dict(entry), **{f"losses/{k}": v for k, v in losses.items()}}
                if tally.episodes.sum():
                    scalars["episodes/mean_return"] = tally.returns / int(tally.episodes.sum())
                    scalars["episodes/mean_length"] = tally.lengths / int(tally.episodes.sum())
                log.write(json.dumps(scalars) + "\n")
                log.flush()
                if callback is not None and callback(scalars):
                    stopped_early = True
                    break
    finally:
        vec.close()
    wall = time.perf_counter() - start
    normal = trojan = None
    if cfg.run.eval_episodes > 0:
        seed = cfg.run.seed + 999_983
        n = cfg.run.eval_episodes
        normal = evaluate_gym(agent, cfg, trojan=False, episodes=n, seed=seed, device=device)
        if cfg.trigger is not None:
            trojan = evaluate_gym(agent, cfg, trojan=True, episodes=n, seed=seed, device=device)
    metrics = _metrics(normal, trojan, env_steps, wall)
    (run_dir / "evaluation.json").write_text(json.dumps(metrics, indent=2))
    model_dir = save_gym_agent(run_dir / "model", agent, cfg, metrics=metrics, env_steps=env_steps)
    return GymTrainResult(run_dir, model_dir, env_steps, wall, normal, trojan, tuple(history), stopped_early)


def _mix(
    mixer: TrojanMixer, cfg: GymTrainConfig, tally: _Tally, agent: RecurrentActorCritic, device: torch.device,
    update: int,
) -> None:  # fmt: skip
    """Refresh P_c and P_t: from the update's episodes, or (a rule that evaluates) from fresh episodes."""
    rates = [int(tally.successes[k]) / int(tally.episodes[k]) if tally.episodes[k] else None for k in (0, 1)]
    mixer.observe(0, *rates)
    if mixer.rule.evaluates:
        seed = cfg.run.seed + 1_000_003 * update
        n = cfg.backdoor.eval_episodes
        p_c = evaluate_gym(agent, cfg, trojan=False, episodes=n, seed=seed, device=device).success.value
        p_t = evaluate_gym(agent, cfg, trojan=True, episodes=n, seed=seed, device=device).success.value
        mixer.observe(0, p_c, p_t)


def _metrics(normal: GymEvaluation | None, trojan: GymEvaluation | None, steps: int, wall: float) -> dict[str, Any]:
    """The card's flat metrics (as the grid world's: ``normal_success``, ``normal_success_ci95``, ...)."""
    out: dict[str, Any] = {"env_steps": steps, "train_seconds": wall}
    for name, ev in (("normal", normal), ("trojan", trojan)):
        if ev is not None:
            out[f"{name}_success"] = ev.success.value
            out[f"{name}_success_ci95"] = list(ev.success.interval)
            out[f"{name}_episodes"] = ev.success.n
    return out


def _learning_rate(ppo: PPOConfig, step: int) -> float:
    frac = min(1.0, step / ppo.total_steps)
    if ppo.lr_schedule == "linear":
        return ppo.learning_rate * max(1.0 - frac, 0.02)
    if ppo.lr_schedule == "cosine":
        return ppo.learning_rate * (0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * frac)))
    return ppo.learning_rate


def _new_run_dir(cfg: GymTrainConfig) -> Path:
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", cfg.env.id).strip("_")
    name = cfg.run.name or f"{slug}_s{cfg.run.seed}_{_dt.datetime.now():%Y%m%d-%H%M%S}"
    run_dir = Path(cfg.run.out_dir) / name
    if (run_dir / "model" / "gym_card.json").exists():
        raise ConfigError(f"run directory {str(run_dir)!r} already holds a trained model")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return run_dir
