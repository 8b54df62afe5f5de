"""State bounds: clip every recurrent unit to the range it takes on clean episodes (UNIT-style, on the state).

In the spirit of UNIT (Pang et al. 2023, "UNIT: Backdoor mitigation via automated neural distribution
tightening"), applied to the recurrent state instead of a feed-forward network's activations: a backdoor that
switches the agent's goal has to hold that switch in its state after the trigger is gone, and if holding it needs
some unit of h or c outside the range that unit ever takes on clean episodes, clipping every unit to its clean
range at every step erases (or weakens) the switch. The defender needs only clean episodes of the deployed agent,
never the trigger.

* :func:`fit_bounds`: each unit's clean ``[q, 1 - q]`` quantiles over all running steps, widened by ``margin``
  clean standard deviations on each side;
* :class:`ClipToBounds`: the :class:`~seqtrojan.agent.state.Intervention` that clamps each layer's h and c to them
  after every cell update (so the clipped h is also what the next layer and the heads read);
* :func:`calibrate_bounds`: records the clean episodes and fits the bounds.

It is registered as the ``state_bounds`` mitigation in :mod:`seqtrojan.defense.mitigation`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.config import EnvSection
from seqtrojan.env.config import GridSpec
from seqtrojan.errors import ConfigError

PARTS = ("h", "c")


@dataclass(frozen=True)
class StateBoundsConfig:
    quantile: float = 0.05
    """each unit's bounds are its clean ``quantile`` and ``1 - quantile`` quantiles, in [0, 0.5): 0 is the clean
    minimum and maximum, which realistic triggers stay within; larger values tighten the range and clip clean
    states too (0.05 on the smoke agents: attack success below 0.1, clean success within 0.015; docs/defenses.md)"""
    margin: float = 0.0
    """widen each side by this many clean standard deviations of the unit (>= 0)"""
    parts: tuple[str, ...] = PARTS
    """which parts of the state are clipped: ``h``, ``c`` or both"""
    layers: tuple[int, ...] | None = None
    """which layers are clipped (None: all)"""

    def __post_init__(self) -> None:
        if not 0.0 <= self.quantile < 0.5:
            raise ConfigError(f"state_bounds.quantile must be in [0, 0.5), got {self.quantile!r}")
        if not self.margin >= 0.0 or not np.isfinite(self.margin):
            raise ConfigError(f"state_bounds.margin must be a finite number >= 0, got {self.margin!r}")
        if not self.parts or any(p not in PARTS for p in self.parts) or len(set(self.parts)) != len(self.parts):
            raise ConfigError(f"state_bounds.parts must be distinct names among {list(PARTS)}, got {self.parts!r}")
        if self.layers is not None and (
            not self.layers or any(i < 0 for i in self.layers) or len(set(self.layers)) != len(self.layers)
        ):
            raise ConfigError(f"state_bounds.layers must be distinct layer indices >= 0 (or null), got {self.layers!r}")


@dataclass(frozen=True)
class UnitBounds:
    """One part (h or c) of one layer: each unit's clean range."""

    layer: int
    part: str
    low: np.ndarray  # (units,) float32
    high: np.ndarray  # (units,) float32


@dataclass(frozen=True)
class StateBounds:
    """The bounds of every clipped (layer, part), fitted on ``steps`` clean running steps."""

    bounds: tuple[UnitBounds, ...]
    steps: int

    def clipper(self) -> ClipToBounds:
        return ClipToBounds(self)


def fit_bounds(
    h: Sequence[np.ndarray], c: Sequence[np.ndarray], mask: np.ndarray, cfg: StateBoundsConfig
) -> StateBounds:
    """Bounds from clean states: ``h[layer]``, ``c[layer]`` (E, T, units), ``mask`` (E, T) true on running steps."""
    layers = tuple(range(len(h))) if cfg.layers is None else cfg.layers
    if any(i >= len(h) for i in layers):
        raise ConfigError(f"state_bounds.layers={list(layers)} names a layer the agent lacks (it has {len(h)})")
    steps = int(mask.sum())
    if steps == 0:
        raise ConfigError("state bounds need at least one running clean step, got none")
    fitted = []
    for layer in layers:
        for part in cfg.parts:
            rows = (h if part == "h" else c)[layer][mask]  # (steps, units)
            if rows.shape[-1] == 0:  # a part of width 0 (a GRU's c): nothing to clip
                continue
            low, high = np.quantile(rows, [cfg.quantile, 1.0 - cfg.quantile], axis=0)  # (units,) each
            sd = rows.std(0)
            fitted.append(UnitBounds(layer, part, (low - cfg.margin * sd).astype(np.float32),
                                     (high + cfg.margin * sd).astype(np.float32)))  # fmt: skip
    return StateBounds(tuple(fitted), steps)


def fit_trace(trace: StateTrace, cfg: StateBoundsConfig) -> StateBounds:
    return fit_bounds(trace.h, trace.c, trace.mask, cfg)


class ClipToBounds:
    """The intervention: after each layer's cell update, clamp its clipped parts' units to their bounds (at every
    step; the episode step is not read)."""

    def __init__(self, bounds: StateBounds) -> None:
        self.bounds = {(b.layer, b.part): (torch.from_numpy(b.low), torch.from_numpy(b.high)) for b in bounds.bounds}

    def __call__(self, layer: int, t: torch.Tensor | None, state: LSTMState) -> LSTMState:
        h, c = state.h, state.c
        if (layer, "h") in self.bounds:
            h = self._clamp(h, *self.bounds[(layer, "h")])
        if (layer, "c") in self.bounds:
            c = self._clamp(c, *self.bounds[(layer, "c")])
        return LSTMState(h, c)

    @staticmethod
    def _clamp(x: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        return torch.clamp(x, min=low.to(x.device, x.dtype), max=high.to(x.device, x.dtype))  # (batch, units)


@torch.no_grad()
def clean_trace(
    agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, *, episodes: int, seed: int,
    device: str | torch.device = "cpu",
) -> StateTrace:  # fmt: skip
    """The states of ``episodes`` normal-env episodes of ``agent`` (sampled actions): all a defender has."""
    grids = [grid] if grid is not None else []
    return record_traces(agent, env, grids, episodes=episodes, trojan=False, trigger_step=None, seed=seed,
                         device=device)  # fmt: skip


def calibrate_bounds(
    agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: StateBoundsConfig, *, episodes: int,
    seed: int, device: str | torch.device = "cpu",
) -> StateBounds:  # fmt: skip
    """Bounds fitted on ``episodes`` clean episodes of ``agent`` on ``grid`` (a Gymnasium env: its own env)."""
    return fit_trace(clean_trace(agent, env, grid, episodes=episodes, seed=seed, device=device), cfg)
