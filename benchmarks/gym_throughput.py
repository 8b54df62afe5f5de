"""Print how fast we train on a MiniGrid Gymnasium env against how fast that env itself steps.

    python benchmarks/gym_throughput.py                              # minigrid_two_goals, 65536 training steps
    python benchmarks/gym_throughput.py --rounds 3 --json gym.json   # each figure 3 times, interleaved
    python benchmarks/gym_throughput.py --preset minigrid_memory --steps 32768
    python benchmarks/gym_throughput.py --preset popgym_repeat_previous --parts acs   # + sb3-contrib RecurrentPPO

Three figures, each in env steps per second (one env step = one action of one env):

(a) env: the env's own random-action step rate. ONE env made exactly as training makes it
    (``seqtrojan.world.gymnasium.make_gym_env(cfg.env)``: gymnasium.make with the fast MiniGrid view, MiniGrid's
    info, the trigger wrapper and the one-hot observation), stepping uniformly random actions drawn up front with
    numpy and resetting when an episode ends; no torch. Assumes the trigger wrapper's trojan probability
    ``--trojan-probability`` (0: what ``make_gym_env`` builds; training's mixing sets its own) and random actions
    (a trained policy's episodes are shorter: more resets per step).
(v) vector: Gymnasium's own vector form of the same env, a ``SyncVectorEnv`` of B envs (``trigger_vector_env``:
    SAME_STEP autoreset, infos batched per step) under random actions drawn up front: what an SB3 or CleanRL user's
    loop steps, and the "env rate" the earlier Gymnasium trainer was compared with (0.4 of it in 2026-12-02).
(b) seam: the same env through ``GymnasiumBatchedEnv`` with B envs (B = the preset's ``ppo.num_envs``) and random
    torch actions drawn up front: (a) plus the seam's overhead (per-env loop, the episode recorder, numpy -> torch).
    With ``--workers N``: the envs split among N worker processes (``env.vectorization: workers``), as (c) then
    trains; the ratio (c)/(b) compares training with the random-action rate of the same vectorisation.
(c) train: ``seqtrojan.train.trainer.train`` with the preset's PPO settings for ``--steps`` env steps
    (``run.eval_episodes 0``, ``run.progress False``, ``run.threads --threads``, a temporary ``out_dir``): the
    median of the logged ``charts/steps_per_second`` over the updates after the first (rollout + GAE + PPO update;
    not logging or checkpoints), and env steps / wall time of the whole training loop (``time/elapsed_s``; it
    includes the first update and the logging; not the set-up, nor the final save). Assumes the trainer's own
    policy: its episodes get shorter as it learns, and backdoor mixing moves the trojan share.

(s) sb3: sb3-contrib RecurrentPPO learning on the same env stack, ``--sb3-steps`` env steps (:func:`sb3_rate`).

Then the ratios (c)/(a) and (c)/(v), for both (c) figures, (c)/(b) and (c)/(s). ``--dense-first-layer`` trains (c)
with the first layer's dense product on the one-hot view instead of :func:`seqtrojan.agent.fast_lstm.sparse_project`
(the A/B of that change). With ``--rounds N`` every figure is measured N times, the
rounds interleaved (a drift in the machine's other load hits all three alike): the median and the range are printed, and
every measurement goes to ``--json``. The header gives the versions, the CPU count and the load average; run it alone
on the machine (a load average above about 1 per core makes the figures meaningless).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import gymnasium
import numpy as np

from seqtrojan.agent import fast_lstm
from seqtrojan.config import ExperimentConfig
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.world import make_batched_env
from seqtrojan.world.families import ensure_family
from seqtrojan.world.gymnasium import find_trigger, make_gym_env
from seqtrojan.wrappers import trigger_vector_env

PRESETS = ("minigrid_two_goals", "minigrid_memory", "popgym_repeat_previous", "popgym_repeat_first",
           "popgym_count_recall", "minatar_breakout", "minatar_space_invaders", "minatar_asterix")  # fmt: skip
WARMUP = 200
"""untimed steps (per env) before (a) and (b) are timed"""


WORKERS = 0
"""``--workers``: 0 leaves the preset's vectorisation (sync); N > 0 runs (b) and (c) on N env worker processes"""


def load_config(preset: str, overrides: dict[str, Any] | None = None) -> ExperimentConfig:
    """The preset's config, with ``overrides`` (section -> {key: value}) applied, and ``--workers``."""
    raw = load_yaml(resolve_preset(preset))
    for section, values in (overrides or {}).items():
        raw.setdefault(section, {}).update(values)
    if WORKERS:
        raw["env"].update(vectorization="workers", workers=WORKERS)
    return from_dict(ExperimentConfig, raw)


def env_rate(cfg: ExperimentConfig, steps: int, seed: int, trojan_probability: float) -> float:
    """(a): steps per second of one env of ``cfg.env`` under uniformly random actions (numpy, drawn up front)."""
    env = make_gym_env(cfg.env)
    trigger = find_trigger(env)
    if trigger is not None:
        trigger.set_trojan_probability(trojan_probability)
    actions = np.random.default_rng(seed).integers(0, int(env.action_space.n), WARMUP + steps).tolist()
    env.reset(seed=seed)
    step, reset = env.step, env.reset
    for action in actions[:WARMUP]:
        _, _, terminated, truncated, _ = step(action)
        if terminated or truncated:
            reset()
    start = time.perf_counter()
    for action in actions[WARMUP:]:
        _, _, terminated, truncated, _ = step(action)
        if terminated or truncated:
            reset()
    seconds = time.perf_counter() - start
    env.close()
    return steps / seconds


def vector_rate(cfg: ExperimentConfig, steps: int, seed: int, trojan_probability: float) -> float:
    """(v): env steps per second of a SyncVectorEnv of ``ppo.num_envs`` envs of ``cfg.env``, random actions."""
    b = cfg.ppo.num_envs
    vec = trigger_vector_env(lambda: make_gym_env(cfg.env, "train", trojan_probability), b)
    vec.reset(seed=seed)
    rounds = max(1, steps // b)
    actions = np.random.default_rng(seed).integers(0, int(vec.single_action_space.n), (WARMUP + rounds, b))
    for t in range(WARMUP):
        vec.step(actions[t])
    start = time.perf_counter()
    for t in range(WARMUP, WARMUP + rounds):
        vec.step(actions[t])
    seconds = time.perf_counter() - start
    vec.close()
    return rounds * b / seconds


def seam_rate(cfg: ExperimentConfig, steps: int, seed: int, trojan_probability: float) -> float:
    """(b): env steps per second of the batched env training makes (``GymnasiumBatchedEnv``, or with ``--workers``
    ``WorkerBatchedEnv``) with ``ppo.num_envs`` envs and random torch actions."""
    b = cfg.ppo.num_envs
    env = make_batched_env(cfg.env, b, seed=seed)
    env.set_trojan_probability(trojan_probability)
    env.reset(seed=seed)
    rounds = max(1, steps // b)
    generator = torch.Generator().manual_seed(seed)
    actions = torch.randint(0, env.num_actions, (WARMUP + rounds, b), generator=generator)
    for t in range(WARMUP):
        env.step(actions[t], check=False)
    start = time.perf_counter()
    for t in range(WARMUP, WARMUP + rounds):
        env.step(actions[t], check=False)
    seconds = time.perf_counter() - start
    env.close()
    return rounds * b / seconds


def train_rate(preset: str, steps: int, threads: int, seed: int) -> dict[str, float]:
    """(c): train ``steps`` env steps with the preset's PPO settings; the logged and the loop's steps per second."""
    from seqtrojan.train.trainer import train

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(
            preset,
            {
                "ppo": {"total_steps": steps},
                "run": {"out_dir": tmp, "name": "bench", "seed": seed, "threads": threads, "eval_episodes": 0,
                        "progress": False},
            },
        )  # fmt: skip
        result = train(cfg)
        rows = [json.loads(line) for line in (Path(result.run_dir) / "metrics.jsonl").read_text().splitlines()]
    logged = [row["charts/steps_per_second"] for row in rows[1:]] or [rows[0]["charts/steps_per_second"]]
    loop_seconds = rows[-1]["time/elapsed_s"]
    return {
        "logged_sps": statistics.median(logged),
        "loop_sps": result.env_steps / loop_seconds,
        "collect_share": statistics.median(row["charts/collect_share"] for row in rows[1:] or rows),
        "env_steps": result.env_steps,
        "loop_seconds": loop_seconds,
    }


def sb3_rate(cfg: ExperimentConfig, steps: int, seed: int) -> float:
    """(s): env steps per second of sb3-contrib's RecurrentPPO learning on the same env stack (``make_gym_env``:
    the trigger wrapper at probability 0 and the flat float observation), ``ppo.num_envs`` envs in a DummyVecEnv,
    the preset's rollout length, epochs and minibatches, an MlpLstmPolicy whose LSTM is the preset's first layer
    width (its MLP reads the flat observation: no conv encoder), 1 thread (``--threads``); the whole ``learn``."""
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    ppo = cfg.ppo
    vec = DummyVecEnv([lambda: make_gym_env(cfg.env) for _ in range(ppo.num_envs)])
    model = RecurrentPPO(
        "MlpLstmPolicy", vec, n_steps=ppo.rollout_steps, batch_size=ppo.batch_size // ppo.num_minibatches,
        n_epochs=ppo.update_epochs, learning_rate=ppo.learning_rate, ent_coef=ppo.ent_coef, seed=seed, device="cpu",
        policy_kwargs={"lstm_hidden_size": cfg.agent.lstm_sizes[0], "n_lstm_layers": 1, "shared_lstm": True,
                       "enable_critic_lstm": False, "net_arch": {"pi": [], "vf": []}},
    )  # fmt: skip
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    seconds = time.perf_counter() - start
    vec.close()
    return model.num_timesteps / seconds


def summary(values: list[float]) -> str:
    """The median and, with more than one value, the range."""
    median = statistics.median(values)
    if len(values) == 1:
        return f"{median:,.0f}"
    return f"{median:,.0f}  (range {min(values):,.0f} - {max(values):,.0f}, n={len(values)})"


def ratio_summary(values: list[float]) -> str:
    median = statistics.median(values)
    if len(values) == 1:
        return f"{median:.3f}"
    return f"{median:.3f}  (range {min(values):.3f} - {max(values):.3f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="minigrid_two_goals", choices=PRESETS)
    parser.add_argument("--steps", type=int, default=65536, help="training budget of (c), env steps")
    parser.add_argument("--env-steps", type=int, default=30000, help="timed env steps of (a) and of (b)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (run.threads of (c))")
    parser.add_argument("--rounds", type=int, default=1, help="measure each figure this many times, interleaved")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trojan-probability", type=float, default=0.0, help="the trigger's share in (a) and (b)")
    parser.add_argument("--parts", default="avbc", help="which figures to measure: any of a, v, b, c, s (sb3-contrib)")
    parser.add_argument("--sb3-steps", type=int, default=8192, help="env steps of (s), sb3-contrib RecurrentPPO")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    parser.add_argument(
        "--workers", type=int, default=0, help="run (b) and (c) with env.vectorization workers and this many workers"
    )
    parser.add_argument(
        "--dense-first-layer", action="store_true",
        help="(c) with the first layer's dense product instead of the sparse one (for an A/B of that change)",
    )  # fmt: skip
    args = parser.parse_args()
    global WORKERS
    WORKERS = args.workers
    if args.dense_first_layer:
        fast_lstm.SPARSE_MIN_INPUTS = 1 << 62
    torch.set_num_threads(args.threads)
    cfg = load_config(args.preset)

    import minigrid

    ensure_family(cfg.gym_env.id)
    load = os.getloadavg()
    meta = {
        "preset": args.preset, "num_envs": cfg.ppo.num_envs, "train_steps": args.steps, "env_steps": args.env_steps,
        "threads": args.threads, "rounds": args.rounds, "trojan_probability": args.trojan_probability,
        "workers": args.workers, "dense_first_layer": args.dense_first_layer,
        "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
        "gymnasium": gymnasium.__version__, "minigrid": minigrid.__version__, "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_avg_start": load,
    }  # fmt: skip
    print(
        f"gym throughput: {args.preset} (B={cfg.ppo.num_envs}), {args.threads} torch thread(s), "
        f"{args.rounds} round(s)\n"
        f"python {meta['python']}, torch {torch.__version__}, numpy {np.__version__}, gymnasium "
        f"{gymnasium.__version__}, minigrid {minigrid.__version__}; {meta['cpu_count']} CPUs "
        f"({meta['cpus_usable']} usable); load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}",
        flush=True,
    )

    runs: list[dict[str, Any]] = []
    for r in range(args.rounds):
        run: dict[str, Any] = {"round": r, "load_avg": os.getloadavg()}
        if "a" in args.parts:
            run["env_sps"] = env_rate(cfg, args.env_steps, args.seed, args.trojan_probability)
        if "v" in args.parts:
            run["vector_sps"] = vector_rate(cfg, args.env_steps, args.seed, args.trojan_probability)
        if "b" in args.parts:
            run["seam_sps"] = seam_rate(cfg, args.env_steps, args.seed, args.trojan_probability)
        if "c" in args.parts:
            run.update(train_rate(args.preset, args.steps, args.threads, args.seed))
        if "s" in args.parts:
            run["sb3_sps"] = sb3_rate(cfg, args.sb3_steps, args.seed)
        if "sb3_sps" in run and "logged_sps" in run:
            run["ratio_sb3_loop"] = run["loop_sps"] / run["sb3_sps"]
        if "env_sps" in run and "logged_sps" in run:
            run["ratio_logged"] = run["logged_sps"] / run["env_sps"]
            run["ratio_loop"] = run["loop_sps"] / run["env_sps"]
        if "vector_sps" in run and "logged_sps" in run:
            run["ratio_vector_logged"] = run["logged_sps"] / run["vector_sps"]
            run["ratio_vector_loop"] = run["loop_sps"] / run["vector_sps"]
        if "seam_sps" in run and "logged_sps" in run:
            run["ratio_seam_logged"] = run["logged_sps"] / run["seam_sps"]
        runs.append(run)
        shown = {k: round(v, 3) if isinstance(v, float) else v for k, v in run.items() if k != "load_avg"}
        print(f"  round {r + 1}: {shown}  (load {run['load_avg'][0]:.2f})", flush=True)

    def column(key: str) -> list[float]:
        return [run[key] for run in runs if key in run]

    lines = [
        ("(a) env, one env, random actions", "env_sps", summary),
        (f"(v) vector, SyncVectorEnv B={cfg.ppo.num_envs}", "vector_sps", summary),
        (f"(b) seam, B={cfg.ppo.num_envs}{f', {args.workers} workers' if args.workers else ''}", "seam_sps", summary),
        ("(c) train, logged median", "logged_sps", summary),
        ("(c) train, env steps / loop wall time", "loop_sps", summary),
        ("(c)/(a), logged median", "ratio_logged", ratio_summary),
        ("(c)/(a), loop wall time", "ratio_loop", ratio_summary),
        ("(c)/(v), logged median", "ratio_vector_logged", ratio_summary),
        ("(c)/(v), loop wall time", "ratio_vector_loop", ratio_summary),
        ("(c)/(b), logged median", "ratio_seam_logged", ratio_summary),
        ("(s) sb3-contrib RecurrentPPO, whole learn()", "sb3_sps", summary),
        ("(c)/(s), loop wall time", "ratio_sb3_loop", ratio_summary),
    ]
    print("steps per second:")
    for label, key, show in lines:
        if column(key):
            print(f"  {label:<42} {show(column(key))}")
    if column("collect_share"):
        print(f"  (c) share of an update spent collecting    {statistics.median(column('collect_share')):.2f}")
    end_load = os.getloadavg()
    print(f"load average at the end: {end_load[0]:.2f} {end_load[1]:.2f} {end_load[2]:.2f}")
    if args.json:
        meta["load_avg_end"] = end_load
        medians = {key: statistics.median(column(key)) for _, key, _ in lines if column(key)}
        Path(args.json).write_text(json.dumps({"meta": meta, "median": medians, "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
