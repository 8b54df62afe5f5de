"""Print recurrent-PPO training throughput: env steps per second of the whole loop.

    python benchmarks/train_throughput.py                  # both parts, CPU
    python benchmarks/train_throughput.py --part speed     # throughput only
    python benchmarks/train_throughput.py --part cells     # throughput of each sequence model (agent.cell)
    python benchmarks/train_throughput.py --part cells --cells lstm transformer --backends cpp --rounds 6
    python benchmarks/train_throughput.py --device cuda

Throughput: env steps per second of the whole PPO loop (collect + GAE + 4 epochs of minibatch updates) with the
paper's network (54 -> LSTM 64 -> LSTM 32), median over updates 2-6, for each LSTM backend.
Cells: the same loop and widths (64, 32) with each sequence model: the LSTM, peephole LSTM and GRU on their fused
C++ kernels and on the PyTorch path, the windowed Transformer (window 8) with its C++ kernels (band attention,
fused bias + residual + norm and bias + ReLU passes, one-call rollout step; its linear products are PyTorch's either
way) and on the PyTorch path. With --rounds N every measurement is taken N times, the rounds interleaved (so that
a drift in the machine's other load hits every cell alike): the table shows the median and the range, the JSON each
run.
Time and env steps to a success target: benchmarks/sample_efficiency.py.
Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
from rich.console import Console
from rich.table import Table

from seqtrojan.agent import fast_lstm
from seqtrojan.config import CELLS, AgentConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.env import EnvConfig
from seqtrojan.train.trainer import train


def measure_speed(
    size: int, holes: int, num_envs: int, backend: str, device: str, out_dir: str, cell: str = "lstm"
) -> float:
    cfg = ExperimentConfig(
        env=EnvConfig(size=size, holes=holes),
        agent=AgentConfig(cell=cell),
        ppo=PPOConfig(total_steps=num_envs * 64 * 6, num_envs=num_envs, rollout_steps=64),
        run=RunConfig(
            out_dir=out_dir,
            device=device,
            progress=False,
            eval_episodes=0,
            checkpoint_every=10**12,
            lstm_backend=backend,
        ),
    )
    rates: list[float] = []
    train(cfg, callback=lambda s: rates.append(s["charts/steps_per_second"]) or False)
    return statistics.median(rates[1:])


def measure_cells(args: argparse.Namespace, tmp: str, console: Console) -> list[dict]:
    """Each cell on each grid and backend, ``args.rounds`` times, round after round; prints the table."""
    kernels = args.device == "cpu" and fast_lstm.extension() is not None
    backends = [b for b in ("torch", "cpp") if b in args.backends and (b == "torch" or kernels)]
    keys = [(cell, size, holes) for cell in args.cells for size, holes in ((7, 3), (17, 30))]
    runs: dict[tuple[str, int, int, str], list[float]] = {(*k, b): [] for k in keys for b in backends}
    for r in range(args.rounds):
        for cell, size, holes in keys:
            for b in backends:
                rate = measure_speed(size, holes, 512, b, args.device, tmp, cell)
                runs[cell, size, holes, b].append(rate)
                if args.rounds > 1:
                    console.print(f"round {r + 1}: {cell} {size}x{size}/{holes} {b} {rate:,.0f} env steps/s")
    title = f"PPO training throughput per cell, env steps/s ({args.device}, 512 envs"
    table = Table(title=title + (f"; median and range of {args.rounds} rounds)" if args.rounds > 1 else ")"))
    for col in ("cell", "grid", *backends):
        table.add_column(col, justify="right")
    rows = []
    for cell, size, holes in keys:
        rates = {b: runs[cell, size, holes, b] for b in backends}
        medians = {b: statistics.median(x) for b, x in rates.items()}
        rows.append({"cell": cell, "grid": f"{size}x{size}/{holes}", **medians, "runs": rates})
        shown = [f"{medians[b]:,.0f}" + (f" ({min(x):,.0f}-{max(x):,.0f})" if len(x) > 1 else "")
                 for b, x in rates.items()]  # fmt: skip
        table.add_row(cell, f"{size}x{size}/{holes}", *shown)
    console.print(table)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=("speed", "cells", "all"), default="all")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", default=None)
    parser.add_argument("--cells", nargs="+", choices=CELLS, default=list(CELLS), help="cells of the cells part")
    parser.add_argument("--backends", nargs="+", choices=("torch", "cpp"), default=["torch", "cpp"],
                        help="backends of the cells part")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=1, help="measurements of each cell, interleaved (cells part)")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    console = Console()
    report: dict = {"torch": torch.__version__, "threads": torch.get_num_threads(), "device": args.device}
    with tempfile.TemporaryDirectory() as tmp:
        if args.part in ("speed", "all"):
            backends = ["torch"] + (["cpp"] if args.device == "cpu" and fast_lstm.extension() is not None else [])
            table = Table(
                title=f"PPO training throughput, env steps/s ({args.device}, {torch.get_num_threads()} threads)"
            )
            for col in ("grid", "envs", *backends):
                table.add_column(col, justify="right")
            report["speed"] = []
            for size, holes in ((7, 3), (17, 30)):
                for envs in (512, 1024):
                    rates = {b: measure_speed(size, holes, envs, b, args.device, tmp) for b in backends}
                    report["speed"].append({"grid": f"{size}x{size}/{holes}", "envs": envs, **rates})
                    table.add_row(f"{size}x{size}/{holes}", str(envs), *(f"{rates[b]:,.0f}" for b in backends))
            console.print(table)
        if args.part in ("cells", "all"):
            report["cells"] = measure_cells(args, tmp, console)

    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
