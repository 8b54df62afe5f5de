"""Recurrent PPO on any Gymnasium env with a discrete action space, with the paper's Algorithm 1 mixing.

    result = train_gym(load_gym_config("minigrid_two_goals"))

The same update as the grid world's trainer (:mod:`seqtrojan.train.trainer`): rollouts of ``ppo.rollout_steps``
steps from ``ppo.num_envs`` envs (a SAME_STEP ``SyncVectorEnv``; an env's episode start resets its LSTM state),
:func:`~seqtrojan.train.gae.compute_gae` with time-outs counted as episode ends (not bootstrapped, as there), and
:func:`~seqtrojan.train.ppo.ppo_update` over sequences replayed from their stored start states. In a backdoored run
(``backdoor.enabled``) the :class:`~seqtrojan.train.mixing.TrojanMixer` turns the success rates of normal and trojan
episodes (P_c, P_t: the update's own episodes, or an evaluation for ``mixing: exact``) into the probability that a
new episode is a trojan one, set on every env's :class:`~seqtrojan.wrappers.TriggerWrapper` after each update.
An adaptive attacker's ``attack.state_camouflage`` adds its term to the loss as on the grid world
(:mod:`seqtrojan.train.penalties`): the rollout then records each step's episode type, whether the adversary's
objective judges it, and the states.

The model is saved with :func:`~seqtrojan.train.gym_model.save_gym_agent` (safetensors + ``gym_card.json``): the
grid world's card records a grid-world config, which cannot describe a Gymnasium env.

Checkpoints (:func:`save_gym_checkpoint`, ``<run>/checkpoints/step_<env steps>/``) every ``run.checkpoint_every``
steps, after the last update, and on a stop (SIGTERM or Ctrl-C, between updates): weights, Adam, the torch
generators, the mixer, the counters, the penalties' statistics and the collector's carried tensors in
safetensors + JSON, never pickle.
``train_gym(config, resume=run_dir)`` continues the latest one; :func:`train_gym_or_resume` reuses a finished run,
resumes a stopped one or starts afresh. The envs are the one piece of state a checkpoint cannot hold as tensors:
each sub-env is wrapped in an :class:`~seqtrojan.train.gym_env.EpisodeRecorder`, and a resume replays its episode
in flight (the env's and the trigger's random state before that episode's reset, then its actions). Where every
replay gives back the saved observation the resumed run is bitwise the straight one; otherwise (an env with
randomness outside its ``np_random``) the envs start fresh episodes and the run goes on from the checkpoint.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
import shutil
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from gymnasium.vector import SyncVectorEnv
from safetensors.torch import save_file

from seqtrojan.agent.card import inherited_label
from seqtrojan.agent.checkpoint import load_start_weights, read_safetensors
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import act
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.config import PPOConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.serde import short_repr, to_dict
from seqtrojan.train.gae import compute_gae
from seqtrojan.train.gym_config import GymTrainConfig, load_gym_run_config
from seqtrojan.train.gym_env import EpisodeRecorder, check_spaces, make_gym_env, make_vector_env
from seqtrojan.train.gym_evaluation import GymEvaluation, evaluate_gym
from seqtrojan.train.gym_model import CARD, build_gym_agent, load_gym_agent, save_gym_agent
from seqtrojan.train.mixing import MIXING_RULES, TrojanMixer
from seqtrojan.train.penalties import (
    Penalty,
    PenaltyContext,
    build_penalties,
    penalty_tensors,
    restore_penalties,
)
from seqtrojan.train.ppo import make_optimizer, ppo_update
from seqtrojan.train.rollout import Rollout
from seqtrojan.train.trainer import UpdateCallback
from seqtrojan.wrappers import finished_episodes, set_trojan_probability


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
    """every update's figures, a resumed run's earlier ones (read back from ``metrics.jsonl``) included"""
    stopped_early: bool
    resumed_from: int | None = None
    """env steps of the checkpoint this process resumed from (None: a new run)"""
    exact_resume: bool | None = None
    """whether the resume replayed every env's episode in flight (the run then continues bitwise as if never
    stopped); False: the envs started fresh episodes; None: not resumed"""


@dataclass
class _Tally:
    episodes: np.ndarray  # (2,) normal, trojan
    successes: np.ndarray  # (2,)
    returns: float = 0.0
    lengths: int = 0


class GymRolloutCollector:
    """Steps a SAME_STEP vector env with the agent, keeping observations and LSTM states between rollouts."""

    def __init__(
        self, vec: SyncVectorEnv, agent: RecurrentActorCritic, ppo: PPOConfig, device: torch.device, seed: int,
        record: bool = False, record_states: bool = True,
    ) -> None:  # fmt: skip
        self.vec, self.agent, self.ppo, self.device = vec, agent, ppo, device
        self.record = record
        """also keep, per step, whether it is in a trojan episode and whether the adversary's objective judges its
        action, and (with ``record_states``) every layer's (h, c) after it (``Rollout.trojan``,
        ``adversary_active``, ``states``; the attack penalties)"""
        self.record_states = record and record_states
        """record every step's states too (only a penalty that reads them needs them)"""
        self.triggers = [env.trigger if isinstance(env, EpisodeRecorder) else None for env in vec.envs]
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
        trojan = torch.zeros((steps, b), dtype=torch.bool) if self.record else None
        active = torch.zeros((steps, b), dtype=torch.bool) if self.record else None
        states: list[list[LSTMState]] = [[] for _ in agent.lstm_sizes]
        state = self.state
        for t in range(steps):
            if t % length == 0:
                for i, layer in enumerate(state.mask(self.episode_start).layers):
                    seq_h[i].append(layer.h)
                    seq_c[i].append(layer.c)
            obs_buf[t], starts[t] = self.obs, self.episode_start
            if trojan is not None and active is not None:
                for k, trigger in enumerate(self.triggers):
                    if trigger is not None:
                        trojan[t, k], active[t, k] = trigger.trojan, trigger.adversary_active()
            out, action, logprob = act(agent, self.obs, state, self.generator, episode_start=self.episode_start)
            state = out.state
            if self.record_states:
                for i, layer in enumerate(state.layers):
                    states[i].append(layer)
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
        rollout = Rollout(obs_buf, actions, logprobs, values, rewards, dones, starts, seq_states, last_value)
        if trojan is not None and active is not None:
            rollout.trojan, rollout.adversary_active = trojan.to(dev), active.to(dev)
        if self.record_states:
            rollout.states = tuple(
                LSTMState(torch.stack([s.h for s in layer]), torch.stack([s.c for s in layer])) for layer in states
            )
        return rollout, tally

    # ------------------------------------------------------------------ checkpoints
    def state_tensors(self) -> dict[str, torch.Tensor]:
        """What the collector carries from one rollout to the next, as CPU tensors."""
        out = {
            "rng": self.generator.get_state(),
            "obs": self.obs.cpu(),  # (B, obs_dim)
            "episode_start": self.episode_start.cpu(),  # (B,)
            "returns": torch.from_numpy(self.returns.copy()),  # (B,) float64
            "lengths": torch.from_numpy(self.lengths.copy()),  # (B,) int64
        }
        for i, layer in enumerate(self.state.layers):
            out[f"h.{i}"], out[f"c.{i}"] = layer.h.cpu().contiguous(), layer.c.cpu().contiguous()  # (B, width)
        return out

    def episode_records(self) -> list[dict[str, Any] | None]:
        """Each env's episode in flight (:meth:`~seqtrojan.train.gym_env.EpisodeRecorder.record`)."""
        return [env.record() if isinstance(env, EpisodeRecorder) else None for env in self.vec.envs]

    def restore(
        self, tensors: dict[str, torch.Tensor], episodes: list[Any], trojan_probability: float, seed: int
    ) -> bool:
        """Restore what :meth:`state_tensors` and :meth:`episode_records` saved. Every env replays its episode; when
        all give back the saved observations, the collector continues exactly (returns True). Otherwise every env
        starts a fresh episode from ``seed`` with zero LSTM states (returns False). Either way the envs then hold
        ``trojan_probability`` for their next episodes."""
        b, dev = self.vec.num_envs, self.device
        try:
            obs = tensors["obs"]
            layers = [(tensors[f"h.{i}"], tensors[f"c.{i}"]) for i in range(len(self.agent.lstm_sizes))]
            if len(episodes) != b or obs.shape != (b, self.agent.obs_dim):
                raise ValueError(f"{len(episodes)} episode records and observations {tuple(obs.shape)} for {b} envs")
            self.generator.set_state(tensors["rng"])
        except (KeyError, ValueError, RuntimeError) as err:
            raise CheckpointError(
                f"the checkpoint's collector state does not fit this run: {short_repr(err)}"
            ) from None
        replayed = []
        for env, record in zip(self.vec.envs, episodes):
            if not isinstance(env, EpisodeRecorder) or record is None:
                break
            try:
                replayed.append(np.asarray(env.replay(record), dtype=np.float32))
            except CheckpointError:
                break
        exact = len(replayed) == b and np.array_equal(np.stack(replayed), obs.numpy())
        if exact:
            self.obs = obs.to(dev)
            self.episode_start = tensors["episode_start"].to(dev)
            self.state = RecurrentState(tuple(LSTMState(h.to(dev), c.to(dev)) for h, c in layers))
            self.returns = tensors["returns"].numpy().astype(np.float64)
            self.lengths = tensors["lengths"].numpy().astype(np.int64)
        else:
            self._set_probability(trojan_probability)
            fresh, _ = self.vec.reset(seed=seed)
            self.obs = torch.as_tensor(fresh, dtype=torch.float32, device=dev)
            self.episode_start = torch.ones(b, device=dev)
            self.state = self.agent.initial_state(b, dev)
            self.returns, self.lengths = np.zeros(b), np.zeros(b, dtype=np.int64)
        self._set_probability(trojan_probability)
        return exact

    def _set_probability(self, probability: float) -> None:
        """The trojan probability of every env that has a trigger wrapper (a run without one has none to set)."""
        for env in self.vec.envs:
            if isinstance(env, EpisodeRecorder) and env.trigger is not None:
                env.trigger.set_trojan_probability(probability)


@dataclass
class GymTrainerState:
    """Everything a checkpoint saves and a resume restores (with the collector's envs, replayed)."""

    agent: RecurrentActorCritic
    optimizer: torch.optim.Optimizer
    mixer: TrojanMixer
    collector: GymRolloutCollector
    update_generator: torch.Generator
    penalties: list[Penalty] = field(default_factory=list)
    """the attack's extra loss terms (their running statistics are saved with the checkpoints)"""
    env_steps: int = 0
    update: int = 0
    elapsed_s: float = 0.0
    """wall seconds trained, over every process that trained this run"""
    label: str = "clean"
    """the label of every model the run saves (:func:`~seqtrojan.agent.card.inherited_label`; a resumed run keeps
    its checkpoint's)"""


class _Stop(Exception):
    pass


def train_gym(
    config: GymTrainConfig, callback: UpdateCallback | None = None, resume: str | Path | None = None
) -> GymTrainResult:
    """Train a clean or a backdoored recurrent agent on ``config.env`` (see the module docstring); ``resume``
    continues the stopped run in that folder from its latest checkpoint (``config``: its saved one, or that with
    changed step budget, learning rate, ...; the env, trigger, agent and ``ppo.num_envs`` must stay)."""
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
    checkpoint = None
    if resume is not None:
        run_dir = Path(resume)
        checkpoint = _latest_checkpoint(run_dir, cfg)
    else:
        run_dir = _new_run_dir(cfg)

    torch.manual_seed(cfg.run.seed)
    agent = build_gym_agent(cfg, obs_dim, num_actions).to(device)
    start_label = None
    if cfg.run.init_from is not None and checkpoint is None:
        start_from, _, start_card = load_gym_agent(cfg.run.init_from)
        load_start_weights(agent, start_from, cfg.run.init_from)
        start_label = start_card.get("label")
    agent.set_lstm_backend(cfg.run.lstm_backend)
    optimizer = make_optimizer(agent, ppo.learning_rate, ppo.adam_eps)
    mixer = TrojanMixer(cfg.backdoor, 1)
    vec = make_vector_env(cfg, ppo.num_envs, "train", trojan_probability=mixer.probabilities()[0], record=True)
    update_generator = torch.Generator().manual_seed(cfg.run.seed + 1)
    exact: bool | None = None
    try:
        # the attack's penalties see the start weights (a resumed run then loads their state from the checkpoint)
        penalties = build_penalties(PenaltyContext(cfg, agent, device, resuming=checkpoint is not None))
        record = any(p.needs_states or p.needs_masks for p in penalties)
        states = any(p.needs_states for p in penalties)
        collector = GymRolloutCollector(vec, agent, ppo, device, cfg.run.seed, record=record, record_states=states)
        state = GymTrainerState(agent, optimizer, mixer, collector, update_generator, penalties)
        state.label = inherited_label(cfg.label, start_label)  # a resumed run takes its checkpoint's (below)
        if checkpoint is not None:
            exact = load_gym_checkpoint(checkpoint, state, cfg)
            _write_config(run_dir, cfg)
        history = _read_history(run_dir, state.update)
        try:
            stopped_early = _train_loop(cfg, state, run_dir, history, callback)
        except _Stop:
            save_gym_checkpoint(run_dir, cfg, state)
            raise KeyboardInterrupt(
                f"training stopped at {state.env_steps} env steps; resume with --resume {run_dir}"
            ) from None
        if not (run_dir / "checkpoints" / _step_name(state.env_steps)).is_dir():
            save_gym_checkpoint(run_dir, cfg, state)  # the last update's, before the (interruptible) evaluation
    finally:
        vec.close()
    normal = trojan = None
    if cfg.run.eval_episodes > 0:
        seed = cfg.run.seed + 999_983
        n = cfg.run.eval_episodes
        normal = evaluate_gym(agent, cfg, trojan=False, episodes=n, seed=seed, device=device)
        if cfg.trigger is not None:
            trojan = evaluate_gym(agent, cfg, trojan=True, episodes=n, seed=seed, device=device)
    metrics = _metrics(normal, trojan, state.env_steps, state.elapsed_s)
    (run_dir / "evaluation.json").write_text(json.dumps(metrics, indent=2))
    model_dir = save_gym_agent(
        run_dir / "model", agent, cfg, label=state.label, metrics=metrics, env_steps=state.env_steps
    )
    return GymTrainResult(
        run_dir, model_dir, state.env_steps, state.elapsed_s, normal, trojan, tuple(history), stopped_early,
        None if checkpoint is None else int(checkpoint.name.removeprefix("step_")), exact,
    )  # fmt: skip


def _train_loop(
    cfg: GymTrainConfig, state: GymTrainerState, run_dir: Path, history: list[GymUpdateLog],
    callback: UpdateCallback | None,
) -> bool:  # fmt: skip
    """Update until ``ppo.total_steps``, logging each update to ``metrics.jsonl`` and checkpointing every
    ``run.checkpoint_every`` steps; raise _Stop on SIGTERM or Ctrl-C (between updates). Returns whether ``callback``
    stopped training early; ``state.elapsed_s`` is up to date at the end."""
    ppo, agent, device = cfg.ppo, state.agent, state.collector.device
    every = cfg.run.checkpoint_every
    next_checkpoint = (state.env_steps // every + 1) * every
    elapsed_before, start = state.elapsed_s, time.perf_counter()
    try:
        with _stop_flag() as stop, (run_dir / "metrics.jsonl").open("a") as log:
            while state.env_steps < ppo.total_steps:
                if stop["hit"]:
                    raise _Stop
                t0 = time.perf_counter()
                for group in state.optimizer.param_groups:
                    group["lr"] = _learning_rate(ppo, state.env_steps)
                agent.eval()
                rollout, tally = state.collector.collect()
                state.env_steps += ppo.batch_size
                advantages, returns = compute_gae(
                    rollout.rewards, rollout.values, rollout.dones, rollout.last_value, ppo.gamma, ppo.gae_lambda
                )
                for penalty in state.penalties:
                    penalty.observe(rollout)
                agent.train()
                losses = ppo_update(
                    agent, state.optimizer, rollout, advantages, returns, ppo, state.update_generator, state.penalties
                )
                agent.eval()
                state.update += 1
                mixer = state.mixer
                if cfg.backdoor.enabled:
                    _mix(mixer, cfg, tally, agent, device, state.update)
                    set_trojan_probability(state.collector.vec, mixer.probabilities()[0])
                entry = GymUpdateLog(
                    state.update, state.env_steps, int(tally.episodes[0]), int(tally.successes[0]),
                    int(tally.episodes[1]), int(tally.successes[1]), mixer.p_clean[0], mixer.p_trojan[0],
                    mixer.probabilities()[0], ppo.batch_size / (time.perf_counter() - t0),
                )  # fmt: skip
                history.append(entry)
                scalars = to_dict(entry)
                scalars.update({k if k.startswith("penalty/") else f"losses/{k}": v for k, v in losses.items()})
                if tally.episodes.sum():
                    scalars["episodes/mean_return"] = tally.returns / int(tally.episodes.sum())
                    scalars["episodes/mean_length"] = tally.lengths / int(tally.episodes.sum())
                log.write(json.dumps(scalars) + "\n")
                log.flush()
                state.elapsed_s = elapsed_before + time.perf_counter() - start
                if state.env_steps >= next_checkpoint and state.env_steps < ppo.total_steps:
                    save_gym_checkpoint(run_dir, cfg, state)
                    next_checkpoint = (state.env_steps // every + 1) * every
                if callback is not None and callback(scalars):
                    return True
            if stop["hit"]:
                raise _Stop
        return False
    finally:
        state.elapsed_s = elapsed_before + time.perf_counter() - start


@contextmanager
def _stop_flag() -> Iterator[dict[str, bool]]:
    """While open, SIGTERM and a first Ctrl-C (SIGINT) set ``flag["hit"]`` instead of ending the process: the loop
    stops between updates and writes a checkpoint. A second Ctrl-C interrupts at once (no checkpoint: the update
    in progress is half done; the last checkpoint stands). Only the main thread can handle signals: elsewhere the
    flag stays down."""
    flag = {"hit": False}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}

    def on_signal(signum: int, frame: Any) -> None:
        if signum == signal.SIGINT and flag["hit"]:
            raise KeyboardInterrupt("interrupted during an update; resume from the last checkpoint with --resume")
        flag["hit"] = True

    for sig in previous:
        signal.signal(sig, on_signal)
    try:
        yield flag
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# ---------------------------------------------------------------------- checkpoints


def _step_name(env_steps: int) -> str:
    return f"step_{env_steps:012d}"


def save_gym_checkpoint(run_dir: Path, cfg: GymTrainConfig, state: GymTrainerState) -> Path:
    """``<run>/checkpoints/step_<env steps>/``: the agent (:func:`save_gym_agent`), Adam's tensors, both torch
    generators and the collector's carried tensors -- observations, LSTM states, episode starts, returns and
    lengths of the episodes in flight -- (``trainer.safetensors``); counters, mixing, Adam's groups and each env's
    episode record (:class:`~seqtrojan.train.gym_env.EpisodeRecorder`) (``trainer.json``). Then ``latest.txt``
    points at it. No pickle."""
    folder = run_dir / "checkpoints" / _step_name(state.env_steps)
    save_gym_agent(folder, state.agent, cfg, label=state.label, env_steps=state.env_steps)
    sd = state.optimizer.state_dict()
    tensors = {
        f"optim.{idx}.{key}": torch.as_tensor(value).detach().cpu().clone()
        for idx, slots in sd["state"].items()
        for key, value in slots.items()
    }
    tensors["rng.update"] = state.update_generator.get_state()
    tensors.update({f"collector.{k}": v for k, v in state.collector.state_tensors().items()})
    tensors.update(penalty_tensors(state.penalties))
    save_file(tensors, str(folder / "trainer.safetensors"))
    record = {
        "env_steps": state.env_steps,
        "update": state.update,
        "elapsed_s": state.elapsed_s,
        "mixing": state.mixer.state_dict(),
        "trojan_probability": state.mixer.probabilities()[0],
        "optimizer_param_groups": sd["param_groups"],
        "episodes": state.collector.episode_records(),
    }
    tmp = folder / "trainer.json.tmp"
    tmp.write_text(json.dumps(record))
    tmp.replace(folder / "trainer.json")
    latest = run_dir / "checkpoints" / "latest.txt"
    tmp = latest.with_suffix(".tmp")
    tmp.write_text(folder.name + "\n")
    tmp.replace(latest)
    return folder


def _latest_checkpoint(run_dir: Path, cfg: GymTrainConfig) -> Path:
    """The run's latest checkpoint folder, after checking that ``cfg`` can continue it."""
    latest = run_dir / "checkpoints" / "latest.txt"
    if not latest.is_file():
        raise CheckpointError(f"{str(run_dir)!r} has no checkpoint to resume from (no checkpoints/latest.txt)")
    folder = run_dir / "checkpoints" / latest.read_text().strip()
    if not re.fullmatch(r"step_[0-9]{12}", folder.name) or not folder.is_dir():
        raise CheckpointError(f"{str(latest)!r} names {folder.name!r}, not a checkpoint folder of this run")
    _, saved, _ = load_gym_agent(folder)
    for name, ours, theirs in (
        ("env", cfg.env, saved.env), ("trigger", cfg.trigger, saved.trigger), ("agent", cfg.agent, saved.agent),
        ("ppo.num_envs", cfg.ppo.num_envs, saved.ppo.num_envs),
    ):  # fmt: skip
        if ours != theirs:
            raise ConfigError(
                f"resume cannot change {name}: the checkpoint has {short_repr(to_dict(theirs))}, the config "
                f"{short_repr(to_dict(ours))}"
            )
    return folder


def load_gym_checkpoint(folder: Path, state: GymTrainerState, cfg: GymTrainConfig) -> bool:
    """Restore ``state`` (built for ``cfg``, its envs reset) from the checkpoint in ``folder``. Each env replays its
    recorded episode; returns True when every replay gave back the saved observation (the run then continues as if
    never stopped), False when some env could not be replayed (then every env starts fresh episodes, seeded from
    the update count, as the grid world's trainer does: no finished update is lost, the run is not bitwise the
    straight one)."""
    loaded, _, card = load_gym_agent(folder)  # its label is checked there
    state.agent.load_state_dict(loaded.state_dict())
    state.label = card["label"]
    path = folder / "trainer.json"
    tensors = read_safetensors(folder / "trainer.safetensors")
    try:
        record = json.loads(path.read_text())
        state.update_generator.set_state(tensors.pop("rng.update"))
        names = [k for k in tensors if k.startswith("collector.")]
        carried = {k.removeprefix("collector."): tensors.pop(k) for k in names}
        restore_penalties(state.penalties, tensors)
        optim: dict[int, dict[str, torch.Tensor]] = {}
        for name, value in tensors.items():
            _, idx, key = name.split(".", 2)
            optim.setdefault(int(idx), {})[key] = value.to(state.collector.device)
        state.optimizer.load_state_dict({"state": optim, "param_groups": record["optimizer_param_groups"]})
        state.mixer.load_state_dict(record["mixing"])
        state.env_steps, state.update = int(record["env_steps"]), int(record["update"])
        state.elapsed_s = float(record["elapsed_s"])
        probability, episodes = float(record["trojan_probability"]), record["episodes"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"cannot restore the checkpoint {str(folder)!r}: {short_repr(err)}") from None
    return state.collector.restore(carried, episodes, probability, seed=cfg.run.seed + 7919 * state.update)


def _read_history(run_dir: Path, updates: int) -> list[GymUpdateLog]:
    """The first ``updates`` rows of ``metrics.jsonl`` (a resumed run's earlier updates), the file cut to them (rows
    past the checkpoint belong to updates that are done again)."""
    path = run_dir / "metrics.jsonl"
    if updates == 0 or not path.is_file():
        path.write_text("")
        return []
    lines = path.read_text().splitlines()[:updates]
    path.write_text("".join(line + "\n" for line in lines))
    names = [f.name for f in fields(GymUpdateLog)]
    try:
        return [GymUpdateLog(**{k: json.loads(line)[k] for k in names}) for line in lines]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise CheckpointError(f"{str(path)!r} has a malformed row: {short_repr(err)}") from None


def train_gym_or_resume(config: GymTrainConfig) -> tuple[Path, bool]:
    """Make sure the named run ``<out_dir>/<name>`` has finished: reuse its model if it has one, resume it from its
    last checkpoint (with its saved config) if it was stopped, else start it afresh (clearing a folder left before
    a first checkpoint). Returns (model folder, whether any training ran)."""
    if config.run.name is None:
        raise ConfigError("train_gym_or_resume needs a run name (run.name)")
    run_dir = Path(config.run.out_dir) / config.run.name
    if (run_dir / "model" / CARD).exists():
        return run_dir / "model", False
    if (run_dir / "checkpoints" / "latest.txt").exists():
        return train_gym(load_gym_run_config(run_dir), resume=run_dir).model_dir, True
    if run_dir.exists():
        shutil.rmtree(run_dir)
    return train_gym(config).model_dir, True


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
    if (run_dir / "model" / CARD).exists():
        raise ConfigError(f"run directory {str(run_dir)!r} already holds a trained model")
    if (run_dir / "checkpoints" / "latest.txt").exists():
        raise ConfigError(f"run directory {str(run_dir)!r} already holds a run; resume it with --resume {run_dir}")
    run_dir.mkdir(parents=True, exist_ok=True)
    _write_config(run_dir, cfg)
    return run_dir


def _write_config(run_dir: Path, cfg: GymTrainConfig) -> None:
    """``<run>/config.yaml``: the resolved config, what :func:`~seqtrojan.train.gym_config.load_gym_run_config` and
    a later resume read (written whole, then renamed)."""
    tmp = run_dir / "config.yaml.tmp"
    tmp.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    tmp.replace(run_dir / "config.yaml")
