"""Print how much faster a zoo builds on two local Ray nodes than on one, and whether both build the same models.

    python benchmarks/ray_nodes.py                                   # 8 grid models of 200k env steps, 1 round
    python benchmarks/ray_nodes.py --models 12 --steps 300000 --rounds 2 --json ray_nodes.json

Each arm builds the same zoo (``seqtrojan.zoo.build_zoo``: ``--models`` grid-world models, half clean and half
poisoned, ``--steps`` env steps each on the curriculum 5x5/0 -> 5x5/1, LSTM 32, 16 evaluation episodes per env type)
on the ``ray`` job backend, one torch thread per job, into a fresh folder:

- one node: a Ray cluster of one node with 1 CPU (``ray.cluster_utils.Cluster``, on this machine): the jobs one
  after another, as a one-machine Ray user would run them on one core;
- two nodes: the same with two nodes of 1 CPU each, so that two jobs run at once, one per node: what a second
  machine adds, here both nodes on this machine's two cores (a cluster of real machines adds its network and
  scheduling costs; this measures Ray's own).

Per arm the wall time of ``build_zoo`` (Ray's start-up, the trainings, the evaluations and the manifest; not the
cluster's start), models per hour, and the speed-up of two nodes over one. Every model's weights are hashed: the two
arms must build bitwise the same models (the backend changes where a job runs, not what it computes). With
``--rounds N`` the arms alternate N times (a drift in the machine's load hits both alike); the medians are printed.
Run it alone on the machine: the two-node arm needs both cores.
"""

from __future__ import annotations

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)

# isort: on
import argparse
import datetime
import hashlib
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from seqtrojan.env.config import GridSpec
from seqtrojan.zoo.build import ZooConfig, build_zoo

ARMS = (("one node", 1), ("two nodes", 2))
"""arm name, Ray nodes of 1 CPU each"""


def zoo_config(models: int, steps: int) -> ZooConfig:
    return ZooConfig(
        clean=models // 2, backdoored=models - models // 2, total_steps=steps, num_envs=64, eval_episodes=16,
        lstm_sizes=((32,),), curricula=((GridSpec(5, 0), GridSpec(5, 1)),), functional_at=0.0,
    )  # fmt: skip


def weights_digest(zoo: Path) -> dict[str, str]:
    """model folder name -> sha256 of its weights file, for every model the zoo holds."""
    return {
        path.parent.name: hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(zoo.glob("models/*/model.safetensors"))
    }


def build_on_nodes(nodes: int, cfg: ZooConfig) -> tuple[float, dict[str, str]]:
    """Wall seconds of one zoo build on a local cluster of ``nodes`` one-CPU Ray nodes, and its weights' digests."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=1)
    try:
        with tempfile.TemporaryDirectory(prefix="seqtrojan_ray_nodes_") as tmp:
            root = Path(tmp) / "zoo"
            start = time.perf_counter()
            build_zoo(cfg, root, workers=nodes, backend="ray", ray_address=cluster.address, threads=1,
                      log=lambda *_: None)  # fmt: skip
            seconds = time.perf_counter() - start
            return seconds, weights_digest(root)
    finally:
        cluster.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=int, default=8)
    parser.add_argument("--steps", type=int, default=200_000, help="env steps per model")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--json", help="write every measurement here")
    args = parser.parse_args()
    if args.models < 2 or args.steps < 1 or args.rounds < 1:
        parser.error("--models must be >= 2, --steps and --rounds >= 1")
    cfg = zoo_config(args.models, args.steps)
    print(f"ray nodes: {args.models} models x {args.steps} env steps, {args.rounds} round(s); "
          f"{os.cpu_count()} CPUs, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")  # fmt: skip
    seconds: dict[str, list[float]] = {name: [] for name, _ in ARMS}
    digests: dict[str, dict[str, str]] = {}
    for r in range(args.rounds):
        for name, nodes in ARMS:
            wall, digest = build_on_nodes(nodes, cfg)
            seconds[name].append(wall)
            digests.setdefault(name, digest)
            print(f"  round {r + 1}, {name}: {wall:.1f} s ({args.models / wall * 3600:.0f} models/hour)", flush=True)
    same = digests["one node"] == digests["two nodes"] and len(digests["one node"]) == args.models
    one, two = (statistics.median(seconds[name]) for name, _ in ARMS)
    print(f"one node  {one:8.1f} s  {args.models / one * 3600:7.0f} models/hour")
    print(f"two nodes {two:8.1f} s  {args.models / two * 3600:7.0f} models/hour")
    print(f"speed-up  {one / two:8.2f}x   same models on both: {'yes' if same else 'NO'}")
    if args.json:
        record = {
            "command": " ".join(["python", *sys.argv]), "date": datetime.date.today().isoformat(),
            "models": args.models, "steps": args.steps, "cpus": os.cpu_count(), "seconds": seconds,
            "speed_up": one / two, "same_models": same,
        }  # fmt: skip
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")
    if not same:
        raise SystemExit("the two arms built different models")


if __name__ == "__main__":
    main()
