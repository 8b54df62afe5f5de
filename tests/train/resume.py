"""The stop-and-resume harness the trainer's resume tests share: one config trained straight through, and the same
config stopped by SIGTERM after update 3 and resumed, both taking fresh episodes from one env seed at the same
point (resume starts fresh episodes, so the straight run restarts every episode before its 4th rollout, and the
resumed run before its 1st)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

from seqtrojan.config import ExperimentConfig
from seqtrojan.train import trainer as trainer_module
from seqtrojan.train.trainer import TrainResult, load_run_config, train

STOP_AFTER_UPDATE = 3


def straight_and_resumed(
    cfg: ExperimentConfig, monkeypatch, at_stop: Callable[[Path], None] | None = None
) -> tuple[TrainResult, TrainResult]:
    """``cfg`` trained straight (run ``straight``) and stopped then resumed (run ``stopped``); ``at_stop`` sees the
    stopped run's folder before the resume."""
    fresh_episodes_before = {"rollout": STOP_AFTER_UPDATE + 1}

    class FreshEpisodesCollector(trainer_module.RolloutCollector):
        rollouts = 0

        def collect(self):
            self.rollouts += 1
            if self.rollouts == fresh_episodes_before["rollout"]:
                self.env.reset(seed=123_456_789)
                self.reset()
            return super().collect()

    monkeypatch.setattr(trainer_module, "RolloutCollector", FreshEpisodesCollector)
    straight = train(dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name="straight")))

    def sigterm_after_three(scalars):
        if scalars["update"] == STOP_AFTER_UPDATE:
            os.kill(os.getpid(), signal.SIGTERM)  # the trainer's handler stops before the next update
        return False

    stopped = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name="stopped"))
    stop_step = STOP_AFTER_UPDATE * cfg.ppo.batch_size
    with pytest.raises(KeyboardInterrupt, match=f"stopped at {stop_step} env steps"):
        train(stopped, callback=sigterm_after_three)
    run = Path(cfg.run.out_dir) / "stopped"
    if at_stop is not None:
        at_stop(run)
    fresh_episodes_before["rollout"] = 1
    return straight, train(load_run_config(run), resume=run)


def logged_rows(run_dir: Path) -> list[dict]:
    """The run's metrics.jsonl rows without the wall-time figures (which differ between any two runs)."""
    timing = {"time/elapsed_s", "charts/steps_per_second", "charts/collect_share"}
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in timing} for line in lines]
