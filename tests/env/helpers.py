"""Shared helpers for the env tests: tiny hand-built episodes."""

from __future__ import annotations

import dataclasses

import torch

from seqtrojan.env import EnvConfig, Layout, TrojanGridCore

EMPTY7 = """
A . . . . . U
. . . . . . .
. . . . . . .
. . . . . . .
. . . . . . .
. . . . . . .
. . . S . . .
"""

UP, RIGHT, DOWN, LEFT = 0, 1, 2, 3


def make_core(layout: str = EMPTY7, on_step=None, off_step=None, num_envs: int = 1, **cfg) -> TrojanGridCore:
    lay = Layout.from_ascii(layout)
    trigger = cfg.pop("trigger", None)
    config = EnvConfig(size=lay.size, holes=0, **cfg)
    if trigger is not None:
        config = dataclasses.replace(config, trigger=trigger)
    core = TrojanGridCore(config, num_envs, seed=0)
    for i in range(num_envs):
        core.set_episode(i, lay, on_step=on_step, off_step=off_step)
    return core


def act(core: TrojanGridCore, *actions: int, autoreset: bool = False):
    """Apply the same action sequence to every env; return the list of StepResults."""
    results = []
    for a in actions:
        results.append(core.step(torch.full((core.num_envs,), a, dtype=torch.int64), autoreset=autoreset))
    return results
