"""Hole layouts: a single-grid value type for hand-built layouts and replays, and the batched sampler.

Sampling follows SPEC section 1: H holes uniformly at random on cells other than the start and the two goals,
afresh every episode, resampled until both goals are reachable from the start by a 4-connected path.

The sampler works on the *padded* grid of side ``P = N_max + view_size - 1`` shared by every env of a batch
(an env whose own grid is smaller sees walls beyond it). Solvability is a flood fill in which each padded row
is one 64-bit word, so one fill step over k grids is a handful of tensor ops on a (k, P) tensor.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.env import rng
from seqtrojan.env.codes import ADV_GOAL, ASCII_SYMBOLS, EMPTY, HOLE, USER_GOAL, WALL
from seqtrojan.env.config import GridSpec
from seqtrojan.errors import LayoutError

_SYMBOL_CODES = {s: c for c, s in ASCII_SYMBOLS.items()}
_SORT_SENTINEL = 1 << 40
_COUNTER_STRIDE = 1 << 13  # > any candidate count (N <= 61 gives at most 3718 candidates)
_MAX_DEDUPE_ROUNDS = 256


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
        if cells[0, n - 1] != USER_GOAL or cells[0, 0] != ADV_GOAL:
            raise LayoutError("a layout needs the user goal at the top-right and the adversary goal at the top-left")
        allowed = {EMPTY, HOLE, USER_GOAL, ADV_GOAL}
        if not set(np.unique(cells).tolist()) <= allowed:
            raise LayoutError(f"layout cells must be empty, hole or goal codes {sorted(allowed)}")
        if int((cells == USER_GOAL).sum()) != 1 or int((cells == ADV_GOAL).sum()) != 1:
            raise LayoutError("a layout has exactly one user goal and one adversary goal")
        if cells[n - 1, n // 2] != EMPTY:
            raise LayoutError(f"the start cell (row {n - 1}, col {n // 2}) must be empty")
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
        return (self.size - 1, self.size // 2)

    @property
    def num_holes(self) -> int:
        return int((self.cells == HOLE).sum())

    @classmethod
    def empty(cls, size: int) -> Layout:
        cells = np.full((size, size), EMPTY, dtype=np.int8)
        cells[0, 0], cells[0, size - 1] = ADV_GOAL, USER_GOAL
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
        return (0, 0) in seen and (0, n - 1) in seen


class LayoutSampler:
    """Samples solvable hole layouts for a batch of envs, each env on one of several grid stages."""

    def __init__(self, grids: Sequence[GridSpec], view_size: int, max_tries: int, device: torch.device) -> None:
        self.grids = tuple(grids)
        self.radius = view_size // 2
        self.n_max = max(g.size for g in self.grids)
        self.side = self.n_max + 2 * self.radius
        self.max_tries = max_tries
        self.device = device
        p, r = self.side, self.radius
        s_count = len(self.grids)
        templates = np.full((s_count, p, p), WALL, dtype=np.uint8)
        candidates = np.zeros((s_count, p, p), dtype=bool)
        n_cand = max(g.size**2 - 3 for g in self.grids)
        cand_cells = np.zeros((s_count, n_cand), dtype=np.int64)
        starts = np.zeros(s_count, dtype=np.int64)
        for s, g in enumerate(self.grids):
            n = g.size
            templates[s, r : r + n, r : r + n] = EMPTY
            templates[s, r, r] = ADV_GOAL
            templates[s, r, r + n - 1] = USER_GOAL
            candidates[s, r : r + n, r : r + n] = True
            candidates[s, r, r] = candidates[s, r, r + n - 1] = candidates[s, r + n - 1, r + n // 2] = False
            flat = np.flatnonzero(candidates[s])
            cand_cells[s, : len(flat)] = flat
            starts[s] = (r + n - 1) * p + r + n // 2
        t = lambda a: torch.as_tensor(a, device=device)  # noqa: E731
        self.templates = t(templates.reshape(s_count, p * p))
        self.candidates = t(candidates.reshape(s_count, p * p))
        self.cand_cells = t(cand_cells)
        self.n_cand = t(np.array([g.size**2 - 3 for g in self.grids], dtype=np.int64))
        holes = np.array([g.holes for g in self.grids], dtype=np.int64)
        self.pick_holes = t(holes <= (self.n_cand.cpu().numpy() - holes))
        self.n_pick = t(np.minimum(holes, self.n_cand.cpu().numpy() - holes))
        self.starts = t(starts)
        self.sizes = t(np.array([g.size for g in self.grids], dtype=np.int64))
        self._pow2 = t(np.array([1 << i for i in range(p)], dtype=np.int64))

    # ------------------------------------------------------------------ sampling
    def sample(self, keys: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Solvable hole masks ``(k, P*P)`` for episode keys ``(k,)`` on grid stages ``(k,)``.

        Raises LayoutError naming the grid if some env finds no solvable layout within ``max_tries``.
        """
        k = keys.shape[0]
        holes = torch.zeros((k, self.side * self.side), dtype=torch.bool, device=self.device)
        todo = torch.arange(k, device=self.device)
        for attempt in range(self.max_tries):
            attempt_keys = rng.combine(keys[todo], rng.ATTEMPT + attempt)
            mask = self.hole_masks(attempt_keys, stages[todo])
            ok = self.solvable(mask, stages[todo])
            holes[todo[ok]] = mask[ok]
            todo = todo[~ok]
            if todo.numel() == 0:
                return holes
        g = self.grids[int(stages[todo[0]])]
        raise LayoutError(
            f"no solvable layout found for size={g.size}, holes={g.holes} within {self.max_tries} tries; "
            "use fewer holes or raise env.max_layout_tries"
        )

    def hole_masks(self, keys: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Uniformly random H-subsets of the candidate cells (no solvability check), as ``(k, P*P)`` masks.

        Draws min(H, M - H) distinct candidates by drawing with replacement and redrawing duplicates (the result
        is uniform over subsets by symmetry); when H > M/2 the drawn cells are the ones left free.
        """
        k, dev = keys.shape[0], self.device
        n_pick, n_cand = self.n_pick[stages], self.n_cand[stages]
        width = int(n_pick.max()) if k else 0
        cells = torch.zeros((k, self.side * self.side + 1), dtype=torch.bool, device=dev)
        if width > 0:
            draw_keys = rng.combine(keys, rng.HOLE_DRAW)[:, None]
            positions = torch.arange(width, device=dev)
            valid = positions[None, :] < n_pick[:, None]
            values = self._draw(draw_keys, positions, 0, n_cand)
            values = torch.where(valid, values, _SORT_SENTINEL)
            for round_ in range(1, _MAX_DEDUPE_ROUNDS + 1):
                values, _ = values.sort(dim=1)
                dup = torch.zeros_like(valid)
                dup[:, 1:] = (values[:, 1:] == values[:, :-1]) & (values[:, 1:] < _SORT_SENTINEL)
                if not bool(dup.any()):
                    break
                values = torch.where(dup, self._draw(draw_keys, positions, round_, n_cand), values)
            else:  # pragma: no cover - each round halves the duplicates; 256 rounds do not fail in practice
                raise LayoutError("hole sampling did not converge")
            flat = torch.gather(self.cand_cells[stages], 1, values.clamp(max=self.cand_cells.shape[1] - 1))
            flat = torch.where(valid, flat, self.side * self.side)
            cells.scatter_(1, flat, True)
        picked = cells[:, :-1]
        cand = self.candidates[stages]
        return torch.where(self.pick_holes[stages, None], picked, cand & ~picked)

    def _draw(self, keys: torch.Tensor, positions: torch.Tensor, round_: int, n: torch.Tensor) -> torch.Tensor:
        counters = rng.hash32((positions + round_ * _COUNTER_STRIDE + 0x9E3779B9) & rng.M32)
        return rng.below(rng.hash32(keys ^ counters[None, :]), n[:, None])

    # ------------------------------------------------------------------ solvability
    def solvable(self, holes: torch.Tensor, stages: torch.Tensor) -> torch.Tensor:
        """Whether both goals are 4-connected to the start, for hole masks ``(k, P*P)``; returns ``(k,)`` bool."""
        k, p, r = holes.shape[0], self.side, self.radius
        if k == 0:
            return torch.zeros(0, dtype=torch.bool, device=self.device)
        free = (self.templates[stages] != WALL) & ~holes
        free_rows = (free.view(k, p, p).to(torch.int64) * self._pow2).sum(-1)  # (k, P): bit c = column c
        rows = torch.arange(k, device=self.device)
        start = self.starts[stages]
        reach = torch.zeros_like(free_rows)
        reach[rows, start // p] = self._pow2[start % p]
        n = self.sizes[stages]
        adv_bit, user_bit = self._pow2[r], self._pow2[r + n - 1]
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

    def probe(self, samples: int = 1024) -> list[float]:
        """Fraction of random layouts that are solvable, per stage (used to refuse near-impossible grids early)."""
        fractions = []
        for s in range(len(self.grids)):
            keys = rng.seed_keys(torch.arange(samples, device=self.device) + 0xC0FFEE * (s + 1))
            stages = torch.full((samples,), s, dtype=torch.int64, device=self.device)
            fractions.append(float(self.solvable(self.hole_masks(keys, stages), stages).float().mean()))
        return fractions
