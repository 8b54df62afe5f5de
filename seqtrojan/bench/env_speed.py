"""Env steps per second of the batched core with random actions.

Actions are drawn up front so that the figure is the env's own cost. Each measurement runs after a warm-up
(which also fills the envs with episodes at all stages of progress, so resets happen at their steady rate).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from seqtrojan.env import EnvConfig, TrojanGridCore


@dataclass(frozen=True)
class EnvSpeed:
    size: int
    holes: int
    num_envs: int
    steps_per_second: float
    resets_per_step: float
    device: str


def measure_env_speed(
    size: int, holes: int, num_envs: int, steps: int = 200, device: str = "cpu", seed: int = 0
) -> EnvSpeed:
    core = TrojanGridCore(EnvConfig(size=size, holes=holes), num_envs, seed=seed, device=device, trojan_probability=0.5)
    gen = torch.Generator(device="cpu").manual_seed(seed)
    actions = torch.randint(0, core.num_actions, (steps + 50, num_envs), generator=gen).to(device)
    for a in actions[:50]:
        core.step(a, check=False)
    _sync(device)
    start = time.perf_counter()
    for a in actions[50:]:
        core.step(a, check=False)
    _sync(device)
    elapsed = time.perf_counter() - start
    finished = sum(int(core.step(a, check=False).done.sum()) for a in actions[:20])  # reset rate, untimed
    return EnvSpeed(size, holes, num_envs, steps * num_envs / elapsed, finished / (20 * num_envs), device)


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
