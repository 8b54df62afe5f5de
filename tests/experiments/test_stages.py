"""The stage runner: a stage whose outputs exist is skipped, every stage that runs is timed under its name, and the
reproduction's list holds only the stages its config has."""

from __future__ import annotations

import json
from dataclasses import dataclass

from seqtrojan.artifacts import RunLayout
from seqtrojan.experiments.reproduce import ReproduceConfig, reproduce_stages
from seqtrojan.experiments.stages import StageContext, run_stages
from seqtrojan.serde import from_dict
from seqtrojan.timings import Timings


@dataclass(frozen=True)
class FileStage:
    """Writes ``<out>/<name>.txt`` (with what the earlier stage wrote, to show the order) and a finer timing."""

    name: str

    def done(self, layout: RunLayout) -> bool:
        return (layout.out / f"{self.name}.txt").exists()

    def run(self, context: StageContext) -> None:
        earlier = sorted(p.stem for p in context.layout.out.glob("*.txt"))
        (context.layout.out / f"{self.name}.txt").write_text(",".join(earlier))
        context.timings.record(f"{self.name}_step", 0.5)


def _context(tmp_path, messages: list[str]) -> StageContext:
    layout = RunLayout(tmp_path)
    return StageContext(layout, messages.append, Timings(layout.timings))


def test_runner_skips_done_stages_and_times_the_others_under_their_names(tmp_path):
    (tmp_path / "b.txt").write_text("made before")
    messages: list[str] = []
    ran = run_stages([FileStage("a"), FileStage("b"), FileStage("c")], _context(tmp_path, messages))
    assert ran == ["a", "c"]
    assert (tmp_path / "b.txt").read_text() == "made before"  # not run again
    assert (tmp_path / "c.txt").read_text() == "a,b"  # in order, after a
    assert messages == ["b: done (outputs exist), skipped"]
    timings = json.loads((tmp_path / "timings.json").read_text())
    assert list(timings) == ["a_step", "a", "c_step", "c"]  # a stage's own records come before its total
    assert all(seconds >= 0 for seconds in timings.values())


def test_a_second_run_skips_everything_and_keeps_the_timings(tmp_path):
    run_stages([FileStage("a")], _context(tmp_path, []))
    before = json.loads((tmp_path / "timings.json").read_text())
    messages: list[str] = []
    assert run_stages([FileStage("a"), FileStage("d")], _context(tmp_path, messages)) == ["d"]
    after = json.loads((tmp_path / "timings.json").read_text())
    assert after["a"] == before["a"] and set(after) == {"a_step", "a", "d_step", "d"}
    assert messages == ["a: done (outputs exist), skipped"]


def test_the_reproduction_lists_only_the_stages_its_config_has():
    full: dict[str, dict] = {"tradeoff": {}, "zoo": {}, "cells": {}}
    names = [s.name for s in reproduce_stages(from_dict(ReproduceConfig, full))]
    assert names == [
        "training", "evaluation", "curves", "trajectory", "analysis", "defense", "tradeoff", "zoo", "cells", "report",
    ]  # fmt: skip
    headline_only = {"curves": None, "trajectory": None, "analysis": None, "defense": None}
    names = [s.name for s in reproduce_stages(from_dict(ReproduceConfig, headline_only))]
    assert names == ["training", "evaluation", "report"]
    stages = reproduce_stages(from_dict(ReproduceConfig, {"defense": None}))
    assert [s.name for s in stages] == ["training", "evaluation", "curves", "trajectory", "analysis", "report"]
