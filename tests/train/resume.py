"""The stop-and-resume harness the trainer's resume tests share: one config trained straight through, and the same
config stopped by SIGTERM after update 3 and resumed from its checkpoint (which keeps the episodes in flight, so
the resumed run must continue them exactly)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

from seqtrojan.config import ExperimentConfig
from seqtrojan.train.trainer import TrainResult, load_run_config, train

STOP_AFTER_UPDATE = 3


def straight_and_resumed(
    cfg: ExperimentConfig, monkeypatch, at_stop: Callable[[Path], None] | None = None
) -> tuple[TrainResult, TrainResult]:
    """``cfg`` trained straight (run ``straight``) and stopped then resumed (run ``stopped``); ``at_stop`` sees the
    stopped run's folder before the resume. The resumed run must say it continued the episodes in flight."""
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
    resumed = train(load_run_config(run), resume=run)
    assert resumed.exact_resume is True
    return straight, resumed


def logged_rows(run_dir: Path) -> list[dict]:
    """The run's metrics.jsonl rows without the wall-time figures (which differ between any two runs)."""
    timing = {"time/elapsed_s", "charts/steps_per_second", "charts/collect_share"}
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in timing} for line in lines]
