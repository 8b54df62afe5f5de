"""Where a reproduction keeps what it makes: :class:`RunLayout` knows every artifact path under its output folder,
and reads each stage's results back typed (one method per stage), for the report and for anyone else.

    layout = RunLayout(Path("results/smoke"))
    analysis = layout.analysis()          # an AnalysisResult, or None when the stage has not run
    defense = layout.defense()            # a DefenseResult, or None

The stages write through the same paths (:mod:`seqtrojan.experiments.reproduce`). A result file with a misspelt,
missing or ill-typed key (one written by an older version, or edited by hand) is a ConfigError naming the file
and the key's dotted path.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from seqtrojan.analysis.results import ANALYSIS_FILE, AnalysisResult
from seqtrojan.benchmark.leaderboard import LEADERBOARD_FILE, Leaderboard
from seqtrojan.defense.results import DEFENSE_FILE, DETECTION_FILE, DefenseResult, DetectionResult
from seqtrojan.evaluation.results import EVALUATION_FILE, SweepRow, load_sweep
from seqtrojan.experiment_results import (
    CELLS_FILE,
    CURVES_FILE,
    TRADEOFF_FILE,
    CellsResult,
    CurvesResult,
    TradeoffResult,
)
from seqtrojan.serde import load_json

T = TypeVar("T")

HEADLINE_ROLES = ("clean", "backdoor")


@dataclass(frozen=True)
class TrajectoryResult:
    """The trajectory figure's layout with and without the trigger (``trajectory.json``)."""

    trigger_step: int
    outcomes: dict[str, str]
    """'normal' / 'trojan' -> how that episode ended (user_goal, adversary_goal, hole, timeout)"""


@dataclass(frozen=True)
class RunSummary:
    """One training run, from its model card and metrics log (the report's training table)."""

    grid: str
    env_steps: int
    minutes: float
    sps: float
    """mean env steps per second"""
    stage: int
    """the curriculum stage it ended in"""


@dataclass(frozen=True)
class RunLayout:
    """The artifacts of a reproduction in folder ``out``."""

    out: Path

    # --- paths
    @property
    def config(self) -> Path:
        return self.out / "reproduce.yaml"

    @property
    def timings(self) -> Path:
        return self.out / "timings.json"

    @property
    def report(self) -> Path:
        return self.out / "report.html"

    @property
    def runs(self) -> Path:
        return self.out / "runs"

    def run(self, name: str) -> Path:
        """A training run's folder (``clean``, ``backdoor``, ``<role>_seed<k>``, trade-off agents ...)."""
        return self.runs / name

    def model(self, name: str) -> Path:
        return self.run(name) / "model"

    @property
    def evaluation_dir(self) -> Path:
        return self.out / "evaluation"

    @property
    def evaluation_file(self) -> Path:
        return self.evaluation_dir / EVALUATION_FILE

    def evaluation_seed_file(self, seed: int) -> Path:
        """One training seed's rows (kept so that a stopped evaluation resumes)."""
        return self.evaluation_dir / f"seed{seed}.json"

    @property
    def evaluation_summary(self) -> Path:
        return self.evaluation_dir / "summary.json"

    @property
    def curves_dir(self) -> Path:
        return self.out / "curves"

    @property
    def curves_file(self) -> Path:
        return self.curves_dir / CURVES_FILE

    @property
    def curves_figure(self) -> Path:
        return self.curves_dir / "curves.png"

    @property
    def trajectory_figure(self) -> Path:
        return self.out / "trajectory.png"

    @property
    def trajectory_file(self) -> Path:
        return self.out / "trajectory.json"

    def trajectory_frames(self, env: str) -> Path:
        return self.out / f"trajectory_{env}.txt"

    @property
    def analysis_dir(self) -> Path:
        return self.out / "analysis"

    @property
    def analysis_file(self) -> Path:
        return self.analysis_dir / ANALYSIS_FILE

    @property
    def analysis_figures(self) -> Path:
        return self.analysis_dir / "figures"

    @property
    def defense_dir(self) -> Path:
        return self.out / "defense"

    @property
    def defense_file(self) -> Path:
        return self.defense_dir / DEFENSE_FILE

    @property
    def tradeoff_dir(self) -> Path:
        return self.out / "tradeoff"

    @property
    def tradeoff_file(self) -> Path:
        return self.tradeoff_dir / TRADEOFF_FILE

    @property
    def zoo_dir(self) -> Path:
        return self.out / "zoo"

    @property
    def cells_dir(self) -> Path:
        return self.out / "cells"

    @property
    def cells_file(self) -> Path:
        return self.cells_dir / CELLS_FILE

    @property
    def cells_figure(self) -> Path:
        return self.cells_dir / "cells.png"

    @property
    def detection_file(self) -> Path:
        return self.zoo_dir / DETECTION_FILE

    @property
    def leaderboard_file(self) -> Path:
        """The benchmark leaderboard of the zoo, where ``seqtrojan zoo detect --zoo OUT/zoo --out OUT/zoo/leaderboard``
        writes it (the reproduction does not run it; its report shows it when it is there)."""
        return self.zoo_dir / "leaderboard" / LEADERBOARD_FILE

    # --- each stage's results, typed (None, or empty, when the stage has not run)
    def evaluation(self) -> list[SweepRow]:
        return load_sweep(self.evaluation_file) if self.evaluation_file.exists() else []

    def analysis(self) -> AnalysisResult | None:
        return _load(AnalysisResult, self.analysis_file)

    def defense(self) -> DefenseResult | None:
        return _load(DefenseResult, self.defense_file)

    def detection(self) -> DetectionResult | None:
        return _load(DetectionResult, self.detection_file)

    def leaderboard(self) -> Leaderboard | None:
        return _load(Leaderboard, self.leaderboard_file)

    def trajectory(self) -> TrajectoryResult | None:
        return _load(TrajectoryResult, self.trajectory_file)

    def curves(self) -> CurvesResult | None:
        return _load(CurvesResult, self.curves_file)

    def tradeoff(self) -> TradeoffResult | None:
        return _load(TradeoffResult, self.tradeoff_file)

    def cells(self) -> CellsResult | None:
        return _load(CellsResult, self.cells_file)

    def stage_seconds(self) -> dict[str, float]:
        """Wall seconds per stage (``timings.json``)."""
        return _json(self.timings) or {}

    def headline_runs(self) -> dict[str, RunSummary | None]:
        """Every headline agent's run (clean, backdoor, then <role>_seed<k> in seed order) with its summary (None
        while it has no model card or metrics)."""
        names = list(HEADLINE_ROLES)
        if self.runs.is_dir():
            extra = [p.name for p in self.runs.iterdir() if re.fullmatch(r"(clean|backdoor)_seed\d+", p.name)]
            names += sorted(extra, key=lambda n: (int(n.rsplit("seed", 1)[1]), n))
        return {name: self.run_summary(name) for name in names}

    def run_summary(self, name: str) -> RunSummary | None:
        run_dir = self.run(name)
        metrics = run_dir / "metrics.jsonl"
        card = _json(run_dir / "model" / "card.json")
        if card is None or not metrics.exists():
            return None
        rows = [json.loads(line) for line in metrics.read_text().splitlines() if line]
        evaluation = card.get("metrics", {})
        seconds = evaluation.get("train_seconds") or (rows[-1]["time/elapsed_s"] if rows else 0.0)
        env_steps = card.get("env_steps") or 0
        return RunSummary(
            grid=evaluation.get("grid", "?"),
            env_steps=env_steps,
            minutes=seconds / 60,
            sps=env_steps / seconds if seconds else 0.0,
            stage=evaluation.get("stage", rows[-1]["curriculum/stage"] if rows else 0),
        )


def _load(cls: type[T], path: Path) -> T | None:
    return load_json(cls, path) if path.exists() else None


def _json(path: Path) -> Any:
    return json.loads(path.read_text()) if path.exists() else None
