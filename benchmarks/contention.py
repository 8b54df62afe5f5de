"""PPO training throughput under CPU contention: alone, then beside 1, 2 and 4 CPU-bound processes.

    python benchmarks/contention.py                                  # 7x7/3, 512 envs, 0/1/2/4 competitors
    python benchmarks/contention.py --competitors 0 1 --rounds 5
    python benchmarks/contention.py --competitor matmul              # competitors multiply matrices instead
    python benchmarks/contention.py --variant default --variant GOMP_SPINCOUNT=300000 --competitors 0 1
    python benchmarks/contention.py --cell transformer --variant default --variant GOMP_SPINCOUNT=3000

Each --variant (NAME=VALUE[,NAME=VALUE...], or 'default' for the environment as it is) is measured in turn,
interleaved with the others; GOMP_SPINCOUNT=300000 with OMP_WAIT_POLICY unset is libgomp's own default (what
seqtrojan ran with before it set OMP_WAIT_POLICY=PASSIVE; see seqtrojan/__init__.py).

Each figure is the env steps per second of the whole PPO loop (collect + GAE + 4 epochs of minibatch updates,
median over updates 2-6), measured as benchmarks/train_throughput.py does, in a fresh process (so that settings
given with --variant reach the OpenMP runtime before it starts). Competitors are single-threaded busy loops
started just before that process and killed after it. Rounds interleave the conditions (alone, 1, 2, 4, alone, ...)
so that drifts in the machine's other load hit all of them alike. The table shows the median per condition, its
ratio to the same variant's median alone, and ("vs first") its ratio to the first variant under the same load. A
fair share with n competitors on c cores and t training threads is about min(1, c / (t + n)) of the alone figure.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# Single-threaded CPU-bound loops; each ends by itself soon after the benchmark does (its parent changes).
_UNTIL_ORPHANED = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n"
COMPETITORS = {
    "busy": _UNTIL_ORPHANED + "    for _ in range(1_000_000):\n        pass\n",
    "matmul": "import numpy as np\na = np.random.rand(256, 256)\n"
    + _UNTIL_ORPHANED
    + "    for _ in range(100):\n        a = (a @ a) / np.abs(a).sum(0).max()\n",
}


def _worker(size: int, holes: int, envs: int, backend: str, cell: str) -> None:
    """Print one JSON line: this process's PPO throughput and the settings it ran with."""
    import seqtrojan  # first: it sets the OpenMP defaults, which torch's runtime reads once when it loads

    sys.path.insert(0, str(HERE))
    import torch
    from train_throughput import measure_speed

    from seqtrojan.agent import fast_lstm

    del seqtrojan

    with tempfile.TemporaryDirectory() as tmp:
        rate = measure_speed(size, holes, envs, backend, "cpu", tmp, cell)
    settings = {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")}
    used = "cpp" if backend != "torch" and fast_lstm.extension() is not None else "torch"
    print(json.dumps({"rate": rate, "threads": torch.get_num_threads(), "backend": used, **settings}))


def _start_competitors(n: int, kind: str) -> list[subprocess.Popen]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    procs = [subprocess.Popen([sys.executable, "-c", COMPETITORS[kind]], env=env) for _ in range(n)]
    time.sleep(0.5)  # let them start spinning
    return procs


def measure(competitors: int, args: argparse.Namespace, env: dict[str, str]) -> dict:
    procs = _start_competitors(competitors, args.competitor)
    try:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--grid", str(args.grid[0])]
        cmd += [str(args.grid[1]), "--envs", str(args.envs), "--backend", args.backend, "--cell", args.cell]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
    if out.returncode != 0:
        raise SystemExit(f"measurement failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _variant_env(variant: str, parser: argparse.ArgumentParser) -> dict[str, str]:
    env = dict(os.environ)
    if variant == "default":
        return env
    for item in variant.split(","):
        name, sep, value = item.partition("=")
        if not sep or not name:
            parser.error(f"--variant takes NAME=VALUE[,NAME=VALUE...] or 'default', got {variant!r}")
        env[name.strip()] = value.strip()
    return env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--competitors", type=int, nargs="+", default=[0, 1, 2, 4])
    parser.add_argument("--competitor", choices=sorted(COMPETITORS), default="busy")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--grid", type=int, nargs=2, default=[7, 3], metavar=("SIZE", "HOLES"))
    parser.add_argument("--envs", type=int, default=512)
    parser.add_argument("--backend", choices=("auto", "torch", "cpp"), default="auto")
    # seqtrojan.config.CELLS, written out: importing seqtrojan here would set OMP_WAIT_POLICY in this process's
    # environment, which every --variant's worker inherits
    parser.add_argument("--cell", choices=("lstm", "lstm_peephole", "gru", "transformer"), default="lstm",
                        help="the sequence model trained (agent.cell)")  # fmt: skip
    parser.add_argument("--variant", action="append", default=[], help="NAME=VALUE[,NAME=VALUE...] or 'default'")
    parser.add_argument("--json", default=None)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        _worker(args.grid[0], args.grid[1], args.envs, args.backend, args.cell)
        return

    from rich.console import Console
    from rich.table import Table

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so that the competitors are stopped
    variants = args.variant or ["default"]
    envs = {v: _variant_env(v, parser) for v in variants}
    counts = sorted(set([0, *args.competitors]))
    console = Console(width=max(120, Console().width))
    console.print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; cores: {os.cpu_count()}")
    rates: dict[str, dict[int, list[float]]] = {v: {n: [] for n in counts} for v in variants}
    info: dict[str, dict] = {}
    for r in range(args.rounds):
        for n in counts:
            for v in variants:
                result = measure(n, args, envs[v])
                rates[v][n].append(result.pop("rate"))
                info[v] = result
                console.print(f"round {r + 1}, {n} competitors, {v}: {rates[v][n][-1]:,.0f} env steps/s")
    table = Table(
        title=f"PPO throughput under contention: {args.cell}, {args.grid[0]}x{args.grid[0]}/{args.grid[1]}, "
        f"{args.envs} envs, {args.competitor} competitors, {args.rounds} rounds"
    )
    for col in ("variant", "competitors", "median env steps/s", "ratio to alone", "vs first"):
        table.add_column(col, justify="right")
    table.add_column("runs")
    first = variants[0]
    for v in variants:
        alone = statistics.median(rates[v][0])
        for n in counts:
            med = statistics.median(rates[v][n])
            table.add_row(
                v if n == counts[0] else "", str(n), f"{med:,.0f}", f"{med / alone:.2f}",
                f"{med / statistics.median(rates[first][n]):.2f}", " ".join(f"{x:,.0f}" for x in rates[v][n]),
            )  # fmt: skip
    console.print(table)
    for v in variants:
        console.print(f"{v}: the worker ran with {', '.join(f'{k}={x}' for k, x in info[v].items())}")
    console.print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        record = {"cell": args.cell, "competitor": args.competitor, "settings": info, "rates": rates}
        Path(args.json).write_text(json.dumps(record))


if __name__ == "__main__":
    main()
