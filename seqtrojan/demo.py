"""The foundation demo: build the envs, run random and scripted agents, render episodes to text and PNG.

    seqtrojan demo --out outputs/demo

Writes ``summary.json`` (success, hole and time-out rates with 95% intervals, env speed), ``episode_*.txt``
(ANSI frames) and ``trajectories.png`` (one layout run with and without the trigger, as the paper's Figure 6).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import torch
from gymnasium.utils.env_checker import check_env
from rich.console import Console
from rich.table import Table

from seqtrojan.bench.env_speed import measure_env_speed
from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.config import min_steps_to_goal
from seqtrojan.env.rollout import run_episodes
from seqtrojan.env.scripted import OracleAgent, RandomAgent
from seqtrojan.report.figures import frames_to_text, plot_trajectory_pair, record_episode, run_pair


@dataclass
class DemoArgs:
    """Build environments, run random and scripted agents, and render a few episodes to text and PNG."""

    out: Path = Path("outputs/demo")
    """output folder"""
    size: int = 7
    """grid side N"""
    holes: int = 3
    """holes H"""
    episodes: int = 1000
    """episodes per (agent, env) pair, all run as one batch"""
    seed: int = 0
    """seed of the episodes"""
    device: str = "cpu"
    """torch device (cpu or cuda)"""


def run_demo(args: DemoArgs) -> dict:
    console = Console()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    cfg = EnvConfig(size=args.size, holes=args.holes)
    summary: dict = {"config": dataclasses.asdict(cfg), "episodes": args.episodes, "agents": {}}

    table = Table(title=f"Scripted agents on {args.size}x{args.size}/{args.holes}, {args.episodes} episodes each")
    for col in ("agent", "env", "success", "95% CI", "hole", "timeout", "wrong goal"):
        table.add_column(col, justify="right")
    for env_name, p_trojan in (("normal", 0.0), ("trojan", 1.0)):
        core = TrojanGridCore(cfg, args.episodes, device=args.device, trojan_probability=p_trojan, phase="eval")
        for agent_name, agent in (("random", RandomAgent(core, args.seed)), ("oracle", OracleAgent(core))):
            batch = run_episodes(core, agent.act, seed=args.seed)
            lo, hi = batch.success_interval()
            wrong = batch.rate("adversary_goal") if env_name == "normal" else batch.rate("user_goal")
            row = {
                "success": batch.success_rate,
                "ci95": [lo, hi],
                "hole": batch.rate("hole"),
                "timeout": batch.rate("timeout"),
                "wrong_goal": wrong,
            }
            summary["agents"][f"{agent_name}/{env_name}"] = row
            table.add_row(
                agent_name,
                env_name,
                f"{row['success']:.3f}",
                f"[{lo:.3f}, {hi:.3f}]",
                f"{row['hole']:.3f}",
                f"{row['timeout']:.3f}",
                f"{wrong:.3f}",
            )
    console.print(table)

    # One layout, run by the oracle with and without the trigger (the paper's Figure 6, scripted).
    core = TrojanGridCore(cfg, 1, seed=args.seed, device=args.device, phase="eval")
    trigger_step = min(12, min_steps_to_goal(args.size) - 1)
    runs = run_pair(core, core.layout(0), trigger_step, lambda: OracleAgent(core).act)
    for name, (frames, _) in runs.items():
        (out / f"episode_{name}.txt").write_text(frames_to_text(frames))
    plot_trajectory_pair(runs, "Same layout, with and without the trigger (scripted oracle)", out / "trajectories.png")

    random_core = TrojanGridCore(cfg, 1, seed=args.seed + 1, device=args.device, trojan_probability=1.0)
    random_frames, _ = record_episode(random_core, RandomAgent(random_core).act)
    (out / "episode_random.txt").write_text(frames_to_text(random_frames))

    env = gym.make("seqtrojan/Trojan-v0", render_mode="rgb_array", size=args.size, holes=args.holes)
    check_env(env.unwrapped)
    summary["gymnasium_check_env"] = "passed"

    start = time.perf_counter()
    speed = measure_env_speed(args.size, args.holes, 4096, steps=100, device=args.device)
    summary["env_steps_per_second_4096_envs"] = speed.steps_per_second
    summary["threads"] = torch.get_num_threads()
    summary["seconds_for_speed_check"] = time.perf_counter() - start
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    console.print(
        f"env speed: {speed.steps_per_second / 1e6:.2f} M steps/s with 4096 envs; Gymnasium check_env passed\n"
        f"wrote {out}/summary.json, {out}/trajectories.png, {out}/episode_normal.txt, "
        f"{out}/episode_trojan.txt, {out}/episode_random.txt"
    )
    return summary
