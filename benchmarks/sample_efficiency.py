"""Print sample efficiency: env steps and wall time until an agent reaches a success target, over seeds.

    python benchmarks/sample_efficiency.py                              # 7x7/3 clean, the shipped preset, 5 seeds
    python benchmarks/sample_efficiency.py --settings base,epochs8    # compare PPO settings (see SETTINGS)
    python benchmarks/sample_efficiency.py --task 17x17 --kind backdoored --target 0.95
    python benchmarks/sample_efficiency.py --sb3                        # also sb3-contrib RecurrentPPO, same env
    python benchmarks/sample_efficiency.py --base previous --settings base,rollout32   # the study's screens
    python benchmarks/sample_efficiency.py --list                       # the settings and what they change

The rule, the same for every agent: after each update (ours) or rollout (sb3-contrib), the training episodes on the
target grid that ended in that window (at least 50; for ours the last curriculum stage, both env types when
backdoored) must succeed >= target; then 1000 fresh episodes of the sampled policy on the target grid must too
(otherwise training goes on). The steps reported are the env steps taken when that check passed; a run that never
passes within --budget steps is shown as censored (">budget"). Ours uses the training stop rule
(`stop.success = target, stop.updates = 1, stop.confirm_episodes = 1000`).

7x7 task: the clean_7x7 preset (curriculum 5x5/0 -> 5x5/1 -> 7x7/3); `--no-curriculum` trains on 7x7/3 directly.
17x17 task: clean_s17_h30 / trojan_s17_h30 (curriculum to 17x17/30). sb3-contrib trains on 7x7/3 or 17x17/30 directly
(no curriculum, no Algorithm 1: clean only), MlpLstmPolicy with one shared LSTM of 64, 16 envs x 128 steps, 4 epochs
of 4 minibatches, lr 1e-3, entropy 0.01, one torch thread.

Step counts do not depend on the machine's load; wall times do: time them with nothing else running.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time
from collections import deque
from pathlib import Path
from typing import Any

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
from rich.console import Console
from rich.table import Table

from seqtrojan.config import ExperimentConfig
from seqtrojan.experiments.specs import deep_merge
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train.trainer import train

PRESETS = {("7x7", "clean"): "clean_7x7", ("17x17", "clean"): "clean_s17_h30",
           ("17x17", "backdoored"): "trojan_s17_h30"}  # fmt: skip
SB3_ENVS = {"7x7": "seqtrojan/Normal-v0", "17x17": "seqtrojan/Normal-17x17-H30-v0"}

SETTINGS: dict[str, dict[str, Any]] = {
    "base": {},  # the base settings unchanged (--base)
    "envs128": {"ppo": {"num_envs": 128}},
    "envs512": {"ppo": {"num_envs": 512}},
    "rollout32": {"ppo": {"rollout_steps": 32}},
    "epochs8": {"ppo": {"update_epochs": 8}},
    "minibatches8": {"ppo": {"num_minibatches": 8}},
    "lr2e-3": {"ppo": {"learning_rate": 0.002}},
    "lr5e-4": {"ppo": {"learning_rate": 0.0005}},
    "ent0.003": {"ppo": {"ent_coef": 0.003}},
    "bptt16": {"ppo": {"bptt_length": 16}},
    "promote0.8": {"curriculum": {"promote_at": 0.8}},
    "minep100": {"curriculum": {"min_episodes": 100, "window_updates": 2}},
    "lambda0.9": {"ppo": {"gae_lambda": 0.9}},
    "envs64": {"ppo": {"num_envs": 64}},
    "envs128+rollout32": {"ppo": {"num_envs": 128, "rollout_steps": 32}},
    "envs128+lr2e-3": {"ppo": {"num_envs": 128, "learning_rate": 0.002}},
    "rollout32+lr2e-3": {"ppo": {"rollout_steps": 32, "learning_rate": 0.002}},
    "envs128+rollout32+lr2e-3": {"ppo": {"num_envs": 128, "rollout_steps": 32, "learning_rate": 0.002}},
    "rollout32+epochs8": {"ppo": {"rollout_steps": 32, "update_epochs": 8}},
    "envs64+rollout32": {"ppo": {"num_envs": 64, "rollout_steps": 32}},
    "envs256+rollout32": {"ppo": {"num_envs": 256, "rollout_steps": 32}},
    "envs256+rollout32+lr2e-3": {"ppo": {"num_envs": 256, "rollout_steps": 32, "learning_rate": 0.002}},
}
"""Named changes to a preset for the settings study (nested like the YAML)."""

PREVIOUS: dict[str, dict[str, Any]] = {
    "7x7": {"ppo": {"total_steps": 3_000_000, "num_envs": 256, "rollout_steps": 64, "learning_rate": 0.001}},
    "17x17": {"ppo": {"total_steps": 10_000_000, "rollout_steps": 64, "learning_rate": 0.001}},
}
"""The presets' PPO settings before the study (2026-12-02): ``--base previous`` starts from them, as the study did."""


@dataclasses.dataclass(frozen=True)
class Reached:
    """One run: env steps and seconds when the target was confirmed (None: not within the budget)."""

    seed: int
    env_steps: int | None
    seconds: float | None
    confirmed_success: float | None


def ours(task: str, kind: str, setting: str, seed: int, target: float, budget: int, curriculum: bool,
         out_dir: str, previous: bool = False) -> Reached:  # fmt: skip
    data = load_yaml(resolve_preset(PRESETS[task, kind]))
    data = deep_merge(deep_merge(data, PREVIOUS[task]) if previous else data, SETTINGS[setting])
    data = deep_merge(data, {"ppo": {"total_steps": budget},
                        "stop": {"enabled": True, "success": target, "updates": 1, "confirm_episodes": 1000},
                        "run": {"out_dir": out_dir, "seed": seed, "progress": False, "eval_episodes": 0,
                                "checkpoint_every": 10**12}})  # fmt: skip
    if not curriculum:
        data["curriculum"] = {"stages": []}
    cfg = from_dict(ExperimentConfig, data, "")
    start = time.perf_counter()
    result = train(cfg)
    seconds = time.perf_counter() - start
    if not result.evaluation.get("stopped_early"):
        return Reached(seed, None, None, None)
    confirmed = min(result.evaluation["stop_confirmed"].values())
    return Reached(seed, int(result.evaluation["env_steps"]), seconds, confirmed)


def sb3(task: str, seed: int, target: float, budget: int) -> Reached:
    import gymnasium as gym
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    env_id = SB3_ENVS[task]
    vec = DummyVecEnv([lambda: gym.make(env_id) for _ in range(16)])
    vec.seed(seed)

    class TargetCheck(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.window: deque[bool] = deque()
            self.checks = 0
            self.confirmed: float | None = None

        def _on_step(self) -> bool:
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                if done:
                    self.window.append(bool(info["success"]))
            return self.confirmed is None

        def _on_rollout_end(self) -> None:
            episodes, self.window = list(self.window), deque()
            if len(episodes) >= 50 and sum(episodes) / len(episodes) >= target:
                self.checks += 1
                rate = held_out(self.model, env_id, 1000, seed * 1000 + self.checks)
                if rate >= target:
                    self.confirmed = rate

    model = RecurrentPPO(
        "MlpLstmPolicy", vec, n_steps=128, batch_size=16 * 128 // 4, n_epochs=4, learning_rate=1e-3, ent_coef=0.01,
        seed=seed, device="cpu",
        policy_kwargs={"lstm_hidden_size": 64, "n_lstm_layers": 1, "shared_lstm": True, "enable_critic_lstm": False},
    )  # fmt: skip
    check = TargetCheck()
    start = time.perf_counter()
    model.learn(total_timesteps=budget, callback=check)
    seconds = time.perf_counter() - start
    if check.confirmed is None:
        return Reached(seed, None, None, None)
    return Reached(seed, int(model.num_timesteps), seconds, check.confirmed)


def held_out(model: Any, env_id: str, episodes: int, seed: int) -> float:
    """Success of the sampled policy over fresh episodes (16 at a time)."""
    import gymnasium as gym
    import numpy as np

    envs = gym.vector.SyncVectorEnv([lambda: gym.make(env_id) for _ in range(16)],
                                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)  # fmt: skip
    obs, _ = envs.reset(seed=seed)
    state, starts = None, np.ones(16, dtype=bool)
    successes: list[bool] = []
    while len(successes) < episodes:
        action, state = model.predict(obs, state=state, episode_start=starts, deterministic=False)
        obs, _, terminated, truncated, info = envs.step(action)
        starts = terminated | truncated
        for i in np.flatnonzero(starts):
            successes.append(bool(info["final_info"]["success"][i]))
    envs.close()
    return sum(successes[:episodes]) / episodes


def summary(runs: list[Reached], budget: int) -> tuple[str, str, str]:
    done = [r for r in runs if r.env_steps is not None]
    steps = [r.env_steps for r in done]
    if len(done) * 2 <= len(runs):
        median = f">{budget:,}"
    else:  # censored runs count as above every finished one
        ordered = sorted(steps) + [budget + 1] * (len(runs) - len(done))
        median = f"{statistics.median(ordered):,.0f}"
    per_seed = ", ".join(f"{r.env_steps:,}" if r.env_steps is not None else f">{budget:,}" for r in runs)
    secs = [r.seconds for r in done if r.seconds is not None]
    return median, (f"{statistics.median(secs):.1f}" if secs else "-"), per_seed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", choices=("7x7", "17x17"), default="7x7")
    parser.add_argument("--kind", choices=("clean", "backdoored"), default="clean")
    parser.add_argument("--settings", default="base", help="comma-separated names from SETTINGS (--list)")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--target", type=float, default=None, help="success target (default 0.9 on 7x7, 0.95 on 17x17)")
    parser.add_argument("--budget", type=int, default=None, help="env steps per run (default 3M on 7x7, 10M on 17x17)")
    parser.add_argument(
        "--base",
        choices=("preset", "previous"),
        default="preset",
        help="start from the shipped preset, or from its settings before the study (PREVIOUS)",
    )
    parser.add_argument("--no-curriculum", action="store_true", help="ours trains on the target grid directly")
    parser.add_argument("--sb3", action="store_true", help="also sb3-contrib RecurrentPPO (clean only; slow)")
    parser.add_argument("--sb3-only", action="store_true", help="only sb3-contrib (ours not run)")
    parser.add_argument("--sb3-budget", type=int, default=600_000, help="env steps per sb3-contrib run")
    parser.add_argument("--json", default=None, help="write every run here")
    parser.add_argument("--list", action="store_true", help="print the settings and exit")
    args = parser.parse_args()
    if args.list:
        for name, change in SETTINGS.items():
            print(f"{name:<14} {json.dumps(change)}")
        return
    unknown = [s for s in args.settings.split(",") if s not in SETTINGS]
    if unknown or (args.task, args.kind) not in PRESETS:
        parser.error(f"unknown settings {unknown}" if unknown else f"no preset for {args.task} {args.kind}")
    target = args.target if args.target is not None else (0.9 if args.task == "7x7" else 0.95)
    budget = args.budget if args.budget is not None else (3_000_000 if args.task == "7x7" else 10_000_000)
    seeds = range(args.seeds)
    rows: dict[str, list[Reached]] = {}
    threads = torch.get_num_threads()
    with tempfile.TemporaryDirectory() as tmp:
        for setting in [] if args.sb3_only else args.settings.split(","):
            rows[setting] = [ours(args.task, args.kind, setting, s, target, budget, not args.no_curriculum, tmp,
                                  args.base == "previous") for s in seeds]  # fmt: skip
            print(setting, *summary(rows[setting], budget), flush=True)
    if args.sb3 or args.sb3_only:
        rows["sb3-contrib RecurrentPPO"] = []
        for seed in seeds:
            rows["sb3-contrib RecurrentPPO"].append(sb3(args.task, seed, target, args.sb3_budget))
            print("sb3-contrib", rows["sb3-contrib RecurrentPPO"][-1], flush=True)
    curriculum = "no curriculum" if args.no_curriculum else "curriculum"
    how = f"{args.base} settings, {args.seeds} seeds, {threads} threads, sb3-contrib 1; {curriculum}"
    table = Table(title=f"Env steps to {target:.0%} success, {args.task} {args.kind} ({how})")
    for col in ("settings", "median steps", "median seconds", "per seed"):
        table.add_column(col, justify="right" if col != "settings" else "left")
    for name, runs in rows.items():
        cap = args.sb3_budget if name.startswith("sb3") else budget
        table.add_row(name, *summary(runs, cap))
    Console().print(table)
    if args.json:
        report = {"task": args.task, "kind": args.kind, "target": target, "curriculum": not args.no_curriculum,
                  "base": args.base,
                  "runs": {name: [dataclasses.asdict(r) for r in runs] for name, runs in rows.items()}}  # fmt: skip
        Path(args.json).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
