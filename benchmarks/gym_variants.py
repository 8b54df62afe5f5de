"""Training speed of the Gymnasium path's variants, interleaved round by round, beside the env's vector rate.

    python benchmarks/gym_variants.py --rounds 5 --json variants.json

The host's speed drifts by tens of percent between minutes, so variants measured in separate runs cannot be
compared; here every round measures, one after the other: Gymnasium's ``SyncVectorEnv`` of the preset's envs under
random actions ((v) of ``benchmarks/gym_throughput.py``), then training (the logged median steps/s of
``gym_throughput.train_rate``, ``--steps`` env steps) with each variant:

- ``dense``: env ``sync``, the first layer's dense product on the one-hot view (as before the sparse projection);
- ``sparse``: env ``sync``, the sparse projection (the default);
- ``workers``: the sparse projection and ``env.vectorization: workers`` with 2 workers;
- ``workers_t2``: the same with 2 torch threads.

Printed: per variant the median and range over rounds of its steps/s and of its ratio to the same round's vector
rate (the issue's "env rate"). Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path
from typing import Any

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
sys.path.insert(0, str(Path(__file__).parent))
import gym_throughput as gt

from seqtrojan.agent import fast_lstm

VARIANTS: dict[str, dict[str, Any]] = {
    "dense": {"workers": 0, "threads": 1, "sparse": False},
    "sparse": {"workers": 0, "threads": 1, "sparse": True},
    "workers": {"workers": 2, "threads": 1, "sparse": True},
    "workers_t2": {"workers": 2, "threads": 2, "sparse": True},
}
SPARSE_MIN_INPUTS = fast_lstm.SPARSE_MIN_INPUTS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="minigrid_two_goals", choices=gt.PRESETS)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=65536)
    parser.add_argument("--env-steps", type=int, default=30000)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    names = args.variants.split(",")
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    print(f"gym variants: {args.preset}, {args.rounds} rounds, {args.steps} training steps; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)  # fmt: skip
    runs: list[dict[str, Any]] = []
    for r in range(args.rounds):
        gt.WORKERS = 0
        torch.set_num_threads(1)
        cfg = gt.load_config(args.preset)
        run: dict[str, Any] = {"round": r, "load_avg": os.getloadavg()}
        run["vector_sps"] = gt.vector_rate(cfg, args.env_steps, 0, 0.0)
        for name in names:
            v = VARIANTS[name]
            gt.WORKERS = v["workers"]
            fast_lstm.SPARSE_MIN_INPUTS = SPARSE_MIN_INPUTS if v["sparse"] else 1 << 62
            torch.set_num_threads(v["threads"])
            run[name] = gt.train_rate(args.preset, args.steps, v["threads"], 0)["logged_sps"]
        runs.append(run)
        shown = ", ".join(f"{k} {run[k]:,.0f}" for k in ("vector_sps", *names))
        print(f"  round {r + 1}: {shown}  (load {run['load_avg'][0]:.2f})", flush=True)
    print("training steps/s, median (range) over rounds; ratio to the same round's SyncVectorEnv rate:")
    vector = [run["vector_sps"] for run in runs]
    print(f"  {'SyncVectorEnv':<12} {statistics.median(vector):>8,.0f}  ({min(vector):,.0f} - {max(vector):,.0f})")
    medians = {}
    for name in names:
        sps = [run[name] for run in runs]
        ratio = [run[name] / run["vector_sps"] for run in runs]
        medians[name] = {"sps": statistics.median(sps), "ratio": statistics.median(ratio)}
        print(f"  {name:<12} {statistics.median(sps):>8,.0f}  ({min(sps):,.0f} - {max(sps):,.0f})   ratio "
              f"{statistics.median(ratio):.3f} ({min(ratio):.3f} - {max(ratio):.3f})")  # fmt: skip
    if args.json:
        meta = {"preset": args.preset, "rounds": args.rounds, "steps": args.steps, "variants": VARIANTS,
                "cpu_count": os.cpu_count(), "torch": torch.__version__, "load_avg_end": os.getloadavg()}  # fmt: skip
        Path(args.json).write_text(json.dumps({"meta": meta, "median": medians, "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
