"""Does a backdoored agent's state settle before the trigger, and does the attack work better once it has?

    python scripts/settling.py results/paper/runs/backdoor*/model --grid 7x7/7 --trigger-steps 1,2,4,6,8
    python scripts/settling.py MODEL... --grid 17x17/30 --trigger-steps 1,2,4,8,12,15 --json out.json

For each model: the mean relative change of its recurrent state per step in normal episodes of the grid
(``|s_t - s_{t-1}| / |s_{t-1}|``), and the attack success (trojan env, trigger at each step) over --episodes
episodes; then the mean and sd over the models of each figure. The paper's conjecture for its weak 7x7/7 trojan
result: on a small grid the LSTM's state has not settled when the trigger comes.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.env import GridSpec
from seqtrojan.errors import SeqTrojanError
from seqtrojan.experiments.cells import CellsConfig, settling
from seqtrojan.serde import to_dict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+", help="backdoored model folders")
    parser.add_argument("--grid", default="7x7/7", help="SIZExSIZE/HOLES")
    parser.add_argument("--trigger-steps", default="1,2,4,6,8", help="comma-separated steps")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes per trigger step and model")
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--json", default=None, help="write every model's Settling here")
    args = parser.parse_args()
    try:
        grid = GridSpec.parse(args.grid)
        steps = tuple(int(s) for s in args.trigger_steps.split(","))
        cfg = CellsConfig(settle_grid=grid, settle_trigger_steps=steps, episodes=args.episodes)
    except (SeqTrojanError, ValueError) as err:
        parser.error(str(err))
    results = []
    for folder in args.models:
        try:
            agent, agent_cfg, _ = load_agent(folder)
            results.append(settling(agent, agent_cfg.env, cfg, args.seed))
        except SeqTrojanError as err:
            parser.error(str(err))
        result = results[-1]
        print(f"{folder}: change {', '.join(f'{c:.2f}' for c in result.change[:10])}; attack success "
              + ", ".join(f"{r.value:.3f}" for r in result.attack_success), flush=True)  # fmt: skip

    def mean_sd(values: list[float]) -> str:
        return f"{statistics.mean(values):.3f} ± {statistics.stdev(values) if len(values) > 1 else 0.0:.3f}"

    print(f"\n{grid.label}, {len(results)} models, mean ± sd over models:")
    for t in (1, 2, 4, 8):
        if t <= len(results[0].change):
            print(f"  state change at step {t}: {mean_sd([r.change[t - 1] for r in results])}")
    for i, step in enumerate(steps):
        print(f"  attack success, trigger at step {step}: {mean_sd([r.attack_success[i].value for r in results])}")
    if args.json:
        Path(args.json).write_text(json.dumps([to_dict(r) for r in results], indent=1))


if __name__ == "__main__":
    main()
