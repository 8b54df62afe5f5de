"""The batched trojan grid world: B independent episodes stepped at once as tensors, on CPU or CUDA.

Semantics (docs/environment.md, pinned by ``tests/env/test_semantics.py``):

* Step index ``t`` counts the actions taken in the episode. Observation ``o_t`` is what the agent sees before
  choosing action ``a_t``; ``o_0`` follows a reset.
* A trojan episode shows the ON pattern in ``o_t`` for ``on_step <= t < on_step + duration`` (and, with ON/OFF
  triggers, the OFF pattern from ``off_step``). Patterns replace the chosen view cells with their value (one
  code for the patch, or one per cell). A sequence trigger shows its frame ``k`` in ``o_{on_step + k}``.
* The correct goal for action ``a_t`` is the adversary's iff the latest trigger whose effect time
  (first step + ``delay``; for a sequence, its last frame's step + ``delay``) is ``<= t`` is an ON trigger;
  otherwise the user's. Normal episodes never show one.
* A move into the border leaves the agent in place. Entering a hole ends the episode (``rewards.hole``);
  entering a goal ends it (``rewards.goal`` if it is the correct goal, else ``rewards.wrong_goal``).
  After ``time_limit`` actions the episode is truncated (``rewards.timeout``, a failure).
* With ``autoreset`` (the default), finished envs start a new episode inside the same ``step`` call; the
  returned observation is then the new episode's ``o_0`` and ``done`` marks it as an episode start.

Randomness is counter-based (see :mod:`seqtrojan.env.rng`): env ``i`` seeded with ``s`` draws episode ``j``
from a hash of ``(s, j)`` alone, so env ``i`` of a batch equals a single env seeded with ``seed + i``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from seqtrojan.env import rng
from seqtrojan.env.codes import (
    ACTION_SETS,
    ADV_GOAL,
    CELL_CODES,
    EMPTY,
    FELL_IN_HOLE,
    HOLE,
    NUM_CHANNELS,
    REACHED_ADV_GOAL,
    REACHED_USER_GOAL,
    RUNNING,
    TIMED_OUT,
    USER_GOAL,
    WALL,
)
from seqtrojan.env.config import EnvConfig, GridSpec, min_steps_to_goal
from seqtrojan.env.layout import Layout, LayoutSampler, layout_tries_needed
from seqtrojan.errors import ConfigError, LayoutError, ShapeError

Phase = str  # "train" or "eval"


class StepResult(NamedTuple):
    """What one batched step returns. All tensors have shape ``(B,)`` except ``obs``.

    ``outcome``, ``success``, ``trojan``, ``stage``, ``length`` and ``adversary_active`` describe the episode
    the step was taken in (before any autoreset), so they are what a logger wants where ``done`` is true.
    """

    obs: torch.Tensor  # (B, obs_dim) float32, after autoreset
    reward: torch.Tensor  # float32
    terminated: torch.Tensor  # bool: hole or goal
    truncated: torch.Tensor  # bool: time limit
    done: torch.Tensor  # bool: terminated | truncated (the next observation starts an episode)
    outcome: torch.Tensor  # int64: RUNNING, REACHED_USER_GOAL, REACHED_ADV_GOAL, FELL_IN_HOLE, TIMED_OUT
    success: torch.Tensor  # bool: reached the correct goal
    trojan: torch.Tensor  # bool: the episode was a trojan-env episode
    stage: torch.Tensor  # int64: index of the episode's grid in ``grids``
    length: torch.Tensor  # int64: actions taken in the episode so far
    adversary_active: torch.Tensor  # bool: the adversary's goal was the correct goal for this action


@dataclass(frozen=True)
class EnvState:
    """The episodes in flight of a batched env (:class:`TrojanGridCore` or a Gymnasium env behind the seam
    :mod:`seqtrojan.world`), as a checkpoint keeps them: tensors (the grid world's whole episode state) and
    plain-JSON records (a Gymnasium env's: what replays each episode)."""

    tensors: dict[str, torch.Tensor] = field(default_factory=dict)
    records: list[Any] | None = None


@dataclass(frozen=True)
class EpisodeSnapshot:
    """One env's current state as plain Python values, for rendering, replays and tests."""

    layout: Layout
    agent: tuple[int, int]
    t: int
    trojan: bool
    on_step: int | None
    off_step: int | None
    visible: str | None  # "on", "off" or None: the pattern shown in the current observation
    adversary_active: bool  # the correct goal for the next action is the adversary's
    view_size: int
    on_cells: tuple[tuple[int, int], ...]  # every view cell the ON trigger draws on (all frames of a sequence)
    off_cells: tuple[tuple[int, int], ...]
    time_limit: int
    drawn: tuple[tuple[tuple[int, int], str], ...] = ()
    """the (view cell, code name) pairs of a visible per-cell ON pattern (``trigger.values``, a sequence's frame);
    () otherwise: a one-code patch is drawn on ``on_cells``/``off_cells`` as before"""
    on_frame: int | None = None
    """which frame k of a sequence trigger is visible, None when none is (or the trigger is a single patch)"""


@functools.lru_cache(maxsize=256)
def _solvable_fraction(size: int, holes: int, view_size: int) -> float:
    sampler = LayoutSampler([GridSpec(size, holes)], view_size, max_tries=1, device=torch.device("cpu"))
    return sampler.probe()[0]


class TrojanGridCore:
    """B grid-world episodes as tensors. Each episode runs on one of ``grids`` (a curriculum's stages).

    Args:
        config: view, actions, rewards, trigger and layout settings; its (size, holes) is the grid unless
            ``grids`` is given.
        num_envs: B.
        seed: base seed; env ``i`` uses ``seed + i`` (Gymnasium's vector convention), or one seed per env.
        device: torch device.
        grids: the grid stages episodes are drawn from (weights set by :meth:`set_stage_weights`).
        trojan_probability: chance that a new episode is a trojan-env episode (per stage, or one number).
        phase: "train" draws the trigger step from ``trigger.train_steps``, "eval" from ``trigger.eval_steps``,
            always clipped so that no goal can be reached before the trigger takes effect.
    """

    def __init__(
        self,
        config: EnvConfig,
        num_envs: int,
        *,
        seed: int | Sequence[int] = 0,
        device: str | torch.device = "cpu",
        grids: Sequence[GridSpec] | None = None,
        trojan_probability: float | Sequence[float] = 0.0,
        phase: Phase = "train",
    ) -> None:
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ConfigError(f"num_envs must be a positive integer, got {num_envs!r}")
        if phase not in ("train", "eval"):
            raise ConfigError(f"phase must be 'train' or 'eval', got {phase!r}")
        self.config = config
        self.num_envs = num_envs
        self.device = torch.device(device)
        self.phase = phase
        self.grids: tuple[GridSpec, ...] = tuple(grids) if grids is not None else (config.grid,)
        if not self.grids:
            raise ConfigError("grids must name at least one grid")
        for g in self.grids:
            config.check_padded_side(g.size)
        self.view_size = config.view_size
        self.obs_dim = config.obs_dim
        self.num_actions = config.num_actions
        self.sampler = LayoutSampler(self.grids, config.view_size, config.max_layout_tries, self.device)
        self._check_solvable_fraction()
        self.side = self.sampler.side
        self._build_tables()
        self.set_trojan_probability(trojan_probability)
        self.set_stage_weights([1.0] * len(self.grids))
        self.reset(seed=seed)

    # ------------------------------------------------------------------ set-up
    def _check_solvable_fraction(self) -> None:
        """Refuse grids whose solvable layouts are so rare that an episode could exhaust ``max_layout_tries``."""
        tries = self.config.max_layout_tries
        fractions = [_solvable_fraction(g.size, g.holes, self.view_size) for g in self.grids]
        worst = min(fractions)
        # Enough tries per round that an env needs a second round with probability <= 1e-3.
        rounds = math.log(1e-3) / math.log(1.0 - worst) if 0.0 < worst < 1.0 else 1.0
        self.sampler.attempts_per_round = int(min(32, max(1, math.ceil(rounds))))
        for g, frac in zip(self.grids, fractions, strict=True):
            needed = layout_tries_needed(frac, g.holes)  # then a reset fails with probability <= e^-30
            if needed is None or needed > tries:
                fix = f"raise env.max_layout_tries to >= {needed}" if needed else "raise env.max_layout_tries"
                raise LayoutError(
                    f"solvable layouts are too rare for size={g.size}, holes={g.holes} with max_layout_tries={tries}: "
                    f"{frac:.2%} of random layouts have both goals reachable; use fewer holes or {fix}"
                )

    def _build_tables(self) -> None:
        cfg, p, r, dev = self.config, self.side, self.view_size // 2, self.device
        span = range(-r, r + 1)
        self._window = torch.tensor([dr * p + dc for dr in span for dc in span], dtype=torch.int64, device=dev)
        self._deltas = torch.tensor([dr * p + dc for dr, dc in ACTION_SETS[cfg.actions]], device=dev)
        v = self.view_size
        self._on_patch = torch.zeros(v * v, dtype=torch.bool, device=dev)
        self._on_patch[[row * v + col for row, col in cfg.on_cells]] = True
        self._off_patch = torch.zeros(v * v, dtype=torch.bool, device=dev)
        self._off_patch[[row * v + col for row, col in cfg.off_cells]] = True
        self._on_value = CELL_CODES[cfg.trigger.value]
        self._off_value = CELL_CODES[cfg.trigger.off.value]
        # Per-frame ON tables (frame k shows at on_step + k): what each frame draws where. A single patch of one
        # code (the paper's, the default) keeps the one-mask, one-value path in observe_codes.
        frames = self._frames = cfg.on_frames
        self._on_frames = len(frames)
        self._on_shown = cfg.trigger.shown_steps
        self._on_effect = cfg.trigger.effect_offset
        self._on_uniform = len(frames) == 1 and cfg.trigger.values is None
        self._frame_mask = torch.zeros(len(frames), v * v, dtype=torch.bool, device=dev)  # (F, v*v)
        self._frame_value = torch.zeros(len(frames), v * v, dtype=torch.uint8, device=dev)  # (F, v*v)
        for k, frame in enumerate(frames):
            for (row, col), name in frame:
                self._frame_mask[k, row * v + col] = True
                self._frame_value[k, row * v + col] = CELL_CODES[name]
        self._one_hot = torch.eye(NUM_CHANNELS, dtype=torch.float32, device=dev)
        self._time_limit = torch.tensor([g.time_limit for g in self.grids], device=dev)
        # Trigger step ranges per stage, clipped so the (last) trigger takes effect before a goal is reachable.
        trig, off = cfg.trigger, cfg.trigger.off
        lo, hi = trig.eval_steps if self.phase == "eval" else trig.train_steps
        clip = self.phase == "eval" or trig.clip_train_steps
        on_lo, on_hi, effect_limit = [], [], []
        for g in self.grids:
            limit = min_steps_to_goal(g.size) - 1 - trig.delay  # last step at which a trigger may take effect
            room = off.gap[0] if off.probability > 0 else 0
            # The ON trigger takes effect effect_offset steps after its first step (a sequence: at its last frame).
            top = min(hi, limit - room, limit - (trig.frame_count - 1)) if clip else hi
            if top < 0:
                seq = f", {trig.frame_count} sequence frames" if trig.frame_count > 1 else ""
                raise ConfigError(
                    f"on grid size={g.size} no trigger step can come before a goal is reachable (delay="
                    f"{trig.delay}{seq}{', off gap ' + str(off.gap) if room else ''}); use a larger grid, a shorter "
                    "delay or a shorter sequence"
                )
            if self.phase == "eval" and lo > top:
                raise ConfigError(
                    f"trigger.eval_steps={trig.eval_steps} start after step {top}, the last step at which the "
                    f"trigger can take effect before a goal is reachable on size={g.size}"
                )
            on_lo.append(min(lo, top))
            on_hi.append(top)
            effect_limit.append(limit if clip else 1 << 30)
        decoys = cfg.trigger.decoys
        self._decoys = decoys.enabled and self.phase == "train"  # a training device: evaluation never shows one
        self._decoy_codes = torch.tensor([CELL_CODES[c] for c in decoys.codes], dtype=torch.int64, device=dev)
        self._on_lo = torch.tensor(on_lo, device=dev)
        self._on_hi = torch.tensor(on_hi, device=dev)
        self._effect_limit = torch.tensor(effect_limit, device=dev)

    @property
    def episode_limit(self) -> int:
        """The longest an episode can run (the largest stage's time limit)."""
        return max(g.time_limit for g in self.grids)

    def agent_cells(self) -> torch.Tensor:
        """(B, 2) int64: every env's agent position as (row, col) on its own grid."""
        r = self.view_size // 2  # the padding around each grid
        return torch.stack((self.pos // self.side - r, self.pos % self.side - r), -1)

    @property
    def num_stages(self) -> int:
        """Grid stages episodes are drawn from (the curriculum's)."""
        return len(self.grids)

    image: tuple[int, int, int] | None = None
    """the observation is no image (a convolutional encoder has nothing to read)"""

    def close(self) -> None:
        """Nothing to release (the batched-env seam's ``close``)."""

    EPISODE_STATE = ("_keys", "episode", "grid", "pos", "t", "stage", "trojan", "on_step", "off_step")
    """what every env's episode in flight is: its counter-based seed and episode count, layout, position, step,
    stage, type and trigger steps (the rest follows from the config)"""
    DECOY_STATE = ("decoy_step", "decoy_codes")
    """with decoys: each env's decoy step (-1: none) and the code drawn on each view cell (-1: left as it is)"""

    @property
    def episode_state(self) -> tuple[str, ...]:
        """The names :meth:`save_state` keeps: :data:`EPISODE_STATE`, and :data:`DECOY_STATE` when decoys show."""
        return self.EPISODE_STATE + (self.DECOY_STATE if self._decoys else ())

    def save_state(self) -> EnvState:
        """The episodes in flight (:data:`EPISODE_STATE`) as CPU tensors: a checkpoint restores them exactly."""
        return EnvState({name.lstrip("_"): getattr(self, name).cpu().clone() for name in self.episode_state})

    def load_state(self, state: EnvState, obs: torch.Tensor) -> bool:
        """Restore :meth:`save_state`'s tensors; True when they fit this env and give back the observations
        ``obs``; otherwise nothing changes and False is returned."""
        saved = {name: state.tensors.get(name.lstrip("_")) for name in self.episode_state}
        ours = {name: getattr(self, name) for name in self.episode_state}
        if any(t is None or t.shape != ours[n].shape or t.dtype != ours[n].dtype for n, t in saved.items()):
            return False
        for name, tensor in saved.items():
            assert tensor is not None
            setattr(self, name, tensor.to(self.device).clone())
        if tuple(obs.shape) == (self.num_envs, self.obs_dim) and torch.equal(self.observe().cpu(), obs.cpu()):
            return True
        for name, tensor in ours.items():
            setattr(self, name, tensor)
        return False

    # ------------------------------------------------------------------ mixture controls
    def set_trojan_probability(self, probability: float | Sequence[float] | torch.Tensor) -> None:
        """Chance that a *new* episode is a trojan-env episode: one number or one per grid stage."""
        p = torch.as_tensor(probability, dtype=torch.float32, device=self.device).flatten()
        if p.numel() == 1:
            p = p.expand(len(self.grids)).clone()
        if p.numel() != len(self.grids) or bool(((p < 0) | (p > 1) | p.isnan()).any()):
            raise ConfigError(
                f"trojan probability must be one value or {len(self.grids)} values in [0, 1], got {p.tolist()}"
            )
        self.trojan_probability = p

    def set_stage_weights(self, weights: Sequence[float] | torch.Tensor) -> None:
        """Relative frequency of each grid stage among *new* episodes."""
        w = torch.as_tensor(weights, dtype=torch.float64).flatten()
        if w.numel() != len(self.grids) or bool((w < 0).any()) or float(w.sum()) <= 0:
            raise ConfigError(f"stage weights must be {len(self.grids)} non-negative values, not all 0: {w.tolist()}")
        cum = (w / w.sum()).cumsum(0)
        cum[-1] = 1.0
        self._stage_cdf = cum.to(torch.float32).to(self.device)
        self.stage_weights = (w / w.sum()).tolist()

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | Sequence[int] | None = None) -> torch.Tensor:
        """Start a new episode in every env; with ``seed``, restart every env's stream first."""
        b, dev = self.num_envs, self.device
        if seed is not None:
            seeds = self._seed_tensor(seed)
            self._keys = rng.seed_keys(seeds)
            self.episode = torch.full((b,), -1, dtype=torch.int64, device=dev)
            self.grid = torch.full((b, self.side * self.side), WALL, dtype=torch.uint8, device=dev)
            self.pos = torch.zeros(b, dtype=torch.int64, device=dev)
            self.t = torch.zeros(b, dtype=torch.int64, device=dev)
            self.stage = torch.zeros(b, dtype=torch.int64, device=dev)
            self.trojan = torch.zeros(b, dtype=torch.bool, device=dev)
            self.on_step = torch.full((b,), -1, dtype=torch.int64, device=dev)
            self.off_step = torch.full((b,), -1, dtype=torch.int64, device=dev)
            if self._decoys:
                self.decoy_step = torch.full((b,), -1, dtype=torch.int64, device=dev)
                self.decoy_codes = torch.full((b, self.view_size**2), -1, dtype=torch.int64, device=dev)
        self._begin_episodes(torch.arange(b, device=dev))
        return self.observe()

    def reset_envs(self, mask: torch.Tensor) -> torch.Tensor:
        """Start a new episode in the envs where ``mask`` (B,) is true; returns all observations."""
        mask = torch.as_tensor(mask, device=self.device)
        if mask.shape != (self.num_envs,) or mask.dtype != torch.bool:
            raise ShapeError(f"reset mask must be a bool tensor of shape ({self.num_envs},), got {tuple(mask.shape)}")
        self._begin_episodes(mask.nonzero().squeeze(1))
        return self.observe()

    def _seed_tensor(self, seed: int | Sequence[int]) -> torch.Tensor:
        if isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != self.num_envs:
                raise ShapeError(f"got {len(seeds)} seeds for {self.num_envs} envs")
        if any(s < 0 or s >= 1 << 63 for s in seeds):
            raise ConfigError(f"seeds must be in [0, 2**63), got {seed!r}")
        return torch.tensor(seeds, dtype=torch.int64, device=self.device)

    def _begin_episodes(self, idx: torch.Tensor) -> None:
        if idx.numel() == 0:
            return
        self.episode[idx] += 1
        keys = rng.combine(self._keys[idx], self.episode[idx] & rng.M32)
        if len(self.grids) > 1:
            u = rng.uniform(keys, rng.STAGE)
            stage = torch.searchsorted(self._stage_cdf, u, right=True).clamp(max=len(self.grids) - 1)
        else:
            stage = torch.zeros_like(idx)
        trojan = rng.uniform(keys, rng.TROJAN) < self.trojan_probability[stage]
        lo, hi = self._on_lo[stage], self._on_hi[stage]
        on = lo + rng.below(rng.combine(keys, rng.ON_STEP), hi - lo + 1)
        off_cfg = self.config.trigger.off
        has_off = trojan & (rng.uniform(keys, rng.OFF_FLAG) < off_cfg.probability)
        gap_lo = off_cfg.gap[0]
        gap_hi = torch.clamp(self._effect_limit[stage] - on, max=off_cfg.gap[1]).clamp(min=gap_lo)
        gap = gap_lo + rng.below(rng.combine(keys, rng.OFF_GAP), gap_hi - gap_lo + 1)
        holes = self.sampler.sample(keys, stage)
        rows = self.sampler.templates[stage].masked_fill(holes, HOLE)
        self.grid[idx] = rows
        self.pos[idx] = self.sampler.starts[stage]
        self.t[idx] = 0
        self.stage[idx] = stage
        self.trojan[idx] = trojan
        self.on_step[idx] = torch.where(trojan, on, -1)
        self.off_step[idx] = torch.where(has_off, on + gap, -1)
        if self._decoys:
            self._draw_decoys(idx, keys, trojan, on)

    def _draw_decoys(self, idx: torch.Tensor, keys: torch.Tensor, trojan: torch.Tensor, on: torch.Tensor) -> None:
        """Each new normal episode shows a decoy with ``trigger.decoys.probability``, at the step its trigger would
        have come (``on``), drawn as the behaviour detector draws its candidates (:class:`DecoyConfig`)."""
        cfg, cells = self.config.trigger.decoys, self.view_size**2
        shows = ~trojan & (rng.uniform(keys, rng.DECOY) < cfg.probability)
        whole = rng.uniform(keys, rng.DECOY_WHOLE) < cfg.whole_view_share
        index = torch.arange(cells, device=self.device)
        cell_keys = rng.combine(keys[:, None], index[None, :])  # (n, cells)
        drawn = rng.uniform(cell_keys, rng.DECOY_CELL) < cfg.density
        forced = rng.below(rng.combine(keys, rng.DECOY_FORCED), cells)  # at least one cell drawn on
        drawn = drawn | (~drawn.any(1, keepdim=True) & (index[None, :] == forced[:, None]))
        codes = self._decoy_codes[rng.below(rng.combine(cell_keys, rng.DECOY_CODE), len(self._decoy_codes))]
        one = rng.below(rng.combine(keys, rng.DECOY_CODE), NUM_CHANNELS)  # a whole-view decoy: any code
        codes = torch.where(whole[:, None], one[:, None].expand(-1, cells), torch.where(drawn, codes, -1))
        self.decoy_step[idx] = torch.where(shows, on, -1)
        self.decoy_codes[idx] = codes

    # ------------------------------------------------------------------ step
    def adversary_active(self) -> torch.Tensor:
        """(B,) bool: the adversary's goal is the correct goal for the action taken at the current step."""
        delay = self.config.trigger.delay
        on = (self.on_step >= 0) & (self.t >= self.on_step + self._on_effect)  # on_step + delay for a patch
        off = (self.off_step >= 0) & (self.t >= self.off_step + delay)
        return on & ~off

    def step(self, actions: torch.Tensor, autoreset: bool = True, check: bool = True) -> StepResult:
        """Apply one action per env. ``actions``: (B,) integer tensor in ``[0, num_actions)``."""
        if check:
            self._check_actions(actions)
        a = actions.to(device=self.device, dtype=torch.int64)
        target = self.pos + self._deltas[a]
        cell = self.grid.gather(1, target[:, None]).squeeze(1)
        moved = cell != WALL
        self.pos = torch.where(moved, target, self.pos)
        cell = torch.where(moved, cell, EMPTY)
        adversary = self.adversary_active()
        at_user, at_adv, in_hole = cell == USER_GOAL, cell == ADV_GOAL, cell == HOLE
        terminated = at_user | at_adv | in_hole
        self.t = self.t + 1
        truncated = ~terminated & (self.t >= self._time_limit[self.stage])
        correct = torch.where(adversary, at_adv, at_user)
        wrong = torch.where(adversary, at_user, at_adv)
        rw = self.config.rewards
        reward = torch.full((self.num_envs,), rw.step, dtype=torch.float32, device=self.device)
        reward = reward.masked_fill(correct, rw.goal).masked_fill(wrong, rw.wrong_goal)
        if rw.false_activation is not None:
            reward = reward.masked_fill(wrong & at_adv, rw.false_activation)
        reward = reward.masked_fill(in_hole, rw.hole).masked_fill(truncated, rw.timeout)
        outcome = torch.full_like(self.t, RUNNING)
        outcome = outcome.masked_fill(at_user, REACHED_USER_GOAL).masked_fill(at_adv, REACHED_ADV_GOAL)
        outcome = outcome.masked_fill(in_hole, FELL_IN_HOLE).masked_fill(truncated, TIMED_OUT)
        done = terminated | truncated
        trojan, stage, length = self.trojan, self.stage, self.t
        if autoreset:
            finished = done.nonzero().squeeze(1)
            if finished.numel():
                trojan, stage, length = trojan.clone(), stage.clone(), length.clone()
                self._begin_episodes(finished)
        return StepResult(
            self.observe(), reward, terminated, truncated, done, outcome, correct, trojan, stage, length, adversary
        )

    def _check_actions(self, actions: torch.Tensor) -> None:
        if not isinstance(actions, torch.Tensor):
            raise ShapeError(
                f"actions must be a torch tensor of shape ({self.num_envs},), got {type(actions).__name__}"
            )
        if actions.shape != (self.num_envs,):
            raise ShapeError(f"actions must have shape ({self.num_envs},), got {tuple(actions.shape)}")
        if actions.dtype.is_floating_point or actions.dtype == torch.bool or actions.dtype.is_complex:
            raise ShapeError(f"actions must be integers, got dtype {actions.dtype}")
        bad = (actions < 0) | (actions >= self.num_actions)
        if bool(bad.any()):
            value = int(actions[bad][0])
            raise ShapeError(
                f"action {value} is out of range: this env has {self.num_actions} actions (0..{self.num_actions - 1})"
            )

    # ------------------------------------------------------------------ observation
    def observe_codes(self) -> torch.Tensor:
        """(B, view_size**2) int64 cell codes of the current view, triggers drawn in, row-major."""
        codes = self.grid.gather(1, self.pos[:, None] + self._window)  # (B, v*v) uint8
        t = self.t[:, None]
        if self._on_uniform:
            on_vis = (t >= self.on_step[:, None]) & (t < self.on_step[:, None] + self.config.trigger.duration)
            on_vis = on_vis & (self.on_step[:, None] >= 0) & self._on_patch
            codes = codes.masked_fill(on_vis, self._on_value)
        else:
            k = self.t - self.on_step  # (B,) the ON frame due now (a patch: frame 0 for its whole duration)
            shown = (self.on_step >= 0) & (k >= 0) & (k < self._on_shown)  # (B,)
            frame = k.clamp(0, self._on_frames - 1)  # (B,)
            on_vis = self._frame_mask[frame] & shown[:, None]  # (B, v*v)
            codes = torch.where(on_vis, self._frame_value[frame], codes)
        if self._decoys:
            shown = (self.decoy_step[:, None] == t) & (self.decoy_codes >= 0)  # never in a trojan episode
            codes = torch.where(shown, self.decoy_codes.to(codes.dtype), codes)
        off = self.off_step[:, None]
        off_vis = (t >= off) & (t < off + self.config.trigger.off.duration) & (off >= 0) & self._off_patch
        return codes.masked_fill(off_vis, self._off_value).long()

    def match_on_frames(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, F) bool: whether each row of view codes (B, view_size**2), e.g. :meth:`observe_codes`, shows the
        ON trigger's frame k on its cells (F frames: a sequence's length, else 1; other cells are free)."""
        if codes.dim() != 2 or codes.shape[1] != self.view_size**2:
            raise ShapeError(f"view codes must have shape (B, {self.view_size**2}), got {tuple(codes.shape)}")
        same = codes[:, None, :].to(self.device) == self._frame_value[None].long()  # (B, F, v*v)
        return (same | ~self._frame_mask[None]).all(-1)  # (B, F)

    def observe(self) -> torch.Tensor:
        """(B, obs_dim) float32 one-hot observations (see :mod:`seqtrojan.env.codes` for the layout)."""
        return self._one_hot[self.observe_codes()].view(self.num_envs, self.obs_dim)

    # ------------------------------------------------------------------ hand-built episodes and snapshots
    def set_episode(
        self,
        index: int,
        layout: Layout,
        *,
        on_step: int | None = None,
        off_step: int | None = None,
        stage: int | None = None,
    ) -> None:
        """Replace env ``index``'s episode with a given layout and trigger schedule (t = 0, agent at start).

        ``on_step=None`` makes it a normal-env episode. Used by tests, replays and figures.
        """
        if not 0 <= index < self.num_envs:
            raise ShapeError(f"env index {index} is out of range for {self.num_envs} envs")
        if stage is None:
            matches = [s for s, g in enumerate(self.grids) if g.size == layout.size]
            if not matches:
                raise ConfigError(f"no grid stage has size {layout.size}; stages: {[g.label for g in self.grids]}")
            stage = matches[0]
        if self.grids[stage].size != layout.size:
            raise ConfigError(f"layout size {layout.size} does not match stage {stage} ({self.grids[stage].label})")
        if off_step is not None and (on_step is None or off_step <= on_step):
            raise ConfigError(f"an OFF trigger (off_step={off_step}) needs an earlier ON trigger (on_step={on_step})")
        if off_step is not None and on_step is not None and off_step < on_step + self._on_frames:
            raise ConfigError(
                f"an OFF trigger (off_step={off_step}) must come after the ON sequence's last frame (on_step={on_step}"
                f" + {self._on_frames - 1}), so that it takes effect after the ON trigger does"
            )
        r, n, p = self.view_size // 2, layout.size, self.side
        rows = self.sampler.templates[stage].clone().view(p, p)
        rows[r : r + n, r : r + n] = torch.as_tensor(layout.cells.astype(np.uint8), device=self.device)
        self.grid[index] = rows.view(-1)
        self.pos[index] = self.sampler.starts[stage]
        self.t[index] = 0
        self.stage[index] = stage
        self.trojan[index] = on_step is not None
        self.on_step[index] = -1 if on_step is None else on_step
        self.off_step[index] = -1 if off_step is None else off_step
        if self._decoys:
            self.decoy_step[index] = -1

    def layout(self, index: int) -> Layout:
        """The layout of env ``index``'s current episode."""
        r, p = self.view_size // 2, self.side
        n = self.grids[int(self.stage[index])].size
        cells = self.grid[index].view(p, p)[r : r + n, r : r + n].cpu().numpy().astype(np.int8)
        return Layout(cells)

    def snapshot(self, index: int) -> EpisodeSnapshot:
        r, p = self.view_size // 2, self.side
        t, on, off = int(self.t[index]), int(self.on_step[index]), int(self.off_step[index])
        trig = self.config.trigger
        visible: str | None = None
        drawn: tuple[tuple[tuple[int, int], str], ...] = ()
        on_frame: int | None = None
        if off >= 0 and off <= t < off + trig.off.duration:
            visible = "off"
        elif on >= 0 and on <= t < on + self._on_shown:
            visible = "on"
            frame = min(t - on, self._on_frames - 1)
            drawn = () if self._on_uniform else self._frames[frame]
            on_frame = frame if trig.sequence is not None else None
        pos = int(self.pos[index])
        return EpisodeSnapshot(
            layout=self.layout(index),
            agent=(pos // p - r, pos % p - r),
            t=t,
            trojan=bool(self.trojan[index]),
            on_step=on if on >= 0 else None,
            off_step=off if off >= 0 else None,
            visible=visible,
            adversary_active=bool(self.adversary_active()[index]),
            view_size=self.view_size,
            on_cells=self.config.on_cells,
            off_cells=self.config.off_cells,
            time_limit=self.grids[int(self.stage[index])].time_limit,
            drawn=drawn,
            on_frame=on_frame,
        )
