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
from seqtrojan.agent.state import Intervention, RecurrentState
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.layout import Layout
from seqtrojan.errors import CheckpointError, ShapeError


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


@torch.no_grad()
def record_traces(
    agent: RecurrentActorCritic,
    env: EnvConfig,
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
    layouts (the h and c arrays are then empty)."""
    trig = env.trigger
    if trigger_step is not None:
        trig = dataclasses.replace(trig, eval_steps=(trigger_step, trigger_step))
    env_cfg = dataclasses.replace(env, size=grids[0].size, holes=grids[0].holes, trigger=trig)
    core = TrojanGridCore(
        env_cfg,
        episodes,
        seed=seed,
        device=device,
        grids=grids,
        trojan_probability=1.0 if trojan else 0.0,
        phase="eval",
    )
    limit = max(g.time_limit for g in core.grids)
    widths = agent.lstm_sizes
    kept = limit if record_states else 0
    h = [np.zeros((episodes, kept, w), np.float32) for w in widths]
    c = [np.zeros((episodes, kept, w), np.float32) for w in widths]
    mask = np.zeros((episodes, limit), bool)
    actions = np.zeros((episodes, limit), np.int64)
    positions = np.zeros((episodes, limit, 2), np.int64)
    outcome = np.zeros(episodes, np.int64)
    length = np.zeros(episodes, np.int64)
    layouts = np.stack([core.layout(i).cells for i in range(episodes)])
    trojan_flags = core.trojan.cpu().numpy().copy()
    trigger_steps = core.on_step.cpu().numpy().copy()
    generator = torch.Generator(device=core.device).manual_seed(seed)
    state: RecurrentState = agent.initial_state(episodes, core.device)
    obs = core.observe()
    running = torch.ones(episodes, dtype=torch.bool, device=core.device)
    r = core.view_size // 2
    for t in range(limit):
        out = agent.step(obs, state, t=core.t, intervention=intervention)
        state = out.state
        if greedy:
            action = out.logits.argmax(-1)
        else:
            u = torch.rand(out.logits.shape, device=core.device, generator=generator).clamp_(min=1e-20)
            action = (out.logits - torch.log(-torch.log(u))).argmax(-1)
        live = running.cpu().numpy()
        mask[:, t] = live
        if record_states:
            for i, layer in enumerate(state.layers):
                h[i][:, t] = layer.h.cpu().numpy()
                c[i][:, t] = layer.c.cpu().numpy()
        actions[:, t] = action.cpu().numpy()
        pos = core.pos.cpu().numpy()
        positions[:, t, 0], positions[:, t, 1] = pos // core.side - r, pos % core.side - r
        result = core.step(action, autoreset=False, check=False)
        ended = (result.done & running).cpu().numpy()
        outcome[ended] = result.outcome.cpu().numpy()[ended]
        length[ended] = t + 1
        running &= ~result.done
        obs = result.obs
        if not bool(running.any()):
            limit = t + 1
            break
    info = {
        "grids": [g.label for g in grids],
        "episodes": episodes,
        "trojan": trojan,
        "trigger_step": trigger_step,
        "seed": seed,
        "greedy": greedy,
        "env": dataclasses.asdict(env_cfg),
        **(meta or {}),
    }
    return StateTrace(
        [a[:, :limit] for a in h],
        [a[:, :limit] for a in c],
        mask[:, :limit],
        actions[:, :limit],
        positions[:, :limit],
        outcome,
        length,
        layouts,
        trojan_flags,
        trigger_steps,
        info,
    )


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
    agent's own action preferences at each step, and the positions. Open-loop: the recorded actions are taken."""
    env_cfg = dataclasses.replace(env, size=layout.size, holes=0)
    core = TrojanGridCore(env_cfg, 1, phase="eval")
    core.set_episode(0, layout, on_step=trigger_step)
    state = agent.initial_state(1)
    obs = core.observe()
    hs, cs, prefs, positions = [], [], [], []
    for a in actions:
        positions.append(core.snapshot(0).agent)
        out = agent.step(obs, state, t=core.t, intervention=intervention)
        state = out.state
        hs.append([layer.h[0].numpy().copy() for layer in state.layers])
        cs.append([layer.c[0].numpy().copy() for layer in state.layers])
        prefs.append(torch.softmax(out.logits[0], -1).numpy())
        result = core.step(torch.tensor([int(a)]), autoreset=False)
        obs = result.obs
        if bool(result.done[0]):
            break
    layers = len(agent.lstm_sizes)
    return {
        "h": [np.stack([x[i] for x in hs]) for i in range(layers)],
        "c": [np.stack([x[i] for x in cs]) for i in range(layers)],
        "policy": np.stack(prefs),
        "positions": positions,
    }
