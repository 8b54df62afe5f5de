"""Hole layouts: a single-grid value type for hand-built layouts and replays, and the batched sampler.

Sampling (docs/environment.md, Grid and layout): H holes uniformly at random on cells other than the start and the
two goals, afresh every episode, resampled until both goals are reachable from the start by a 4-connected path.

The sampler works on the *padded* grid of side ``P = N_max + view_size - 1`` shared by every env of a batch
(an env whose own grid is smaller sees walls beyond it). Solvability is a flood fill in which each padded row
is one 64-bit word, so one fill step over k grids is a handful of tensor ops on a (k, P) tensor.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from seqtrojan.env import rng
from seqtrojan.env.codes import ADV_GOAL, ASCII_SYMBOLS, EMPTY, HOLE, USER_GOAL, WALL
from seqtrojan.env.config import GridSpec, adversary_goal_cell, start_cell, user_goal_cell
from seqtrojan.errors import LayoutError

_SYMBOL_CODES = {s: c for c, s in ASCII_SYMBOLS.items()}
_SORT_SENTINEL = 1 << 40
_COUNTER_STRIDE = 1 << 13  # > any candidate count (N <= 61 gives at most 3718 candidates)
_MAX_DEDUPE_ROUNDS = 256
PROBE_SAMPLES = 1024
"""Random layouts :meth:`LayoutSampler.probe` draws per grid to measure the solvable fraction."""
LAYOUT_FAILURE_EXPONENT = 30.0
"""A grid is accepted when an episode's reset exhausts ``max_layout_tries`` with probability at most e^-30."""


def layout_tries_needed(fraction: float, holes: int, samples: int = PROBE_SAMPLES) -> int | None:
    """Fewest layout tries per episode for which running out has probability <= e^-30; None if no number does.

    ``fraction`` is the solvable share measured over ``samples`` random layouts. Tries are independent, so
    ``t`` tries all fail with probability ``(1 - fraction) ** t``; the rule asks for that to be <= e^-30. A grid
    with at most one hole is always solvable (a grid stays connected when any one cell is removed) and needs 1
    try. Otherwise some layouts are unsolvable (two holes can wall a corner goal in), so the failure share is
    taken as at least ``1 / samples``: a probe that saw no failure is no proof that there are none (then 5 tries
    for the default 1024 samples).
    """
    if holes <= 1:
        return 1
    failure = max(1.0 - fraction, 1.0 / samples)
    if failure >= 1.0:
        return None
    return max(1, math.ceil(LAYOUT_FAILURE_EXPONENT / -math.log(failure) - 1e-9))


@dataclass(frozen=True, eq=False)
class Layout:
    """One N x N grid: ``cells[r, c]`` is EMPTY, HOLE, USER_GOAL or ADV_GOAL (row 0 is the top).

    The start is always the bottom row's centre; the user's goal the top-right corner; the adversary's goal the
    top-left corner.
    """

    cells: np.ndarray

    def __post_init__(self) -> None:
        cells = np.asarray(self.cells)
        if cells.ndim != 2 or cells.shape[0] != cells.shape[1]:
            raise LayoutError(f"a layout must be a square 2-D array, got shape {cells.shape}")
        n = cells.shape[0]
        if n < 5 or n % 2 == 0:
            raise LayoutError(f"layout side must be odd and >= 5, got {n}")
        if cells[user_goal_cell(n)] != USER_GOAL or cells[adversary_goal_cell(n)] != ADV_GOAL:
            raise LayoutError("a layout needs the user goal at the top-right and the adversary goal at the top-left")
        allowed = {EMPTY, HOLE, USER_GOAL, ADV_GOAL}
        if not set(np.unique(cells).tolist()) <= allowed:
            raise LayoutError(f"layout cells must be empty, hole or goal codes {sorted(allowed)}")
        if int((cells == USER_GOAL).sum()) != 1 or int((cells == ADV_GOAL).sum()) != 1:
            raise LayoutError("a layout has exactly one user goal and one adversary goal")
        start_row, start_col = start_cell(n)
        if cells[start_row, start_col] != EMPTY:
            raise LayoutError(f"the start cell (row {start_row}, col {start_col}) must be empty")
        object.__setattr__(self, "cells", cells.astype(np.int8))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Layout) and np.array_equal(self.cells, other.cells)

    def __hash__(self) -> int:
        return hash(self.cells.tobytes())

    @property
    def size(self) -> int:
        return int(self.cells.shape[0])

    @property
    def start(self) -> tuple[int, int]:
        return start_cell(self.size)

    @property
    def user_goal(self) -> tuple[int, int]:
        return user_goal_cell(self.size)

    @property
    def adversary_goal(self) -> tuple[int, int]:
        return adversary_goal_cell(self.size)

    @property
    def num_holes(self) -> int:
        return int((self.cells == HOLE).sum())

    @classmethod
    def empty(cls, size: int) -> Layout:
        cells = np.full((size, size), EMPTY, dtype=np.int8)
        cells[adversary_goal_cell(size)], cells[user_goal_cell(size)] = ADV_GOAL, USER_GOAL
        return cls(cells)

    @classmethod
    def from_ascii(cls, text: str) -> Layout:
        """Parse rows of ``. O U A`` (``S`` may mark the start), separated by newlines; spaces are ignored."""
        rows = [line.replace(" ", "") for line in text.strip().splitlines() if line.strip()]
        try:
            cells = np.array([[_SYMBOL_CODES["." if ch == "S" else ch] for ch in row] for row in rows], dtype=np.int8)
        except KeyError as err:
            raise LayoutError(f"unknown layout symbol {err.args[0]!r}; use . O U A S") from None
        except ValueError:
            raise LayoutError("layout rows have different lengths") from None
        return cls(cells)

    def to_ascii(self) -> str:
        return "\n".join(" ".join(ASCII_SYMBOLS[int(c)] for c in row) for row in self.cells)

    def is_solvable(self) -> bool:
        """Both goals reachable from the start by 4-connected moves over non-hole cells (plain BFS)."""
        n, seen = self.size, {self.start}
        queue = deque([self.start])
        while queue:
            r, c = queue.popleft()
            for dr, dc in ((-1, 0), (0, 1), (1, 0), (0, -1)):
                nr, nc = r + dr, c + dc
                if 0 <= nr < n and 0 <= nc < n and (nr, nc) not in seen and self.cells[nr, nc] != HOLE:
                    seen.add((nr, nc))
                    queue.append((nr, nc))
        return self.adversary_goal in seen and self.user_goal in seen


class _NumpyOps:
    """The few array operations the sampler needs, on NumPy (CPU: small-array ops cost ~1 us, not ~5 us)."""

    @staticmethod
    def convert(x: torch.Tensor) -> np.ndarray:
        return x.numpy()

    @staticmethod
    def back(x: np.ndarray, device: torch.device) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x))

    arange = staticmethod(lambda n, like: np.arange(n, dtype=np.int64))
    zeros_bool = staticmethod(lambda shape, like: np.zeros(shape, dtype=bool))
    sort_rows = staticmethod(lambda a: np.sort(a, axis=1))
    gather_rows = staticmethod(lambda a, idx: np.take_along_axis(a, idx, axis=1))
    repeat_each = staticmethod(lambda a, n: np.repeat(a, n))
    tile = staticmethod(lambda a, n: np.tile(a, n))
    where = staticmethod(np.where)
    to_int64 = staticmethod(lambda a: a.astype(np.int64))
    argmax_rows = staticmethod(lambda a: a.argmax(1))

    @staticmethod
    def set_true(cells: np.ndarray, idx: np.ndarray) -> None:
        np.put_along_axis(cells, idx, True, axis=1)


class _TorchOps:
    """The same operations on torch tensors (CUDA)."""

    convert = staticmethod(lambda x: x)
    back = staticmethod(lambda x, device: x)
    arange = staticmethod(lambda n, like: torch.arange(n, device=like.device))
    zeros_bool = staticmethod(lambda shape, like: torch.zeros(shape, dtype=torch.bool, device=like.device))
    sort_rows = staticmethod(lambda a: a.sort(dim=1).values)
    gather_rows = staticmethod(lambda a, idx: torch.gather(a, 1, idx))
    repeat_each = staticmethod(lambda a, n: a.repeat_interleave(n))
    tile = staticmethod(lambda a, n: a.repeat(n))
    where = staticmethod(torch.where)
    to_int64 = staticmethod(lambda a: a.to(torch.int64))
    argmax_rows = staticmethod(lambda a: a.to(torch.int8).argmax(1))

    @staticmethod
    def set_true(cells: torch.Tensor, idx: torch.Tensor) -> None:
        cells.scatter_(1, idx, True)


class LayoutSampler:
    """Samples solvable hole layouts for a batch of envs, each env on one of several grid stages.

    Tensors in and out; inside, the work runs on NumPy arrays on CPU and on torch tensors on CUDA (one
    implementation over both, see ``_NumpyOps``/``_TorchOps``), with identical results.
    """

    def __init__(
        self, grids: Sequence[GridSpec], view_size: int, max_tries: int, device: torch.device, backend: str = "auto"
    ) -> None:
        self.grids = tuple(grids)
        self.radius = view_size // 2
        self.n_max = max(g.size for g in self.grids)
        self.side = self.n_max + 2 * self.radius
        self.max_tries = max_tries
        self.attempts_per_round = 1
        """layouts tried per env in one batched round; set from the solvable fraction by the env core"""
        self.device = device
        p, r = self.side, self.radius
        s_count = len(self.grids)
        templates = np.full((s_count, p, p), WALL, dtype=np.uint8)
        candidates = np.zeros((s_count, p, p), dtype=bool)
        cand_cells = np.zeros((s_count, max(g.size**2 - 3 for g in self.grids)), dtype=np.int64)
        starts = np.zeros(s_count, dtype=np.int64)
        for s, g in enumerate(self.grids):
            n = g.size
            (adv_row, adv_col), (user_row, user_col), (start_row, start_col) = g.adversary_goal, g.user_goal, g.start
            templates[s, r : r + n, r : r + n] = EMPTY
            templates[s, r + adv_row, r + adv_col] = ADV_GOAL
            templates[s, r + user_row, r + user_col] = USER_GOAL
            candidates[s, r : r + n, r : r + n] = True
            for row, col in (g.adversary_goal, g.user_goal, g.start):
                candidates[s, r + row, r + col] = False
            flat = np.flatnonzero(candidates[s])
            cand_cells[s, : len(flat)] = flat
            starts[s] = (r + start_row) * p + r + start_col
        holes = np.array([g.holes for g in self.grids], dtype=np.int64)
        n_cand = np.array([g.size**2 - 3 for g in self.grids], dtype=np.int64)
        tables = {
            "templates": templates.reshape(s_count, p * p),
            "candidates": candidates.reshape(s_count, p * p),
            "cand_cells": cand_cells,
            "n_cand": n_cand,
            "pick_holes": holes <= n_cand - holes,
            "n_pick": np.minimum(holes, n_cand - holes),
            "starts": starts,
            "sizes": np.array([g.size for g in self.grids], dtype=np.int64),
            "pow2": np.array([1 << i for i in range(p)], dtype=np.int64),
        }
        if backend == "auto":
            backend = "numpy" if device.type == "cpu" else "torch"
        if backend == "numpy" and device.type != "cpu":
            raise ValueError("the numpy layout backend runs on CPU only")
        # NumPy or torch: the work arrays below are ndarrays or tensors alike, so they are typed Any.
        self.ops: Any = _NumpyOps if backend == "numpy" else _TorchOps
        # Torch copies on the env's device (the core reads templates and starts) and the work arrays.
        self.templates = torch.as_tensor(tables["templates"], device=device)
        self.starts = torch.as_tensor(tables["starts"], device=device)
        self._x: dict[str, Any] = {
            k: (v if self.ops is _NumpyOps else torch.as_tensor(v, device=device)) for k, v in tables.items()
        }

    # ------------------------------------------------------------------ public, tensors in and out
    def sample(self, keys: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Solvable hole masks ``(k, P*P)`` bool for episode keys ``(k,)`` on grid stages ``(k,)``.

        Each round tries ``attempts_per_round`` layouts per env at once (attempt ``a`` is a hash of the key and
        ``a``) and keeps the first solvable one, so an env's layout does not depend on the round size. Raises
        LayoutError naming the grid if some env finds no solvable layout within ``max_tries``.
        """
        ops = self.ops
        keys_x, stages_x = ops.convert(keys), ops.convert(stages)
        k = keys_x.shape[0]
        holes = ops.zeros_bool((k, self.side * self.side), keys_x)
        todo = ops.arange(k, keys_x)
        attempt = 0
        while todo.shape[0]:
            if attempt >= self.max_tries:
                g = self.grids[int(stages_x[todo[0]])]
                raise LayoutError(
                    f"no solvable layout found for size={g.size}, holes={g.holes} within {self.max_tries} tries; "
                    "use fewer holes or raise env.max_layout_tries"
                )
            n, tries = todo.shape[0], min(self.attempts_per_round, self.max_tries - attempt)
            salts = rng.ATTEMPT + attempt + ops.arange(tries, keys_x)
            trial_keys = rng.combine(ops.repeat_each(keys_x[todo], tries), ops.tile(salts, n))
            trial_stages = ops.repeat_each(stages_x[todo], tries)
            masks = self._hole_masks(trial_keys, trial_stages)
            ok = self._solvable(masks, trial_stages).reshape(n, tries)
            found = ok.any(1)
            chosen = masks.reshape(n, tries, -1)[ops.arange(n, keys_x), ops.argmax_rows(ok)]
            holes[todo[found]] = chosen[found]
            todo = todo[~found]
            attempt += tries
        return ops.back(holes, self.device)

    def hole_masks(self, keys: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Uniformly random hole sets (no solvability check) as ``(k, P*P)`` bool masks."""
        return self.ops.back(self._hole_masks(self.ops.convert(keys), self.ops.convert(stages)), self.device)

    def solvable(self, holes: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Whether both goals are 4-connected to the start, for hole masks ``(k, P*P)``; ``(k,)`` bool."""
        return self.ops.back(self._solvable(self.ops.convert(holes), self.ops.convert(stages)), self.device)

    def probe(self, samples: int = PROBE_SAMPLES) -> list[float]:
        """Fraction of random layouts that are solvable, per stage (used to refuse near-impossible grids early)."""
        fractions = []
        for s in range(len(self.grids)):
            keys = rng.seed_keys(torch.arange(samples) + 0xC0FFEE * (s + 1)).to(self.device)
            stages = torch.full((samples,), s, dtype=torch.int64, device=self.device)
            fractions.append(float(self.solvable(self.hole_masks(keys, stages), stages).float().mean()))
        return fractions

    # ------------------------------------------------------------------ work, on NumPy or torch arrays
    def _hole_masks(self, keys, stages):
        """Draws min(H, M - H) distinct candidates by drawing with replacement and redrawing duplicates (uniform
        over subsets by symmetry); when H > M/2 the drawn cells are the ones left free."""
        ops, x = self.ops, self._x
        k = keys.shape[0]
        n_pick, n_cand = x["n_pick"][stages], x["n_cand"][stages]
        width = int(n_pick.max()) if k else 0
        cells = ops.zeros_bool((k, self.side * self.side + 1), keys)
        if width > 0:
            draw_keys = rng.combine(keys, rng.HOLE_DRAW)[:, None]
            positions = ops.arange(width, keys)
            valid = positions[None, :] < n_pick[:, None]
            values = ops.where(valid, self._draw(draw_keys, positions, 0, n_cand), _SORT_SENTINEL)
            for round_ in range(1, _MAX_DEDUPE_ROUNDS + 1):
                values = ops.sort_rows(values)
                dup = (values[:, 1:] == values[:, :-1]) & (values[:, 1:] < _SORT_SENTINEL)
                if not bool(dup.any()):
                    break
                redraw = self._draw(draw_keys, positions, round_, n_cand)
                values[:, 1:] = ops.where(dup, redraw[:, 1:], values[:, 1:])
            else:  # pragma: no cover - each round halves the duplicates; 256 rounds do not fail in practice
                raise LayoutError("hole sampling did not converge")
            flat = ops.gather_rows(x["cand_cells"][stages], values.clip(max=x["cand_cells"].shape[1] - 1))
            ops.set_true(cells, ops.where(valid, flat, self.side * self.side))
        picked = cells[:, :-1]
        cand = x["candidates"][stages]
        return ops.where(x["pick_holes"][stages][:, None], picked, cand & ~picked)

    def _draw(self, keys, positions, round_: int, n):
        counters = rng.hash32((positions + round_ * _COUNTER_STRIDE + 0x9E3779B9) & rng.M32)
        return rng.below(rng.hash32(keys ^ counters[None, :]), n[:, None])

    def _solvable(self, holes, stages):
        """Flood fill from the start where each padded row is one int64 bit mask (bit c = column c)."""
        ops, x = self.ops, self._x
        k, p, r = holes.shape[0], self.side, self.radius
        free = (x["templates"][stages] != WALL) & ~holes
        free_rows = (ops.to_int64(free.reshape(k, p, p)) * x["pow2"]).sum(-1)  # (k, P)
        start = x["starts"][stages]
        reach = free_rows * 0
        reach[ops.arange(k, free_rows), start // p] = x["pow2"][start % p]
        n = x["sizes"][stages]
        adv_bit, user_bit = x["pow2"][r], x["pow2"][r + n - 1]
        for step in range(p * p):
            grown = reach | (reach << 1) | (reach >> 1)
            grown[:, 1:] |= reach[:, :-1]
            grown[:, :-1] |= reach[:, 1:]
            grown &= free_rows
            if step % 4 == 3:
                top = grown[:, r]
                done = ((top & adv_bit) != 0) & ((top & user_bit) != 0)
                if bool((done | (grown == reach).all(1)).all()):
                    reach = grown
                    break
            reach = grown
        top = reach[:, r]
        return ((top & adv_bit) != 0) & ((top & user_bit) != 0)
