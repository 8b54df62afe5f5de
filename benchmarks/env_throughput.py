"""Print env steps/s of the batched grid world with random actions, for 1k, 4k and 16k envs.

    python benchmarks/env_throughput.py                 # CPU, all cores torch uses
    python benchmarks/env_throughput.py --device cuda   # where a GPU exists
    python benchmarks/env_throughput.py --threads 1

Run it alone on the machine: other heavy jobs on the same cores make the figures meaningless.
"""

from __future__ import annotations

import argparse
import json
import platform

import torch
from rich.console import Console
from rich.table import Table

from seqtrojan.bench.env_speed import measure_env_speed

GRIDS = ((7, 3), (17, 30), (27, 95))
BATCHES = (1024, 4096, 16384)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per measurement")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    table = Table(title=f"seqtrojan env steps/s ({args.device}, {torch.get_num_threads()} threads, random actions)")
    for col in ("grid", *(f"B={b}" for b in BATCHES), "episodes ending / step"):
        table.add_column(col, justify="right")
    rows = []
    for size, holes in GRIDS:
        speeds = [measure_env_speed(size, holes, b, steps=args.steps, device=args.device) for b in BATCHES]
        rows += [vars(s) for s in speeds]
        cells = [f"{s.steps_per_second / 1e6:.2f} M" for s in speeds]
        table.add_row(f"{size}x{size}/{holes}", *cells, f"{speeds[-1].resets_per_step:.3f}")
    Console().print(table)
    if args.json:
        meta = {"torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.processor()}
        with open(args.json, "w") as fh:
            json.dump({"meta": meta, "results": rows}, fh, indent=2)


if __name__ == "__main__":
    main()
