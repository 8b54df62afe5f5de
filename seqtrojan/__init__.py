"""seqtrojan: persistent backdoors in recurrent agents -- build, measure, look inside, defend."""

from __future__ import annotations

import os

# OpenMP threads (torch's intra-op pool and the C++ LSTM kernels) sleep while they wait for work instead of
# spinning: libgomp's default spin (GOMP_SPINCOUNT 300000) burns the CPU time that the other thread of a parallel
# region needs when the machine is busy (benchmarks/contention.py; docs/speed.md). This must happen before torch
# loads its OpenMP runtime, so it takes effect only where seqtrojan is imported first (the CLI always is); a
# setting of the user's own (OMP_WAIT_POLICY or GOMP_SPINCOUNT) is kept.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from seqtrojan.env.registration import register_envs
from seqtrojan.minigrid.registration import register_minigrid_envs

__version__ = "0.1.0"

register_envs()
register_minigrid_envs()  # the MiniGrid tasks' ids (seqtrojan/MiniGrid...; MiniGrid itself loads on first make)

__all__ = ["__version__", "register_envs"]
