"""Rollout storage and collection: T steps of B envs, with the LSTM state kept at every sequence start.

Not the episode loop of :mod:`seqtrojan.env.rollout` (which runs one episode per env to its end): here a fixed
number of steps with autoreset. Each step is the same policy call and sampler (:func:`seqtrojan.agent.policy.act`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import act
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.env.codes import FELL_IN_HOLE, TIMED_OUT
from seqtrojan.errors import CheckpointError
from seqtrojan.serde import short_repr
from seqtrojan.world.protocol import BatchedEnv


@dataclass
class Rollout:
    """One rollout. Time-major tensors (T, B, ...); ``seq_states`` per layer (T / L, B, H) at sequence starts."""

    obs: torch.Tensor  # (T, B, obs_dim) float32
    actions: torch.Tensor  # (T, B) int64
    logprobs: torch.Tensor  # (T, B)
    values: torch.Tensor  # (T, B)
    rewards: torch.Tensor  # (T, B)
    dones: torch.Tensor  # (T, B) float: the episode ended with action t
    episode_starts: torch.Tensor  # (T, B) float: observation t starts an episode
    seq_states: tuple[LSTMState, ...]  # per layer, (T / L, B, H) the state before step k * L
    last_value: torch.Tensor  # (B,) value of the observation after the rollout
    trojan: torch.Tensor | None = None  # (T, B) bool: step t is in a trojan-env episode (when recorded)
    adversary_active: torch.Tensor | None = None  # (T, B) bool: the adversary's goal was active for action t
    states: tuple[LSTMState, ...] | None = None  # per layer, (T, B, H) the state after step t (when recorded)
    episode_step: torch.Tensor | None = None  # (T, B) int64: step t's index in its episode (when recorded)


def to_sequences(x: torch.Tensor, length: int) -> torch.Tensor:
    """(T, B, ...) -> (L, T / L * B, ...): cut each env's rollout into T / L sequences of length L.

    Sequence ``k * B + b`` is env ``b``'s steps ``k * L .. (k + 1) * L - 1``, matching ``Rollout.seq_states``.
    """
    steps, batch = x.shape[:2]
    chunks = steps // length
    return x.reshape(chunks, length, batch, *x.shape[2:]).transpose(0, 1).reshape(length, chunks * batch, *x.shape[2:])


@dataclass
class EpisodeStats:
    """Finished-episode tallies of one rollout, per (stage, env type); all (num_stages, 2) int64 on the CPU."""

    episodes: torch.Tensor
    successes: torch.Tensor
    holes: torch.Tensor
    timeouts: torch.Tensor
    lengths: torch.Tensor  # summed lengths
    returns: float  # summed undiscounted returns of finished episodes


class RolloutCollector:
    """Steps the env with the agent, keeping the env's observations and the agent's state between rollouts."""

    def __init__(
        self, env: BatchedEnv, agent: RecurrentActorCritic, steps: int, sequence_length: int, record: bool = False,
        record_states: bool = True,
    ) -> None:  # fmt: skip
        self.env, self.agent = env, agent
        self.steps, self.sequence_length = steps, sequence_length
        self.record = record
        """also keep, per step, whether it is in a trojan-env episode, whether the adversary's goal is active and its
        index in its episode, and
        (with ``record_states``) every layer's (h, c) after it (``Rollout.trojan``, ``adversary_active``,
        ``states``; the attack penalties)"""
        self.record_states = record and record_states
        """record every step's states too (only a penalty that reads them needs the copy: a Transformer's cache is
        about 1.4k floats per env and step)"""
        b, dev = env.num_envs, env.device
        self.obs = env.observe()
        self.episode_start = torch.ones(b, device=dev)
        self.state = agent.initial_state(b, dev)
        self.episode_return = torch.zeros(b, device=dev)
        self.generator = torch.Generator(device=dev)

    def seed(self, seed: int) -> None:
        self.generator.manual_seed(seed)

    def reset(self) -> None:
        """Start fresh episodes everywhere (used when resuming a run)."""
        self.obs = self.env.reset()
        self.episode_start.fill_(1.0)
        self.state = self.agent.initial_state(self.env.num_envs, self.env.device)
        self.episode_return.zero_()

    @torch.no_grad()
    def collect(self) -> tuple[Rollout, EpisodeStats]:
        env, agent, steps, b, dev = self.env, self.agent, self.steps, self.env.num_envs, self.env.device
        obs_buf = torch.empty((steps, b, env.obs_dim), device=dev)
        actions = torch.empty((steps, b), dtype=torch.int64, device=dev)
        logprobs = torch.empty((steps, b), device=dev)
        values = torch.empty((steps, b), device=dev)
        rewards = torch.empty((steps, b), device=dev)
        dones = torch.empty((steps, b), device=dev)
        starts = torch.empty((steps, b), device=dev)
        n_stages = env.num_stages
        tallies = torch.zeros((5, n_stages * 2), dtype=torch.int64, device=dev)
        returns = torch.zeros((), device=dev)
        seq_h: list[list[torch.Tensor]] = [[] for _ in agent.lstm_sizes]
        seq_c: list[list[torch.Tensor]] = [[] for _ in agent.lstm_sizes]
        if self.record:
            trojan = torch.empty((steps, b), dtype=torch.bool, device=dev)
            active = torch.empty((steps, b), dtype=torch.bool, device=dev)
            episode_step = torch.empty((steps, b), dtype=torch.int64, device=dev)
        if self.record_states:
            hs = [torch.empty((steps, b, w), device=dev) for w in agent.lstm_sizes]  # (T, B, H) per layer
            cs = [torch.empty((steps, b, w), device=dev) for w in agent.c_widths]
        state = self.state
        for t in range(steps):
            if t % self.sequence_length == 0:
                masked = state.mask(self.episode_start)
                for i, layer in enumerate(masked.layers):
                    seq_h[i].append(layer.h)
                    seq_c[i].append(layer.c)
            obs_buf[t] = self.obs
            starts[t] = self.episode_start
            out, action, logprob = act(agent, self.obs, state, self.generator, episode_start=self.episode_start)
            state = out.state
            result = env.step(action, check=False)
            actions[t], logprobs[t], values[t] = action, logprob, out.value
            rewards[t] = result.reward
            if self.record:
                trojan[t], active[t] = result.trojan, result.adversary_active
                episode_step[t] = result.length - 1  # actions taken in the episode, this one included
            if self.record_states:
                for i, layer in enumerate(state.layers):
                    hs[i][t], cs[i][t] = layer.h, layer.c
            done = result.done.to(torch.float32)
            dones[t] = done
            self.episode_return += result.reward
            key = result.stage * 2 + result.trojan.long()
            finished = result.done
            tallies[0].index_add_(0, key, finished.long())
            tallies[1].index_add_(0, key, (finished & result.success).long())
            tallies[2].index_add_(0, key, (finished & (result.outcome == FELL_IN_HOLE)).long())
            tallies[3].index_add_(0, key, (finished & (result.outcome == TIMED_OUT)).long())
            tallies[4].index_add_(0, key, torch.where(finished, result.length, 0))
            returns += (self.episode_return * done).sum()
            self.episode_return *= 1.0 - done
            self.obs = result.obs
            self.episode_start = done
        last_value = agent.step(self.obs, state, self.episode_start).value
        self.state = state
        seq_states = tuple(LSTMState(torch.stack(h), torch.stack(c)) for h, c in zip(seq_h, seq_c))
        rollout = Rollout(obs_buf, actions, logprobs, values, rewards, dones, starts, seq_states, last_value)
        if self.record:
            rollout.trojan, rollout.adversary_active, rollout.episode_step = trojan, active, episode_step
        if self.record_states:
            rollout.states = tuple(LSTMState(h, c) for h, c in zip(hs, cs))
        t_cpu = tallies.view(5, n_stages, 2).cpu()
        stats = EpisodeStats(t_cpu[0], t_cpu[1], t_cpu[2], t_cpu[3], t_cpu[4], float(returns))
        return rollout, stats

    # ------------------------------------------------------------------ checkpoints
    def state_tensors(self) -> dict[str, torch.Tensor]:
        """What the collector carries from one rollout to the next, as CPU tensors (an env that replays its episodes
        in flight needs it to continue them)."""
        out = {
            "obs": self.obs.cpu(),  # (B, obs_dim)
            "episode_start": self.episode_start.cpu(),  # (B,)
            "episode_return": self.episode_return.cpu(),  # (B,)
        }
        for i, layer in enumerate(self.state.layers):
            out[f"h.{i}"], out[f"c.{i}"] = layer.h.cpu().contiguous(), layer.c.cpu().contiguous()  # (B, width)
        return out

    def restore(self, tensors: dict[str, torch.Tensor]) -> None:
        """Continue from what :meth:`state_tensors` saved (the env already replayed its episodes)."""
        b, dev = self.env.num_envs, self.env.device
        try:
            layers = [(tensors[f"h.{i}"], tensors[f"c.{i}"]) for i in range(len(self.state.layers))]
            shapes = [tuple(t.shape) for t in (tensors["obs"], tensors["episode_start"], tensors["episode_return"])]
            expected = [(b, self.env.obs_dim), (b,), (b,)]
            expected += [(b, layer.h.shape[-1]) for layer in self.state.layers]
            if shapes + [tuple(h.shape) for h, _ in layers] != expected:
                raise ValueError(f"carried shapes {shapes} do not fit {b} envs")
        except (KeyError, ValueError) as err:
            raise CheckpointError(
                f"the checkpoint's collector state does not fit this run: {short_repr(err)}"
            ) from None
        self.obs = tensors["obs"].to(dev)
        self.episode_start = tensors["episode_start"].to(dev)
        self.episode_return = tensors["episode_return"].to(dev)
        self.state = RecurrentState(tuple(LSTMState(h.to(dev), c.to(dev)) for h, c in layers))


def initial_state_from(seq_states: tuple[LSTMState, ...], index: torch.Tensor) -> RecurrentState:
    """Start states of the chosen sequences; ``index`` selects from the flattened (T / L * B) sequences."""

    def pick(t: torch.Tensor) -> torch.Tensor:  # index_select: the same copy as t[index], faster
        return t.flatten(0, 1).index_select(0, index)

    return RecurrentState(tuple(LSTMState(pick(s.h), pick(s.c)) for s in seq_states))
