"""Print recurrent-PPO training figures: throughput of the whole loop and time to 90% success on 7x7/3.

    python benchmarks/train_throughput.py                  # both parts, CPU
    python benchmarks/train_throughput.py --part speed     # throughput only
    python benchmarks/train_throughput.py --part cells     # throughput of each sequence model (agent.cell)
    python benchmarks/train_throughput.py --device cuda

Throughput: env steps per second of the whole PPO loop (collect + GAE + 4 epochs of minibatch updates) with the
paper's network (54 -> LSTM 64 -> LSTM 32), median over updates 2-6, for each LSTM backend.
Cells: the same loop and widths (64, 32) with each sequence model: the LSTM, peephole LSTM and GRU on their fused
C++ kernels and on the PyTorch path, the windowed Transformer (window 8, PyTorch only: its training unroll is one
batched attention over the window, not a time loop).
Time to 90%: the clean_7x7 preset (curriculum 5x5/0 -> 5x5/1 -> 7x7/3), stopped at the first update whose 7x7/3
rollout episodes succeed >= 90%; then 1000 fresh evaluation episodes confirm the rate. Several seeds.
Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import dataclasses
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
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train.trainer import train

ROOT = Path(__file__).resolve().parents[1]


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


def time_to_90(seed: int, device: str, out_dir: str, curriculum: bool = True) -> dict:
    cfg = from_dict(ExperimentConfig, load_yaml(ROOT / "configs" / "clean_7x7.yaml"), "")
    cfg = dataclasses.replace(
        cfg, run=dataclasses.replace(cfg.run, out_dir=out_dir, seed=seed, device=device, progress=False)
    )
    if not curriculum:
        cfg = dataclasses.replace(cfg, curriculum=dataclasses.replace(cfg.curriculum, stages=()))
    last = len(cfg.grids) - 1
    hit: dict = {}

    def stop(s: dict) -> bool:
        if s["curriculum/stage"] == last and s.get(f"stages/{last}/normal_success", 0.0) >= 0.9:
            hit.update(env_steps=s["env_steps"], seconds=s["time/elapsed_s"])
            return True
        return False

    result = train(cfg, callback=stop)
    return {"seed": seed, "curriculum": curriculum, **hit, "eval_success": result.evaluation["normal_success"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=("speed", "cells", "time", "all"), default="all")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
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
            kernels = args.device == "cpu" and fast_lstm.extension() is not None
            table = Table(title=f"PPO training throughput per cell, env steps/s ({args.device}, 512 envs)")
            for col in ("cell", "grid", "torch", "cpp"):
                table.add_column(col, justify="right")
            report["cells"] = []
            for cell in CELLS:
                for size, holes in ((7, 3), (17, 30)):
                    backends = ["torch"] + (["cpp"] if kernels and cell != "transformer" else [])
                    rates = {b: measure_speed(size, holes, 512, b, args.device, tmp, cell) for b in backends}
                    report["cells"].append({"cell": cell, "grid": f"{size}x{size}/{holes}", **rates})
                    shown = [f"{rates[b]:,.0f}" if b in rates else "-" for b in ("torch", "cpp")]
                    table.add_row(cell, f"{size}x{size}/{holes}", *shown)
            console.print(table)
        if args.part in ("time", "all"):
            report["time_to_90"] = []
            for curriculum in (True, False):
                runs = [time_to_90(seed, args.device, tmp, curriculum) for seed in range(args.seeds)]
                report["time_to_90"] += runs
                how = "with the curriculum 5x5/0 -> 5x5/1 -> 7x7/3" if curriculum else "directly on 7x7/3"
                table = Table(title=f"Time to 90% success on 7x7/3, {how}")
                for col in ("seed", "env steps", "seconds", "eval success (1000 episodes)"):
                    table.add_column(col, justify="right")
                for r in runs:
                    table.add_row(
                        str(r["seed"]),
                        f"{r.get('env_steps', 0):,}",
                        f"{r.get('seconds', float('nan')):.1f}",
                        f"{r['eval_success']:.3f}",
                    )
                console.print(table)
                secs = [r["seconds"] for r in runs if "seconds" in r]
                if secs:
                    console.print(f"median {statistics.median(secs):.1f} s over {len(secs)} seeds")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
