"""Print one cell's PPO training throughput (env steps/s, median over updates 2..N): the unit of an A/B pair.

On a noisy machine two versions of the code are compared in interleaved pairs, each run alone, e.g. against the
commit before a change (a worktree of it; its kernels build into their own cache folder, keyed by their sources):

    git worktree add /tmp/base <commit>
    for i in 1 2 3; do
      PYTHONPATH=/tmp/base python benchmarks/transformer_ab.py --grid 17 30   # before
      python benchmarks/transformer_ab.py --grid 17 30                        # after
    done

Same loop as benchmarks/train_throughput.py (512 envs, T = 64, 4 epochs, 4 minibatches, widths 64, 32).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)

# isort: on
from seqtrojan.config import CELLS, AgentConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.env import EnvConfig
from seqtrojan.train.trainer import train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grid", type=int, nargs=2, default=(7, 3), metavar=("SIZE", "HOLES"), help="grid and holes")
    parser.add_argument("--cell", choices=CELLS, default="transformer", help="the sequence model (agent.cell)")
    parser.add_argument("--backend", choices=("cpp", "torch"), default="cpp", help="C++ kernels or the PyTorch path")
    parser.add_argument("--updates", type=int, default=8, help="PPO updates to run (the first is not counted)")
    args = parser.parse_args()
    size, holes = args.grid
    with tempfile.TemporaryDirectory() as tmp:
        cfg = ExperimentConfig(
            env=EnvConfig(size=size, holes=holes),
            agent=AgentConfig(cell=args.cell),
            ppo=PPOConfig(total_steps=512 * 64 * args.updates, num_envs=512, rollout_steps=64),
            run=RunConfig(out_dir=tmp, device="cpu", progress=False, eval_episodes=0, checkpoint_every=10**12,
                          lstm_backend=args.backend),
        )  # fmt: skip
        rates: list[float] = []
        shares: list[float] = []

        def record(scalars: dict) -> bool:
            rates.append(scalars["charts/steps_per_second"])
            shares.append(scalars["charts/collect_share"])
            return False

        train(cfg, callback=record)
    print(
        f"{args.cell} {args.backend} {size}x{size}/{holes} median {statistics.median(rates[1:]):,.0f} env steps/s; "
        f"per update {[round(r) for r in rates]}; collect share {statistics.median(shares[1:]):.3f}"
    )


if __name__ == "__main__":
    main()
