"""Observation sequences that a real walk through a real grid could produce, and a search for goal-flipping ones.

The free sequence search (:func:`seqtrojan.analysis.search.search_sequences`) lets every view cell take any code,
which probes the network but yields views no grid can show (an adversary's goal under the agent, three of them at
once). Here:

* :func:`frame_is_plausible` / :func:`is_walkable` check a sequence of views against the grid's physics: walls only
  as the border outside a rectangle, the agent's own cell empty, a goal only at the matching corner of the visible
  grid, no trigger, and each view following from the one before by one move (shifted after a move into an empty
  cell, unchanged after a move into the border; a hole or goal would have ended the episode).
* :func:`search_walks` makes sequences walkable by construction: a random walk from the start cell of an N x N
  grid is fixed per restart, and gradient ascent runs on the hole probabilities of the grid's cells (the walk's
  own cells stay empty, walls and goals are where the grid has them), driving the goal units to their trojan-env
  level. A penalty keeps the hole density of the cells the walk reveals near a target (the training density by
  default), so that found walks look like ordinary episodes. Rounded maps (hole where p > 0.5) give one-hot views.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.config import WalkSearchConfig
from seqtrojan.analysis.results import WalkSearchResult
from seqtrojan.analysis.search import final_goal_activation, frozen
from seqtrojan.analysis.unintentional import GoalUnits
from seqtrojan.env.codes import ADV_GOAL, EMPTY, HOLE, NUM_CHANNELS, TRIGGER, USER_GOAL, WALL
from seqtrojan.env.config import adversary_goal_cell, start_cell, user_goal_cell
from seqtrojan.env.layout import Layout

_MOVES = ((-1, 0), (0, 1), (1, 0), (0, -1))  # up, right, down, left


def _full_lines(walls: np.ndarray) -> tuple[int, int, int, int]:
    """Leading/trailing rows and columns that are all wall: (top, bottom, left, right)."""

    def lead(lines: np.ndarray) -> int:
        n = 0
        for line in lines:
            if not line.all():
                break
            n += 1
        return n

    return lead(walls), lead(walls[::-1]), lead(walls.T), lead(walls.T[::-1])


def frame_is_plausible(frame: np.ndarray) -> bool:
    """Could some grid show this (v, v) view of cell codes to an agent still in its episode?"""
    v = frame.shape[0]
    r = v // 2
    if (frame == TRIGGER).any() or frame[r, r] != EMPTY:
        return False
    walls = frame == WALL
    top, bottom, left, right = _full_lines(walls)
    if max(top, bottom, left, right) > r or (top and bottom) or (left and right):
        return False
    rows, cols = np.indices(frame.shape)
    expected = (rows < top) | (rows >= v - bottom) | (cols < left) | (cols >= v - right)
    if not np.array_equal(walls, expected):
        return False
    for code, col in ((USER_GOAL, v - 1 - right), (ADV_GOAL, left)):
        where = np.argwhere(frame == code)
        if len(where) > 1 or (len(where) == 1 and tuple(where[0]) != (top, col)):
            return False
    return True


def _follows(a: np.ndarray, b: np.ndarray) -> bool:
    """Does view ``b`` follow view ``a`` by one of the four moves?"""
    v = a.shape[0]
    r = v // 2
    for dr, dc in _MOVES:
        target = a[r + dr, r + dc]
        if target == WALL and np.array_equal(a, b):
            return True
        if target != EMPTY:
            continue
        rs, cs = slice(max(0, -dr), v - max(0, dr)), slice(max(0, -dc), v - max(0, dc))
        shifted = a[max(0, dr) : v + min(0, dr), max(0, dc) : v + min(0, dc)]
        if np.array_equal(b[rs, cs], shifted):
            return True
    return False


def is_walkable(codes: np.ndarray) -> bool:
    """``codes``: (L, v*v) cell codes of consecutive views. Every view plausible, each following from the last."""
    v = math.isqrt(codes.shape[1])
    frames = codes.reshape(len(codes), v, v)
    if not all(frame_is_plausible(f) for f in frames):
        return False
    return all(_follows(a, b) for a, b in itertools.pairwise(frames))


def random_walks(size: int, length: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, length, 2) positions: walks from the start cell that stay below the top row and never step down
    (up with probability 1/2, left or right 1/4 each, among the moves that stay in the grid)."""
    walks = np.zeros((count, length, 2), np.int64)
    for k in range(count):
        pos = start_cell(size)
        walks[k, 0] = pos
        for t in range(1, length):
            options = [(m, w) for m, w in (((-1, 0), 2), ((0, 1), 1), ((0, -1), 1))
                       if pos[0] + m[0] >= 1 and 0 <= pos[1] + m[1] < size]  # fmt: skip
            weights = np.array([w for _, w in options], float)
            move = options[rng.choice(len(options), p=weights / weights.sum())][0]
            pos = (pos[0] + move[0], pos[1] + move[1])
            walks[k, t] = pos
    return walks


def _views(probs: torch.Tensor, walks: torch.Tensor, view: int) -> torch.Tensor:
    """probs (R, N, N, C) cell distributions, walks (R, L, 2) -> (L, R, view*view*C) observations."""
    r = view // 2
    n = probs.shape[1]
    wall = torch.zeros(NUM_CHANNELS)
    wall[WALL] = 1.0
    padded = wall.expand(probs.shape[0], n + 2 * r, n + 2 * r, NUM_CHANNELS).clone()
    padded[:, r : r + n, r : r + n] = probs
    offsets = torch.arange(view)
    rows = walks[..., 0, None] + offsets  # (R, L, v) in padded coordinates (the view's top row is pos - r + r)
    cols = walks[..., 1, None] + offsets
    batch = torch.arange(probs.shape[0])[:, None, None, None]
    frames = padded[batch, rows[..., :, None], cols[..., None, :]]  # (R, L, v, v, C)
    return frames.reshape(probs.shape[0], walks.shape[1], -1).transpose(0, 1)


def search_walks(
    agent: RecurrentActorCritic, goal: GoalUnits, cfg: WalkSearchConfig, view: int | None = None
) -> tuple[WalkSearchResult, np.ndarray, np.ndarray]:
    """Returns the summary, the rounded walks' views as cell codes (R, L, view*view), and the rounded grids
    (R, N, N). ``view`` (the view's side) defaults to the agent's, read from its observation size."""
    start = time.perf_counter()
    if view is None:
        view = math.isqrt(agent.obs_dim // NUM_CHANNELS)
    n, density = cfg.size, cfg.target_density
    rng = np.random.default_rng(cfg.seed)
    walks_np = random_walks(n, cfg.length, cfg.restarts, rng)
    walks = torch.as_tensor(walks_np)
    fixed = torch.full((cfg.restarts, n, n), -1, dtype=torch.int64)  # -1: free (hole or empty)
    for (row, col), code in ((adversary_goal_cell(n), ADV_GOAL), (user_goal_cell(n), USER_GOAL)):
        fixed[:, row, col] = code
    fixed[torch.arange(cfg.restarts)[:, None], walks[..., 0], walks[..., 1]] = EMPTY
    free = fixed < 0
    revealed = torch.zeros(cfg.restarts, n, n, dtype=torch.bool)
    r = view // 2
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            rr, cc = walks[..., 0] + dr, walks[..., 1] + dc
            ok = (rr >= 0) & (rr < n) & (cc >= 0) & (cc < n)
            idx = torch.arange(cfg.restarts)[:, None].expand_as(rr)
            revealed[idx[ok], rr[ok], cc[ok]] = True
    scored = free & revealed
    logit0 = float(np.log(density / (1 - density))) if 0 < density < 1 else 0.0
    gen = torch.Generator().manual_seed(cfg.seed)
    logits = (logit0 + 0.1 * torch.randn(cfg.restarts, n, n, generator=gen)).requires_grad_()
    fixed_onehot = torch.nn.functional.one_hot(fixed.clamp(min=0), NUM_CHANNELS).float()

    def probs_of(hole: torch.Tensor) -> torch.Tensor:
        soft = torch.stack([1 - hole, hole], -1)  # channels EMPTY, HOLE
        cells = torch.cat([soft, torch.zeros(cfg.restarts, n, n, NUM_CHANNELS - 2)], -1)
        return torch.where(free[..., None], cells, fixed_onehot)

    def revealed_density(hole: torch.Tensor) -> torch.Tensor:
        return (hole * scored).sum((1, 2)) / scored.sum((1, 2)).clamp(min=1)

    optimizer = torch.optim.Adam([logits], lr=cfg.lr)
    with frozen(agent):
        for _ in range(cfg.steps):
            hole = torch.sigmoid(logits)
            penalty = cfg.density_weight * torch.relu(revealed_density(hole) - density)
            loss = (penalty - final_goal_activation(agent, goal, _views(probs_of(hole), walks, view))).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            hole = (torch.sigmoid(logits) > 0.5).float() * free
            rounded = final_goal_activation(agent, goal, _views(probs_of(hole), walks, view))
            density_after = revealed_density(hole)
    grids = torch.where(free, hole.long() * HOLE, fixed).numpy().astype(np.int8)
    codes = _codes(grids, walks_np, view)
    found_mask = (rounded >= cfg.success_at).numpy()
    result = WalkSearchResult(
        cfg,
        int(found_mask.sum()),
        rounded.tolist(),
        sum(is_walkable(c) for c in codes),
        sum(Layout(g).is_solvable() for g, f in zip(grids, found_mask, strict=True) if f),
        density_after.tolist(),
        time.perf_counter() - start,
    )
    return result, codes, grids


def _codes(grids: np.ndarray, walks: np.ndarray, view: int) -> np.ndarray:
    """Cell codes of each walk's views on its grid: (R, L, view*view)."""
    r = view // 2
    padded = np.pad(grids, ((0, 0), (r, r), (r, r)), constant_values=WALL)
    out = np.empty((walks.shape[0], walks.shape[1], view * view), np.int64)
    for k, walk in enumerate(walks):
        for t, (row, col) in enumerate(walk):
            out[k, t] = padded[k, row : row + view, col : col + view].ravel()
    return out
