"""Counter-based random numbers: every draw is a hash of (seed, env stream, episode, purpose, counter).

Why not ``torch.Generator``: with a counter-based scheme an episode's layout and trigger step depend only on
the seed, the env's stream index and the episode's index in that stream -- not on the batch size, on which
other envs reset at the same step, or on the device. So env ``i`` of a batched env equals a single env on
stream ``i``, CPU equals CUDA, and any episode can be regenerated from its key.

All values are 32-bit unsigned integers held in int64 tensors. Multiplications are split into 16-bit halves so
that no intermediate overflows int64 (signed overflow is not something to rely on across devices).
"""

from __future__ import annotations

import torch

M32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9

# Purposes: distinct salts so that draws for different things are independent.
STAGE, TROJAN, ON_STEP, OFF_FLAG, OFF_GAP, HOLE_DRAW, ATTEMPT = (0x1000 + 7919 * i for i in range(7))


def _mul32(x: torch.Tensor, c: int) -> torch.Tensor:
    lo, hi = c & 0xFFFF, c >> 16
    return (x * lo + (((x * hi) & 0xFFFF) << 16)) & M32


def hash32(x: torch.Tensor) -> torch.Tensor:
    """A strong 32-bit integer hash ('lowbias32', C. Wellons) of int64 tensors holding values in [0, 2^32)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def combine(key: torch.Tensor, value: torch.Tensor | int) -> torch.Tensor:
    """Hash ``value`` into ``key``; broadcasts."""
    if isinstance(value, int):
        value = torch.tensor(value & M32, dtype=torch.int64, device=key.device)
    return hash32(key ^ hash32((value + _GOLDEN) & M32))


def seed_keys(seeds: torch.Tensor) -> torch.Tensor:
    """One stream key per env from its seed (int64 tensor of non-negative seeds)."""
    seeds = seeds.to(torch.int64)
    base = torch.full_like(seeds, 0x5EED)
    return combine(combine(base, seeds & M32), (seeds >> 32) & M32)


def uniform(key: torch.Tensor, purpose: int) -> torch.Tensor:
    """A float32 in [0, 1) per key, exact multiples of 2^-24."""
    return (combine(key, purpose) >> 8).to(torch.float32) * (1.0 / (1 << 24))


def below(bits: torch.Tensor, n: torch.Tensor | int) -> torch.Tensor:
    """Map uniform 32-bit values to integers in [0, n) (multiply-shift; bias below n / 2^32)."""
    return (bits * n) >> 32
