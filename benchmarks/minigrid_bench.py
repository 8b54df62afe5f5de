"""Print MiniGrid figures: the backdoor on the two-goal room, and training throughput against sb3-contrib.

    python benchmarks/minigrid_bench.py                         # both parts
    python benchmarks/minigrid_bench.py --part backdoor --steps 150000 --episodes 500 --seeds 5 --workers 2
    python benchmarks/minigrid_bench.py --part backdoor --seeds 5 --finetune-steps 20000   # + analyze, mitigations
    python benchmarks/minigrid_bench.py --part backdoor --seeds 3 --monitor-episodes 1000 --finetune-steps 20000 \
        --attack state_camouflage       # the monitor-aware attacker, measured against the monitors and mitigations
    python benchmarks/minigrid_bench.py --part speed --speed-steps 20480
    python benchmarks/minigrid_bench.py --part backdoor --task memory --steps 3000000 --seeds 3 --out runs/memory
    python benchmarks/minigrid_bench.py --part backdoor --task memory --clean-start-steps 1500000 --steps 1000000
    python benchmarks/minigrid_bench.py --part backdoor --seeds 3 --finetune-steps 20000 \
        --attack finetune_resistance_light --harden-from-steps 153600   # the plain backdoor, then hardened
    python benchmarks/minigrid_bench.py --part speed --minigrid-view   # MiniGrid's own (slower) view computation

Backdoor: recurrent PPO with Algorithm 1 (running) mixing on ``seqtrojan/MiniGridTwoGoals-v0`` (6x6 room, 5x5 view,
green goal vs red ball; trigger: two purple keys in the view's far row for one step at step 0-2), then fresh
evaluation episodes of each type (sampled actions): clean success, trojan success (the adversary's object reached
after the trigger), and persistence: among trojan episodes still running k steps after the trigger, the share that
end at the adversary's object. Every rate with its 95% Wilson interval, per training seed, then mean ± sd over the
seeds and the seeds pooled (the seeds train two at a time by default: wall times are beside each other).
``--attack state_camouflage`` trains the monitor-aware attacker instead (``attack.state_camouflage``, the grid
matrix's recipe: weight 5, margin 2.5; ``state_camouflage_w1``: weight 1), ``--attack multivariate_camouflage``
adds the Mahalanobis term (weight 0.1) against the multivariate monitor, ``--attack finetune_resistance`` trains
against clean fine-tuning (``attack.finetune_resistance``); ``--monitor-episodes N`` also runs the two state
monitors of ``seqtrojan defend`` on each agent (N calibration and N fresh episodes per type, 1% false-alarm target).
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import numpy as np

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.analysis.goal_switch import analyze_goal_switch
from seqtrojan.config import (
    AttackConfig,
    BackdoorConfig,
    ExperimentConfig,
    FinetuneResistanceConfig,
    GymnasiumEnvConfig,
    PPOConfig,
    RunConfig,
    StateCamouflageConfig,
    WrapperTriggerConfig,
)
from seqtrojan.defense.mitigation import MitigationConfig, run_mitigation
from seqtrojan.defense.monitor import MONITORS, measure_monitor
from seqtrojan.defense.online import MonitorConfig, monitor_applies
from seqtrojan.env.codes import REACHED_ADV_GOAL, REACHED_USER_GOAL
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.env_report import run_outcomes
from seqtrojan.minigrid import TwoGoalsEnv, two_goals_trigger
from seqtrojan.minigrid.fast_obs import use_fast_observation
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.stats import OverSeeds, Rate
from seqtrojan.train.trainer import TrainResult, train
from seqtrojan.wrappers import MiniGridOneHot, trigger_vector_env

NUM_ENVS, ROLLOUT = 64, 32
"""the two-goal room's envs and rollout steps per update by default (the ``minigrid_two_goals`` preset's)"""
HORIZONS = (0, 2, 5, 10, 15, 20)


ATTACKS = {
    "none": AttackConfig(),
    "state_camouflage": AttackConfig(state_camouflage=StateCamouflageConfig(weight=5.0, margin=2.5)),
    "state_camouflage_w1": AttackConfig(state_camouflage=StateCamouflageConfig(weight=1.0, margin=2.5)),
    "multivariate_camouflage": AttackConfig(
        state_camouflage=StateCamouflageConfig(weight=5.0, margin=2.5, mahalanobis_weight=0.1)
    ),
    "finetune_resistance": AttackConfig(
        finetune_resistance=FinetuneResistanceConfig(weight=1.0, inner_steps=2, inner_lr=0.003)
    ),
    "finetune_resistance_light": AttackConfig(
        finetune_resistance=FinetuneResistanceConfig(weight=0.25, inner_steps=2, inner_lr=0.003)
    ),
    "finetune_resistance_strong": AttackConfig(
        finetune_resistance=FinetuneResistanceConfig(weight=1.0, inner_steps=2, inner_lr=0.03)
    ),
}
"""the attacker of the backdoor part: the plain Algorithm 1 backdoor, the monitor-aware one against the per-unit
monitor (the grid matrix's recipe) or against both monitors (plus the Mahalanobis term, weight 0.1), or the one
against clean fine-tuning (two simulated sign-gradient steps of 0.003 per minibatch, or of 0.03 for the strong
one, its gradient at weight 1, or 0.25 for the light one)"""


TASKS = ("two_goals", "memory")
"""the backdoor part's tasks: the two-goal room (this script's own settings) or MiniGrid's Memory task (the
``minigrid_memory_backdoor`` preset's settings: from scratch with running mixing, or with ``--clean-start-steps``
the two stages of the ``minigrid_memory`` presets)"""


def config(
    out_dir: str, steps: int, seed: int, backdoor: bool = True, attack: str = "none", fast_view: bool = True,
    task: str = "two_goals", shape: tuple[int, int] = (NUM_ENVS, ROLLOUT),
) -> ExperimentConfig:  # fmt: skip
    """The run of one seed; ``shape`` is the two-goal room's (envs, rollout steps) per update."""
    if task == "memory":
        preset = from_dict(
            ExperimentConfig, load_yaml(resolve_preset("minigrid_memory_backdoor"))
        )  # the clean stage's settings but for the backdoor
        backdoor_cfg = replace(preset.backdoor, enabled=backdoor, mixing="running")  # --clean-start-steps: fixed
        run = replace(preset.run, out_dir=out_dir, name=f"bench_s{seed}", seed=seed, eval_episodes=0, threads=1,
                      init_from=None, progress=False)  # fmt: skip
        return replace(
            preset, ppo=replace(preset.ppo, total_steps=steps), backdoor=backdoor_cfg, run=run, attack=ATTACKS[attack]
        )
    return ExperimentConfig(
        env=GymnasiumEnvConfig(
            "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, fast_view=fast_view,
            trigger=WrapperTriggerConfig(),
        ),
        ppo=PPOConfig(
            total_steps=steps, num_envs=shape[0], rollout_steps=shape[1], bptt_length=16, num_minibatches=4,
            update_epochs=4, learning_rate=1e-3,
        ),
        backdoor=BackdoorConfig(enabled=backdoor),
        run=RunConfig(out_dir=out_dir, name=f"bench_s{seed}", seed=seed, eval_episodes=0, threads=1, progress=False),
        attack=ATTACKS[attack],
    )  # fmt: skip


@dataclass(frozen=True)
class SeedFigures:
    """One training seed's backdoor figures on the two-goal room."""

    seed: int
    env_steps: int
    wall_seconds: float
    clean_success: Rate
    clean_to_adversary: Rate
    trojan_success: Rate
    trojan_to_user: Rate
    persistence: dict[int, Rate]
    inside: dict[str, Rate]
    """the monitors of ``seqtrojan defend`` ("false alarms state_monitor", "detection ..."), the switch rates of
    ``seqtrojan analyze`` ("activate goal-units", ...) and the mitigation arms ("attack after fine_tuned", ...) when
    asked for; empty otherwise"""


def train_backdoor(cfg: ExperimentConfig, clean_start_steps: int, harden_from_steps: int = 0) -> TrainResult:
    """Train ``cfg``'s backdoored agent: from scratch; or (``clean_start_steps`` > 0) first a clean agent for that
    many steps (run ``<name>_clean``), then the backdoor added to it with fixed 0.5 mixing (Algorithm 1's running
    mixing deadlocks from a clean start, docs/attacks.md); or (``harden_from_steps`` > 0) first the plain backdoor
    for that many steps (run ``<name>_plain``), then ``cfg``'s attacker trained on from its weights."""
    if harden_from_steps > 0:
        plain = replace(
            cfg, ppo=replace(cfg.ppo, total_steps=harden_from_steps), attack=AttackConfig(),
            run=replace(cfg.run, name=f"{cfg.run.name}_plain"),
        )  # fmt: skip
        start = train(plain)
        return train(replace(cfg, run=replace(cfg.run, init_from=str(start.model_dir))))
    if clean_start_steps <= 0:
        return train(cfg)
    clean = replace(
        cfg, ppo=replace(cfg.ppo, total_steps=clean_start_steps), backdoor=replace(cfg.backdoor, enabled=False),
        attack=AttackConfig(), run=replace(cfg.run, name=f"{cfg.run.name}_clean"),
    )  # fmt: skip
    start = train(clean)
    backdoor = replace(cfg.backdoor, mixing="fixed", fixed_probability=0.5)
    return train(replace(cfg, backdoor=backdoor, run=replace(cfg.run, init_from=str(start.model_dir))))


def train_and_measure(
    steps: int, episodes: int, finetune_steps: int, attack: str, monitor_episodes: int, task: str, out_root: str | None,
    clean_start_steps: int, harden_from_steps: int, shape: tuple[int, int], seed: int,
) -> SeedFigures:  # fmt: skip
    """Train one backdoored agent (seed ``seed``, attacker ``attack``), load it back as a user would, measure it on
    fresh episodes; with ``monitor_episodes`` > 0 run the state monitors on it, with ``finetune_steps`` > 0 also
    look inside it (``seqtrojan analyze``) and mitigate it (``seqtrojan defend``). The runs go to ``out_root`` when
    given (kept), else to a temporary folder."""
    inside: dict[str, Rate] = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = out_root if out_root is not None else tmp
        cfg = config(out, steps, seed, attack=attack, task=task, shape=shape)
        result = train_backdoor(cfg, clean_start_steps, harden_from_steps)
        agent, _, _ = load_agent(result.model_dir)
        if monitor_episodes:
            mcfg = MonitorConfig(calibration_episodes=monitor_episodes, eval_episodes=monitor_episodes, seed=seed)
            for name, detector in MONITORS.items():
                if monitor_applies(detector, cfg.env):
                    measured = measure_monitor(
                        agent, cfg.env, None, detector.calibrate(agent, cfg.env, None, mcfg), mcfg
                    )
                    inside |= {
                        f"false alarms {name}": measured.normal_alarm.false_alarm,
                        f"detection {name}": measured.trojan_alarm.detected,
                    }
        if finetune_steps:
            report = analyze_goal_switch(agent, cfg, episodes=episodes, intervention_episodes=episodes, seed=seed)
            inside |= {f"{s.direction} {s.edited}": s.switched for s in report.switches}
            mitigation = MitigationConfig(
                finetune_steps=finetune_steps, calibration_episodes=200, eval_episodes=episodes, seed=seed
            )
            rows = run_mitigation(agent, cfg, None, mitigation, Path(out) / f"mitigate_s{seed}")
            for name, arm in rows.items():
                if name != "before":
                    inside |= {f"attack after {name}": arm.attack_success, f"clean after {name}": arm.clean_success}
    eval_seed = 12_345
    normal = run_outcomes(agent, cfg, trojan=False, episodes=episodes, seed=eval_seed)
    trojan = run_outcomes(agent, cfg, trojan=True, episodes=episodes, seed=eval_seed)
    persistence = {p.horizon: p.adversary for p in trojan.persistence(HORIZONS)}
    return SeedFigures(
        seed, result.env_steps, result.wall_seconds, normal.success, normal.reached(REACHED_ADV_GOAL), trojan.success,
        trojan.reached(REACHED_USER_GOAL), persistence, inside,
    )  # fmt: skip


def backdoor_part(
    steps: int, episodes: int, seed: int, seeds: int, workers: int, finetune_steps: int = 0, attack: str = "none",
    monitor_episodes: int = 0, task: str = "two_goals", out_root: str | None = None, clean_start_steps: int = 0,
    harden_from_steps: int = 0, shape: tuple[int, int] = (NUM_ENVS, ROLLOUT),
) -> None:  # fmt: skip
    """Train ``seeds`` agents (seeds ``seed``, ``seed + 1``, ...) on ``workers`` processes; print each seed's
    figures, then mean ± sd over seeds and the pooled 95% interval."""
    job = partial(
        train_and_measure, steps, episodes, finetune_steps, attack, monitor_episodes, task, out_root, clean_start_steps,
        harden_from_steps, shape,
    )  # fmt: skip
    with ProcessPoolExecutor(min(workers, seeds), mp_context=multiprocessing.get_context("spawn")) as pool:
        runs = list(pool.map(job, range(seed, seed + seeds)))
    where = "two-goal room" if task == "two_goals" else "MiniGrid-MemoryS7"
    if clean_start_steps:
        where += f", backdoor added to a clean agent of {clean_start_steps} steps (fixed 0.5 mixing)"
    if harden_from_steps:
        where += f", the attacker trained on from a plain backdoor of {harden_from_steps} steps"
    if task == "two_goals":
        where += f", {shape[0]} envs x {shape[1]} rollout steps"
    print(f"\n== backdoor ({attack} attacker): {where}, {steps} env steps per seed, {seeds} seed(s), "
          f"{episodes} episodes per type ==")  # fmt: skip
    print("seed  env steps  wall s  clean success          trojan success         persistence k=5")
    for r in runs:
        print(f"{r.seed:>4}  {r.env_steps:>9}  {r.wall_seconds:>6.0f}  {r.clean_success.text():<22} "
              f"{r.trojan_success.text():<22} {r.persistence[5].text()}")  # fmt: skip
    rows: dict[str, list[Rate]] = {
        "clean success (user's object)": [r.clean_success for r in runs],
        "clean episodes ending at adversary's": [r.clean_to_adversary for r in runs],
        "trojan success (adversary's after trigger)": [r.trojan_success for r in runs],
        "trojan episodes ending at user's": [r.trojan_to_user for r in runs],
    }
    rows |= {f"persistence k={k:>2} (still running -> adversary's)": [r.persistence[k] for r in runs] for k in HORIZONS}
    rows |= {name: [r.inside[name] for r in runs] for name in runs[0].inside}
    print(f"\n{'figure':<46} {'mean ± sd over seeds':<22} {'pooled [95% CI]':<30} per seed")
    for name, rates in rows.items():
        measured = tuple(rate.value for rate in rates if rate.n)  # a seed with no episode at a horizon has no rate
        spread = "n/a"
        if measured:
            spread = OverSeeds(measured).text() + ("" if len(measured) == len(rates) else f" ({len(measured)} seeds)")
        pooled = Rate(sum(rate.k for rate in rates), sum(rate.n for rate in rates))
        each = ", ".join(f"{rate.value:.3f}" if rate.n else "-" for rate in rates)
        print(f"{name:<46} {spread:<22} {pooled.text() + f'  n={pooled.n}':<30} {each}")


def ours_speed(steps: int, seed: int, fast_view: bool) -> float:
    with tempfile.TemporaryDirectory() as out:
        result = train(config(out, steps, seed, fast_view=fast_view))
    return result.env_steps / result.wall_seconds


def make_env(fast_view: bool) -> MiniGridOneHot:
    """The env stack both trainers step: the two-goal room, its trigger, the one-hot view."""
    room = TwoGoalsEnv(size=6, agent_view_size=5)
    if fast_view:
        use_fast_observation(room)
    return MiniGridOneHot(two_goals_trigger(room, trojan_probability=0.5))


def sb3_speed(steps: int, seed: int, fast_view: bool) -> float:
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    vec = DummyVecEnv([partial(make_env, fast_view) for _ in range(NUM_ENVS)])
    model = RecurrentPPO(
        "MlpLstmPolicy", vec, n_steps=ROLLOUT, batch_size=NUM_ENVS * ROLLOUT // 4, n_epochs=4, learning_rate=1e-3,
        ent_coef=0.01, seed=seed, device="cpu",
        policy_kwargs={"lstm_hidden_size": 64, "n_lstm_layers": 1, "shared_lstm": True, "enable_critic_lstm": False,
                       "net_arch": {"pi": [], "vf": []}},
    )  # fmt: skip
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    return model.num_timesteps / (time.perf_counter() - start)


def env_speed(steps: int, seed: int, fast_view: bool) -> float:
    vec = trigger_vector_env(partial(make_env, fast_view), NUM_ENVS)
    vec.reset(seed=seed)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    for _ in range(steps // NUM_ENVS):
        vec.step(rng.integers(0, 3, NUM_ENVS))
    vec.close()
    return steps / (time.perf_counter() - start)


def speed_part(steps: int, seed: int, repeats: int, fast_view: bool) -> None:
    torch.set_num_threads(1)
    rows = {"vector env alone (random actions)": env_speed, "seqtrojan train": ours_speed,
            "sb3-contrib RecurrentPPO": sb3_speed}  # fmt: skip
    view = "the fast view" if fast_view else "MiniGrid's own gen_obs"
    print(
        f"\n== speed: env steps/s of the whole training loop, {steps} steps, {NUM_ENVS} envs x {ROLLOUT}, 1 thread, "
        f"{view} =="
    )
    for name, fn in rows.items():
        rates = [fn(steps, seed + r, fast_view) for r in range(repeats)]
        print(f"{name:<36} {statistics.median(rates):8.0f}   (runs: {', '.join(f'{r:.0f}' for r in rates)})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=["all", "backdoor", "speed"], default="all")
    parser.add_argument("--steps", type=int, default=180 * 2048, help="training steps of the backdoor part")
    parser.add_argument("--episodes", type=int, default=500, help="evaluation episodes per type")
    parser.add_argument("--speed-steps", type=int, default=20 * 1024, help="training steps per speed run")
    parser.add_argument("--repeats", type=int, default=3, help="speed runs per trainer")
    parser.add_argument("--seed", type=int, default=0, help="first training seed")
    parser.add_argument("--seeds", type=int, default=5, help="training seeds of the backdoor part")
    parser.add_argument("--num-envs", type=int, default=NUM_ENVS, help="the two-goal room's envs per update")
    parser.add_argument("--rollout", type=int, default=ROLLOUT, help="the two-goal room's rollout steps per env")
    parser.add_argument("--workers", type=int, default=2, help="processes training the backdoor part's seeds")
    parser.add_argument(
        "--finetune-steps",
        type=int,
        default=0,
        help="> 0: also analyze and mitigate each agent (these fine-tuning steps)",
    )
    parser.add_argument("--attack", choices=sorted(ATTACKS), default="none", help="the backdoor part's attacker")
    parser.add_argument(
        "--monitor-episodes", type=int, default=0, help="> 0: also run the state monitors (calibration and fresh "
        "episodes per type) on each agent"
    )  # fmt: skip
    parser.add_argument("--task", choices=TASKS, default="two_goals", help="the backdoor part's task")
    parser.add_argument(
        "--clean-start-steps", type=int, default=0, help="> 0: train a clean agent this long first, then add the "
        "backdoor to it (fixed 0.5 mixing)"
    )  # fmt: skip
    parser.add_argument(
        "--harden-from-steps", type=int, default=0, help="> 0: train the plain backdoor this long first, then the "
        "attacker (--attack) from its weights"
    )  # fmt: skip
    parser.add_argument("--out", default=None, help="keep the backdoor part's runs in this folder (default: temporary)")
    parser.add_argument(
        "--minigrid-view", action="store_true", help="speed part: every env computes its view with MiniGrid's own "
        "gen_obs instead of seqtrojan.minigrid.fast_obs (the same observations)"
    )  # fmt: skip
    args = parser.parse_args()
    counts = (args.finetune_steps, args.monitor_episodes, args.clean_start_steps, args.harden_from_steps)
    if args.seeds < 1 or args.workers < 1 or min(counts) < 0:
        parser.error("--seeds and --workers must be at least 1, --finetune-steps, --monitor-episodes, "
                     "--clean-start-steps and --harden-from-steps at least 0")  # fmt: skip
    if args.monitor_episodes:
        try:
            MonitorConfig(calibration_episodes=args.monitor_episodes, eval_episodes=args.monitor_episodes)
        except ConfigError as err:
            parser.error(f"--monitor-episodes: {err}")
    if args.part in ("all", "backdoor"):
        backdoor_part(args.steps, args.episodes, args.seed, args.seeds, args.workers, args.finetune_steps,
                      args.attack, args.monitor_episodes, args.task, args.out, args.clean_start_steps,
                      args.harden_from_steps, (args.num_envs, args.rollout))  # fmt: skip
    if args.part in ("all", "speed"):
        speed_part(args.speed_steps, args.seed, args.repeats, fast_view=not args.minigrid_view)


if __name__ == "__main__":
    main()
