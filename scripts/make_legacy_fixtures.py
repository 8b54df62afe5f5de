"""Write the legacy fixtures under ``tests/fixtures/legacy/``: tiny model folders and stopped runs.

These folders were written by seqtrojan at commit 9ba8742 and are kept as-is so tests can check that model folders
(and stopped run directories) from that version still load; rerunning the script only reproduces them on that
commit. Do not regenerate them after a format change: that would test the new code against itself.

    python scripts/make_legacy_fixtures.py            # from the repository root

Folders (each trained for real, for a budget of one or two PPO updates, on the CPU with one thread):

    grid_lstm/            grid-world model (model.safetensors + card.json), smoke preset, LSTM (8, 4), backdoored
    gym_two_goals/        Gymnasium model (model.safetensors + gym_card.json), minigrid_two_goals, LSTM (8, 4)
    gym_memory_gru_conv/  Gymnasium model, minigrid_memory, GRU (8,) behind a conv encoder (4,), clean
    grid_run/             a grid-world run stopped (SIGTERM) after its first update and checkpoint
    gym_run/              a Gymnasium run (minigrid_two_goals, LSTM (4, 4) to keep it small) stopped the same way

The runs are trained in a temporary folder entered as the working directory, with ``run.out_dir: runs``, so that
no saved config names an absolute path.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from seqtrojan.config import ExperimentConfig
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train.gym_config import GymTrainConfig, load_gym_config
from seqtrojan.train.gym_trainer import train_gym
from seqtrojan.train.trainer import train

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "tests" / "fixtures" / "legacy"
FOLDERS = ("grid_lstm", "gym_two_goals", "gym_memory_gru_conv", "grid_run", "gym_run")


def grid_config(name: str) -> ExperimentConfig:
    """The ``smoke`` preset (as ``seqtrojan train --config smoke`` reads it) at a tiny size, backdoored: two rollouts
    of 16 envs x 16 steps, a checkpoint after each."""
    base = from_dict(ExperimentConfig, load_yaml(resolve_preset("smoke")), "")
    return dataclasses.replace(
        base,
        agent=dataclasses.replace(base.agent, lstm_sizes=(8, 4)),
        ppo=dataclasses.replace(base.ppo, num_envs=16, rollout_steps=16, total_steps=512),
        backdoor=dataclasses.replace(base.backdoor, enabled=True),
        run=dataclasses.replace(
            base.run, out_dir="runs", name=name, eval_episodes=20, checkpoint_every=256, progress=False, threads=1
        ),
    )


def gym_config(
    preset: str, name: str, lstm_sizes: tuple[int, ...], cell: str = "lstm", conv: tuple[int, ...] = ()
) -> GymTrainConfig:
    """A shipped Gymnasium preset at a tiny size: two rollouts of 4 envs x 16 steps, a checkpoint after each."""
    base = load_gym_config(preset)
    return dataclasses.replace(
        base,
        agent=dataclasses.replace(base.agent, lstm_sizes=lstm_sizes, cell=cell, conv=conv),
        ppo=dataclasses.replace(
            base.ppo, num_envs=4, rollout_steps=16, bptt_length=16, num_minibatches=1, total_steps=128
        ),
        run=dataclasses.replace(base.run, out_dir="runs", name=name, eval_episodes=10, checkpoint_every=64, threads=1),
    )


@contextmanager
def working_directory(path: Path) -> Iterator[None]:
    """Run inside ``path``, so that the relative ``run.out_dir`` lands there (``contextlib.chdir`` is 3.11+)."""
    before = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


def stop_after_first_update(scalars: dict[str, Any]) -> bool:
    """A training callback that stops the run as SIGTERM does: the trainer's handler sets its stop flag, and the
    loop writes a checkpoint and raises KeyboardInterrupt before the next update."""
    signal.raise_signal(signal.SIGTERM)
    return False


def stopped_run(start: Callable[[], object]) -> None:
    """Start a run that :func:`stop_after_first_update` stops; a run that finishes is an error."""
    try:
        start()
    except KeyboardInterrupt as stop:
        print(f"  {stop}")
        return
    raise RuntimeError("the run finished instead of stopping after its first update")


def copy_folder(source: Path, name: str, out: Path) -> None:
    target = out / name
    shutil.copytree(source, target)
    for path in sorted(target.rglob("*")):
        if path.is_file():
            print(f"  {path.relative_to(out)}  {path.stat().st_size:,} B")


def make_fixtures(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in FOLDERS:
        if (out / name).exists():
            shutil.rmtree(out / name)
    with tempfile.TemporaryDirectory(prefix="seqtrojan-fixtures-") as tmp, working_directory(Path(tmp)):
        runs = Path(tmp) / "runs"

        print("grid_lstm: smoke preset, LSTM (8, 4), backdoored")
        train(grid_config("grid_lstm"))
        copy_folder(runs / "grid_lstm" / "model", "grid_lstm", out)

        print("gym_two_goals: minigrid_two_goals, LSTM (8, 4), backdoored")
        train_gym(gym_config("minigrid_two_goals", "gym_two_goals", (8, 4)))
        copy_folder(runs / "gym_two_goals" / "model", "gym_two_goals", out)

        print("gym_memory_gru_conv: minigrid_memory, GRU (8,), conv (4,), clean")
        train_gym(gym_config("minigrid_memory", "gym_memory_gru_conv", (8,), cell="gru", conv=(4,)))
        copy_folder(runs / "gym_memory_gru_conv" / "model", "gym_memory_gru_conv", out)

        print("grid_run: the grid_lstm config, stopped after its first update")
        stopped_run(lambda: train(grid_config("grid_run"), callback=stop_after_first_update))
        shutil.rmtree(runs / "grid_run" / "tb")  # TensorBoard events: a resume does not read them (host name inside)
        copy_folder(runs / "grid_run", "grid_run", out)

        print("gym_run: the gym_two_goals config with LSTM (4, 4), stopped after its first update")
        config = gym_config("minigrid_two_goals", "gym_run", (4, 4))  # (8, 4) and Adam's moments: over 200 KB
        stopped_run(lambda: train_gym(config, callback=stop_after_first_update))
        copy_folder(runs / "gym_run", "gym_run", out)

    for name in ("grid_run", "gym_run"):  # a stopped run has neither
        for leftover in ("model", "evaluation.json"):
            if (out / name / leftover).exists():
                raise RuntimeError(f"{name} holds {leftover}: it did not stop before finishing")
    total = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"total {total:,} B under {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help=f"folder to write into (default: {OUT})")
    args = parser.parse_args()
    make_fixtures(args.out.resolve())


if __name__ == "__main__":
    main()
