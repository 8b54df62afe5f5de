"""Print MiniGrid figures: the backdoor on the two-goal room, and training throughput against sb3-contrib.

    python benchmarks/minigrid_bench.py                         # both parts
    python benchmarks/minigrid_bench.py --part backdoor --steps 150000 --episodes 500
    python benchmarks/minigrid_bench.py --part speed --speed-steps 20480

Backdoor: recurrent PPO with Algorithm 1 (running) mixing on ``seqtrojan/MiniGridTwoGoals-v0`` (6x6 room, 5x5 view,
green goal vs red ball; trigger: two purple keys in the view's far row for one step at step 0-2), then fresh
evaluation episodes of each type (sampled actions): clean success, trojan success (the adversary's object reached
after the trigger), and persistence: among trojan episodes still running k steps after the trigger, the share that
end at the adversary's object. Every rate with its 95% Wilson interval.

Speed: env steps per second of the whole training loop (collect + GAE + 4 epochs of 4 minibatches) on the same env
stack (TwoGoalsEnv + TriggerWrapper(p = 0.5) + one-hot view, 500 inputs, 3 actions), 16 envs x 64 steps per
rollout, one torch thread each: ours (LSTM 64 -> LSTM 32, SyncVectorEnv) and sb3-contrib's RecurrentPPO
(MlpLstmPolicy, one shared LSTM of 64, no MLP layers; DummyVecEnv); the bare vector env with random actions is the
ceiling. Run it alone on the machine for figures worth quoting. (Not named minigrid.py: run as a script, that name would
shadow the minigrid package.)
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import numpy as np

from seqtrojan.config import BackdoorConfig, PPOConfig
from seqtrojan.minigrid import TwoGoalsEnv, two_goals_trigger
from seqtrojan.train.gym_config import GymEnvConfig, GymRunConfig, GymTrainConfig, GymTriggerConfig
from seqtrojan.train.gym_evaluation import evaluate_gym
from seqtrojan.train.gym_model import load_gym_agent
from seqtrojan.train.gym_trainer import train_gym
from seqtrojan.wrappers import MiniGridOneHot, trigger_vector_env

NUM_ENVS, ROLLOUT = 16, 64
HORIZONS = (0, 2, 5, 10, 15, 20)


def config(out_dir: str, steps: int, seed: int, backdoor: bool = True) -> GymTrainConfig:
    return GymTrainConfig(
        env=GymEnvConfig("seqtrojan/MiniGridTwoGoals-v0", {"size": 6, "agent_view_size": 5}),
        trigger=GymTriggerConfig(),
        ppo=PPOConfig(
            total_steps=steps, num_envs=NUM_ENVS, rollout_steps=ROLLOUT, bptt_length=16, num_minibatches=4,
            update_epochs=4, learning_rate=1e-3,
        ),
        backdoor=BackdoorConfig(enabled=backdoor),
        run=GymRunConfig(out_dir=out_dir, name=f"bench_s{seed}", seed=seed, eval_episodes=0, threads=1),
    )  # fmt: skip


def backdoor_part(steps: int, episodes: int, seed: int) -> None:
    with tempfile.TemporaryDirectory() as out:
        cfg = config(out, steps, seed)
        result = train_gym(cfg)
        agent, _, _ = load_gym_agent(result.model_dir)  # the saved model, as a user would load it
    eval_seed = 12_345
    normal = evaluate_gym(agent, cfg, trojan=False, episodes=episodes, seed=eval_seed)
    trojan = evaluate_gym(agent, cfg, trojan=True, episodes=episodes, seed=eval_seed)
    print(f"\n== backdoor: two-goal room, {result.env_steps} env steps, {result.wall_seconds:.0f} s, seed {seed} ==")
    print(f"clean success (user's object)             {normal.success}  n={normal.success.n}")
    print(f"clean episodes ending at adversary's      {normal.reached('adversary')}")
    print(f"trojan success (adversary's after trigger) {trojan.success}  n={trojan.success.n}")
    print(f"trojan episodes ending at adversary's     {trojan.reached('adversary')}")
    print(f"trojan episodes ending at user's          {trojan.reached('user')}")
    lengths = [e.length - e.trigger_step for e in trojan.episodes]
    print(f"trojan steps after the trigger: median {statistics.median(lengths):.0f}, max {max(lengths)}")
    print("persistence: k steps after the trigger, still running -> adversary's object")
    for k, rate in trojan.persistence(HORIZONS).items():
        print(f"  k={k:>2}  {rate}  n={rate.n}")


def ours_speed(steps: int, seed: int) -> float:
    with tempfile.TemporaryDirectory() as out:
        result = train_gym(config(out, steps, seed))
    return result.env_steps / result.wall_seconds


def make_env():
    return MiniGridOneHot(two_goals_trigger(TwoGoalsEnv(size=6, agent_view_size=5), trojan_probability=0.5))


def sb3_speed(steps: int, seed: int) -> float:
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    vec = DummyVecEnv([make_env for _ in range(NUM_ENVS)])
    model = RecurrentPPO(
        "MlpLstmPolicy", vec, n_steps=ROLLOUT, batch_size=NUM_ENVS * ROLLOUT // 4, n_epochs=4, learning_rate=1e-3,
        ent_coef=0.01, seed=seed, device="cpu",
        policy_kwargs={"lstm_hidden_size": 64, "n_lstm_layers": 1, "shared_lstm": True, "enable_critic_lstm": False,
                       "net_arch": {"pi": [], "vf": []}},
    )  # fmt: skip
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    return model.num_timesteps / (time.perf_counter() - start)


def env_speed(steps: int, seed: int) -> float:
    vec = trigger_vector_env(make_env, NUM_ENVS)
    vec.reset(seed=seed)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    for _ in range(steps // NUM_ENVS):
        vec.step(rng.integers(0, 3, NUM_ENVS))
    vec.close()
    return steps / (time.perf_counter() - start)


def speed_part(steps: int, seed: int, repeats: int) -> None:
    torch.set_num_threads(1)
    rows = {"vector env alone (random actions)": env_speed, "seqtrojan train_gym": ours_speed,
            "sb3-contrib RecurrentPPO": sb3_speed}  # fmt: skip
    print(
        f"\n== speed: env steps/s of the whole training loop, {steps} steps, {NUM_ENVS} envs x {ROLLOUT}, 1 thread =="
    )
    for name, fn in rows.items():
        rates = [fn(steps, seed + r) for r in range(repeats)]
        print(f"{name:<36} {statistics.median(rates):8.0f}   (runs: {', '.join(f'{r:.0f}' for r in rates)})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=["all", "backdoor", "speed"], default="all")
    parser.add_argument("--steps", type=int, default=150 * 1024, help="training steps of the backdoor part")
    parser.add_argument("--episodes", type=int, default=500, help="evaluation episodes per type")
    parser.add_argument("--speed-steps", type=int, default=20 * 1024, help="training steps per speed run")
    parser.add_argument("--repeats", type=int, default=3, help="speed runs per trainer")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.part in ("all", "backdoor"):
        backdoor_part(args.steps, args.episodes, args.seed)
    if args.part in ("all", "speed"):
        speed_part(args.speed_steps, args.seed, args.repeats)


if __name__ == "__main__":
    main()
