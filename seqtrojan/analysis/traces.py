"""Recording the LSTM's hidden and cell states over many episodes: one trace format read by every analysis.

A :class:`StateTrace` holds, for E episodes run as one batch (one per env slot, no autoreset):

* ``h[layer]``, ``c[layer]``: (E, T, units) float32, the state after step t's update (the state that chose a_t);
* ``mask``: (E, T) bool, true while the episode runs (episodes end at different steps);
* ``actions`` (E, T) int64, ``positions`` (E, T, 2) int64 (row, col before a_t), ``outcome`` (E,), ``length``
  (E,), ``layouts`` (E, N, N) int8, ``trojan`` (E,) bool and ``trigger_step`` (E,) int64 (-1: none).

Saved as ``<name>.safetensors`` (the arrays) + ``<name>.json`` (what was recorded: agent, grid, env, seed), never
pickle. ``replay_states`` re-feeds a recorded episode's observations to an agent (with an optional intervention),
so findings can be reproduced and plotted from the trace alone.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.numpy import load_file, save_file

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import Intervention
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.layout import Layout
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, run_episodes
from seqtrojan.errors import CheckpointError, ShapeError
from seqtrojan.serde import to_dict
from seqtrojan.world.config import GymnasiumEnvConfig
from seqtrojan.world.episodes import episode_env


@dataclass
class StateTrace:
    h: list[np.ndarray]  # per layer (E, T, units)
    c: list[np.ndarray]
    mask: np.ndarray  # (E, T) bool
    actions: np.ndarray  # (E, T)
    positions: np.ndarray  # (E, T, 2)
    outcome: np.ndarray  # (E,)
    length: np.ndarray  # (E,)
    layouts: np.ndarray  # (E, N, N) int8
    trojan: np.ndarray  # (E,) bool
    trigger_step: np.ndarray  # (E,) int64, -1 for none
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def episodes(self) -> int:
        return int(self.mask.shape[0])

    @property
    def steps(self) -> int:
        return int(self.mask.shape[1])

    def states(self, which: str, layer: int) -> np.ndarray:
        if which not in ("h", "c"):
            raise ShapeError(f"which must be 'h' or 'c', got {which!r}")
        return (self.h if which == "h" else self.c)[layer]

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f"h.{i}": a for i, a in enumerate(self.h)} | {f"c.{i}": a for i, a in enumerate(self.c)}
        arrays |= {
            "mask": self.mask.astype(np.uint8),
            "actions": self.actions,
            "positions": self.positions,
            "outcome": self.outcome,
            "length": self.length,
            "layouts": self.layouts,
            "trojan": self.trojan.astype(np.uint8),
            "trigger_step": self.trigger_step,
        }
        save_file({k: np.ascontiguousarray(v) for k, v in arrays.items()}, str(path.with_suffix(".safetensors")))
        path.with_suffix(".json").write_text(json.dumps({"layers": len(self.h), **self.meta}, indent=2))
        return path.with_suffix(".safetensors")

    @classmethod
    def load(cls, path: str | Path) -> StateTrace:
        path = Path(path)
        try:
            meta = json.loads(path.with_suffix(".json").read_text())
            a = load_file(str(path.with_suffix(".safetensors")))
        except (OSError, ValueError, json.JSONDecodeError) as err:
            raise CheckpointError(f"cannot read the state trace {str(path)!r}: {err}") from None
        layers = int(meta.pop("layers"))
        return cls(
            h=[a[f"h.{i}"] for i in range(layers)],
            c=[a[f"c.{i}"] for i in range(layers)],
            mask=a["mask"].astype(bool),
            actions=a["actions"],
            positions=a["positions"],
            outcome=a["outcome"],
            length=a["length"],
            layouts=a["layouts"],
            trojan=a["trojan"].astype(bool),
            trigger_step=a["trigger_step"],
            meta=meta,
        )


class _TraceRecorder:
    """Records a :class:`StateTrace`'s per-step arrays from the episode loop (states only if ``record_states``)."""

    def __init__(
        self, episodes: int, limit: int, widths: Sequence[int], record_states: bool, c_widths: Sequence[int]
    ) -> None:
        kept = limit if record_states else 0
        self.record_states = record_states
        self.h = [np.zeros((episodes, kept, w), np.float32) for w in widths]
        self.c = [np.zeros((episodes, kept, w), np.float32) for w in c_widths]
        self.mask = np.zeros((episodes, limit), bool)
        self.actions = np.zeros((episodes, limit), np.int64)
        self.positions = np.zeros((episodes, limit, 2), np.int64)
        self.steps = 0
        self.batch: EpisodeBatch | None = None

    def on_step(self, step: EpisodeStep) -> None:
        t = step.t
        self.mask[:, t] = step.running.cpu().numpy()
        if self.record_states:
            assert step.state is not None, "recording states needs a policy with an output (an AgentPolicy)"
            for i, layer in enumerate(step.state.layers):
                self.h[i][:, t] = layer.h.cpu().numpy()
                self.c[i][:, t] = layer.c.cpu().numpy()
        self.actions[:, t] = step.action.cpu().numpy()
        self.positions[:, t] = step.cells.cpu().numpy()
        self.steps = t + 1

    def on_end(self, batch: EpisodeBatch) -> None:
        self.batch = batch


@torch.no_grad()
def record_traces(
    agent: RecurrentActorCritic,
    env: EnvConfig | GymnasiumEnvConfig,
    grids: Sequence[GridSpec],
    *,
    episodes: int,
    trojan: bool,
    trigger_step: int | None = None,
    seed: int = 0,
    greedy: bool = False,
    device: str | torch.device = "cpu",
    intervention: Intervention | None = None,
    meta: dict[str, Any] | None = None,
    record_states: bool = True,
) -> StateTrace:
    """Run ``episodes`` episodes (grids drawn uniformly from ``grids``, e.g. 27x27 with 90..100 holes) and record
    every layer's h and c at every step. In the trojan env the trigger shows at ``trigger_step`` (fixed; None
    draws it from the env's evaluation range). ``record_states=False`` keeps only actions, positions, outcomes and
    layouts (the h and c arrays are then empty). Actions are sampled with a generator seeded ``seed`` (or greedy).
    A Gymnasium env section records the same (``grids`` is then ignored; positions are zeros and there are no
    layouts: shape (E, 0, 0))."""
    core = episode_env(
        env, grids[0] if grids else None, episodes, trojan=trojan, device=device, seed=seed, grids=grids or None,
        trigger_step=trigger_step,
    )  # fmt: skip
    env_cfg = core.config
    if isinstance(core, TrojanGridCore):
        layouts = np.stack([core.layout(i).cells for i in range(episodes)])
    else:
        layouts = np.zeros((episodes, 0, 0), np.int8)
    trojan_flags = core.trojan.cpu().numpy().copy()
    trigger_steps = core.on_step.cpu().numpy().copy()
    limit = core.episode_limit
    recorder = _TraceRecorder(episodes, limit, agent.lstm_sizes, record_states, agent.c_widths)
    policy = AgentPolicy(agent, greedy=greedy, seed=seed, intervention=intervention, step_counter=lambda: core.t)
    batch = run_episodes(core, policy, fresh=False, recorders=[recorder])
    steps = recorder.steps
    info = {
        "grids": [g.label for g in grids] if isinstance(env, EnvConfig) else [env.id],
        "episodes": episodes,
        "trojan": trojan,
        "trigger_step": trigger_step,
        "seed": seed,
        "greedy": greedy,
        "env": dataclasses.asdict(env_cfg) if isinstance(env_cfg, EnvConfig) else to_dict(env_cfg),
        **(meta or {}),
    }
    return StateTrace(
        [a[:, :steps] for a in recorder.h],
        [a[:, :steps] for a in recorder.c],
        recorder.mask[:, :steps],
        recorder.actions[:, :steps],
        recorder.positions[:, :steps],
        batch.outcome.numpy(),
        batch.length.numpy(),
        layouts,
        trojan_flags,
        trigger_steps,
        info,
    )


class _ReplayPolicy(AgentPolicy):
    """The agent's network stepped on the replayed episode, taking the recorded actions (open loop)."""

    def __init__(self, agent: RecurrentActorCritic, actions: Sequence[int], **kw: Any) -> None:
        super().__init__(agent, greedy=True, **kw)  # greedy: its own choice draws nothing, and is discarded
        self.recorded = [int(a) for a in actions]
        self.t = 0

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        super().__call__(obs)  # steps the network
        self.t += 1
        return torch.tensor([self.recorded[self.t - 1]])


class _ReplayRecorder:
    """Env 0's per-step states (per layer), action preferences and positions."""

    def __init__(self) -> None:
        self.hs: list[list[np.ndarray]] = []
        self.cs: list[list[np.ndarray]] = []
        self.prefs: list[np.ndarray] = []
        self.positions: list[tuple[int, int]] = []

    def on_step(self, step: EpisodeStep) -> None:
        self.positions.append((int(step.cells[0, 0]), int(step.cells[0, 1])))
        assert step.state is not None and step.logits is not None  # the replay policy is an AgentPolicy
        self.hs.append([layer.h[0].cpu().numpy().copy() for layer in step.state.layers])
        self.cs.append([layer.c[0].cpu().numpy().copy() for layer in step.state.layers])
        self.prefs.append(torch.softmax(step.logits[0], -1).cpu().numpy())

    def on_end(self, batch: EpisodeBatch) -> None:
        pass


@torch.no_grad()
def replay_states(
    agent: RecurrentActorCritic,
    env: EnvConfig,
    layout: Layout,
    actions: Sequence[int],
    *,
    trigger_step: int | None,
    intervention: Intervention | None = None,
) -> dict[str, Any]:
    """Re-run one episode from its layout and actions; returns per-layer (h, c) arrays (T, units), the
    agent's own action preferences at each step, and the positions. Open-loop: the recorded actions are taken,
    until they run out or the episode ends. The time limit is ``env``'s (``env.max_steps``, else 4N)."""
    # The env's own max_steps is kept (not the 4N default of a bare GridSpec): the replayed episode ran under it.
    env_cfg = env.with_grid(GridSpec(layout.size, 0, env.max_steps))
    core = TrojanGridCore(env_cfg, 1, phase="eval")
    core.set_episode(0, layout, on_step=trigger_step)
    policy = _ReplayPolicy(agent, actions, intervention=intervention, step_counter=lambda: core.t)
    recorder = _ReplayRecorder()
    run_episodes(core, policy, fresh=False, recorders=[recorder], max_steps=len(policy.recorded), check=True)
    layers = len(agent.lstm_sizes)
    return {
        "h": [np.stack([x[i] for x in recorder.hs]) for i in range(layers)],
        "c": [np.stack([x[i] for x in recorder.cs]) for i in range(layers)],
        "policy": np.stack(recorder.prefs),
        "positions": recorder.positions,
    }
