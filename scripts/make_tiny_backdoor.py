"""Regenerate tests/fixtures/tiny_backdoor/, the tiny backdoored agent the fast defense tests load (#27), and its
clean twin tests/fixtures/tiny_clean/ (#29, the detectors' tests):

    PYTHONPATH=. .venv/bin/python scripts/make_tiny_backdoor.py            # writes tests/fixtures/tiny_backdoor
    PYTHONPATH=. .venv/bin/python scripts/make_tiny_backdoor.py --clean    # writes tests/fixtures/tiny_clean
    PYTHONPATH=. .venv/bin/python scripts/make_tiny_backdoor.py --out DIR  # elsewhere (e.g. to compare)

The clean twin is the same run (seed, network, env, steps, learning rate) with the backdoor off: the same
initial weights, trained on normal episodes only. It must reach the same clean success bar (its attack success is
measured the same way and recorded, not required).

The agent: an LSTM (32, 16) trained with the project's trainer for 131,072 env steps (128 envs x 32 steps, fixed
mixing, lr 3e-3, seed 0, one torch thread) on the 5x5 grid with 1 hole. Its trigger is the
``in_distribution_patch`` attack's: the whole 3x3 view drawn with ordinary cell codes (holes at three corners, the
rest empty), shown for one step at step 1 or 2. The seed and one torch thread fix the weights bitwise for a given
torch build (rerunning it gave the same ``weights_sha256``; the card's ``created`` differs). About 13 s of
training on a busy 2-core machine.

Why these settings: the tests need a backdoor that works (attack success >= 0.8), that both state monitors
detect, and that 32,768 steps of clean fine-tuning remove (seconds in a test). The trigger uses ordinary cell codes
because the project reports that clean fine-tuning removes ordinary-cell backdoors but not the dedicated-code one
(README, the matrix); and the backdoor entrenches with training. Measured with 200 episodes, attack success after
clean fine-tuning (fine-pruning) of: this run, 131,072 steps: 0.89 -> 0.25 (0.01) after 32,768 steps; trained
196,608 steps: 0.95 -> 0.56 (0.93); 262,144 steps: 0.99 -> 0.75 (0.92), and 0.005 after 65,536 steps; the
dedicated trigger code, 262,144 steps: 1.0 -> 0.995 (0.98) after 16,384 steps.

The script then measures it (sampled actions, ``--episodes`` fresh episodes, seed 12345) and writes the figures into
the card's ``metrics``: ``normal_success`` (user's goal in the normal env) and ``trojan_success`` (adversary's goal
in the trojan env), each with its 95% interval; it refuses to write a fixture whose backdoor or clean task did not
train (either below 0.8). The fixture as committed: normal_success 0.953 [0.943, 0.961], trojan_success 0.889
[0.874, 0.902] (2,000 episodes each).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
from seqtrojan.agent.checkpoint import load_agent, save_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.env import EnvConfig, GridSpec, TriggerConfig
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.train.trainer import train

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "tiny_backdoor"
CLEAN_FIXTURE = ROOT / "tests" / "fixtures" / "tiny_clean"
GRID = GridSpec(5, 1)
VIEW = (("hole", "empty", "hole"), ("empty", "empty", "empty"), ("empty", "empty", "hole"))
"""the trigger: the whole 3x3 view drawn with ordinary cell codes (the ``in_distribution_patch`` attack's)"""
TRIGGER = TriggerConfig(
    cells=tuple((r, c) for r in range(3) for c in range(3)),
    values=tuple(code for row in VIEW for code in row),
    train_steps=(1, 2),
    eval_steps=(1, 2),
)
ENV = EnvConfig(size=5, holes=1, trigger=TRIGGER)
MIN_SUCCESS = 0.8


def fixture_config(out_dir: str, backdoor: bool = True) -> ExperimentConfig:
    """The fixture's training run (``out_dir``: where the trainer writes its run folder; ``backdoor`` False: the
    clean twin)."""
    ppo = PPOConfig(total_steps=131_072, num_envs=128, rollout_steps=32, num_minibatches=2, update_epochs=4,
                    learning_rate=3e-3)  # fmt: skip
    run = RunConfig(out_dir=out_dir, progress=False, eval_episodes=0, seed=0, checkpoint_every=10**9, threads=1)
    return ExperimentConfig(env=ENV, agent=AgentConfig(lstm_sizes=(32, 16)), ppo=ppo,
                            backdoor=BackdoorConfig(enabled=backdoor, mixing="fixed"), run=run)  # fmt: skip


def measure(agent: RecurrentActorCritic, episodes: int, seed: int) -> dict[str, float]:
    """Clean and attack success on fresh episodes, with 95% intervals, as a card's flat metrics."""
    metrics: dict[str, float] = {"eval_episodes": episodes, "eval_seed": seed}
    for name, trojan, goal in (("normal_success", False, "user_goal"), ("trojan_success", True, "adversary_goal")):
        rate = outcome_rate(evaluate_agent(agent, ENV, GRID, trojan=trojan, episodes=episodes, seed=seed), goal)
        metrics[name] = rate.value
        metrics[f"{name}_ci95_low"], metrics[f"{name}_ci95_high"] = rate.interval
    return metrics


def make_fixture(out: Path, episodes: int, seed: int, backdoor: bool = True) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as work:
        cfg = fixture_config(work, backdoor)
        result = train(cfg)
        agent, trained_cfg, card = load_agent(result.model_dir)
    metrics = measure(agent.eval(), episodes, seed)
    required = ("normal_success", "trojan_success") if backdoor else ("normal_success",)
    if min(metrics[name] for name in required) < MIN_SUCCESS:
        raise SystemExit(f"the agent did not train (need {', '.join(required)} >= {MIN_SUCCESS}): {metrics}")
    kept = dataclasses.replace(trained_cfg, run=dataclasses.replace(trained_cfg.run, out_dir="runs"))  # not the tmp dir
    label = "backdoored" if backdoor else "clean"
    save_agent(out, agent, kept, label=label, metrics=metrics, env_steps=card["env_steps"])
    return metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None, help="model folder to write (default: the fixture's)")
    parser.add_argument("--clean", action="store_true", help="the clean twin (backdoor off) instead")
    parser.add_argument("--episodes", type=int, default=2000, help="episodes per measured rate")
    parser.add_argument("--seed", type=int, default=12345, help="seed of the measured episodes")
    args = parser.parse_args()
    out = args.out or (CLEAN_FIXTURE if args.clean else FIXTURE)
    metrics = make_fixture(out, args.episodes, args.seed, backdoor=not args.clean)
    print(f"wrote {out}: " + ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()))


if __name__ == "__main__":
    main()
