"""Scripted agents for the batched core: a random agent and a privileged shortest-path oracle.

The oracle reads the full layout and which goal is currently correct from the core (it is not a legal
partially observed policy); it is the yardstick for the env's semantics: with evaluation trigger steps it
reaches the correct goal in every solvable layout, in both the normal and the trojan env.
"""

from __future__ import annotations

import torch

from seqtrojan.env.codes import ACTION_SETS, ADV_GOAL, HOLE, USER_GOAL, WALL
from seqtrojan.env.core import TrojanGridCore

_FAR = 1 << 20


class RandomAgent:
    """Uniformly random actions, reproducible from a seed."""

    def __init__(self, core: TrojanGridCore, seed: int = 0) -> None:
        self.core = core
        self.generator = torch.Generator(device="cpu").manual_seed(seed)

    def act(self, obs: torch.Tensor | None = None) -> torch.Tensor:
        actions = torch.randint(0, self.core.num_actions, (self.core.num_envs,), generator=self.generator)
        return actions.to(self.core.device)


class OracleAgent:
    """Follows a shortest hole-free path to whichever goal is correct at the current step."""

    def __init__(self, core: TrojanGridCore) -> None:
        self.core = core
        self._episode = torch.full_like(core.episode, -2)
        p = core.side
        self._dist_user = torch.full((core.num_envs, p * p), _FAR, dtype=torch.int64, device=core.device)
        self._dist_adv = self._dist_user.clone()
        self._deltas = torch.tensor([dr * p + dc for dr, dc in ACTION_SETS[core.config.actions]], device=core.device)

    def act(self, obs: torch.Tensor | None = None) -> torch.Tensor:
        core = self.core
        changed = (core.episode != self._episode) | (core.t == 0)
        if bool(changed.any()):
            idx = changed.nonzero().squeeze(1)
            self._dist_user[idx] = distance_to(core.grid[idx], USER_GOAL, core.side)
            self._dist_adv[idx] = distance_to(core.grid[idx], ADV_GOAL, core.side)
            self._episode = core.episode.clone()
        dist = torch.where(self.heads_for_adversary()[:, None], self._dist_adv, self._dist_user)
        neighbours = (core.pos[:, None] + self._deltas[None, :]).clamp(0, dist.shape[1] - 1)
        return dist.gather(1, neighbours).argmin(dim=1)

    def heads_for_adversary(self) -> torch.Tensor:
        """(B,) bool: which goal each env walks to now; the oracle follows the correct one."""
        return self.core.adversary_active()


def distance_to(grid: torch.Tensor, goal_code: int, side: int) -> torch.Tensor:
    """Moves from every cell to the cell holding ``goal_code`` over non-hole, non-wall cells (4-connected).

    ``grid``: (k, side*side) cell codes. Cells that cannot reach it (and holes, walls, the other goal) get a
    large value.
    """
    k = grid.shape[0]
    cells = grid.view(k, side, side)
    passable = (cells != HOLE) & (cells != WALL) & ((cells == goal_code) | (cells != USER_GOAL + ADV_GOAL - goal_code))
    dist = torch.where(cells == goal_code, 0, _FAR).to(torch.int64)
    for _ in range(side * side):
        best = dist.clone()
        best[:, 1:, :] = torch.minimum(best[:, 1:, :], dist[:, :-1, :] + 1)
        best[:, :-1, :] = torch.minimum(best[:, :-1, :], dist[:, 1:, :] + 1)
        best[:, :, 1:] = torch.minimum(best[:, :, 1:], dist[:, :, :-1] + 1)
        best[:, :, :-1] = torch.minimum(best[:, :, :-1], dist[:, :, 1:] + 1)
        best = torch.where(passable, best, _FAR)
        if torch.equal(best, dist):
            break
        dist = best
    return dist.view(k, side * side)
