"""Counter-based random numbers: every draw is a hash of (env seed, episode index, purpose, counter).

Why not ``torch.Generator``: with a counter-based scheme an episode's layout and trigger step depend only on
the env's seed and the episode's index -- not on the batch size, on which other envs reset at the same step, or
on the device. So env ``i`` of a batch seeded ``s`` equals a single env seeded ``s + i``, CPU equals CUDA, and
any episode can be regenerated from its key.

All values are 32-bit unsigned integers held in int64 arrays; no intermediate overflows int64. ``hash32`` and
``combine`` work alike on Python ints, NumPy arrays and torch tensors (the layout sampler runs on NumPy on CPU,
where small-array operations cost a fraction of torch's dispatch).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

Ints = TypeVar("Ints", int, np.ndarray, torch.Tensor)  # int, numpy int64 array or torch int64 tensor

M32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9

# Purposes: distinct salts so that draws for different things are independent.
STAGE, TROJAN, ON_STEP, OFF_FLAG, OFF_GAP, HOLE_DRAW, ATTEMPT = (0x1000 + 7919 * i for i in range(7))
DECOY, DECOY_WHOLE, DECOY_CELL, DECOY_CODE, DECOY_FORCED = (0x1000 + 7919 * i for i in range(7, 12))
"""decoy draws (``trigger.decoys``); a cell's draw adds its index to DECOY_CELL / DECOY_CODE"""


def hash32(x: Ints) -> Ints:
    """A strong 32-bit integer hash of values in [0, 2^32) (ints, int64 arrays or tensors).

    The two-round xor-shift-multiply hash found by C. Wellons' hash-prospector (bias about 0.108). Both
    multipliers are below 2^31, so every product stays below 2^63: no int64 overflow on any device.
    """
    x = x ^ (x >> 16)
    x = (x * 0x21F0AAAD) & M32
    x = x ^ (x >> 15)
    x = (x * 0x735A2D97) & M32
    return x ^ (x >> 15)


def combine(key: Ints, value) -> Ints:
    """Hash ``value`` (an int or an array like ``key``) into ``key``; broadcasts."""
    return hash32(key ^ hash32((value + _GOLDEN) & M32))


def seed_keys(seeds: torch.Tensor) -> torch.Tensor:
    """One stream key per env from its seed (int64 tensor of non-negative seeds)."""
    seeds = seeds.to(torch.int64)
    base = torch.full_like(seeds, 0x5EED)
    return combine(combine(base, seeds & M32), (seeds >> 32) & M32)


def uniform(key: torch.Tensor, purpose: int) -> torch.Tensor:
    """A float32 in [0, 1) per key, exact multiples of 2^-24."""
    return (combine(key, purpose) >> 8).to(torch.float32) * (1.0 / (1 << 24))


def below(bits: Ints, n) -> Ints:
    """Map uniform 32-bit values to integers in [0, n) (multiply-shift; bias below n / 2^32)."""
    return (bits * n) >> 32
