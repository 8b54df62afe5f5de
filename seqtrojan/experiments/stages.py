"""Stages of a pipeline and the one runner that runs them.

A :class:`Stage` has a name, knows from its outputs whether it is done (``done(layout)``), and writes those outputs
(``run(context)``). :func:`run_stages` runs a list of stages in order: a stage whose outputs exist is skipped (so a
stopped pipeline continues where it stopped), every stage that runs has its wall seconds recorded under its name in
``timings.json`` (:class:`Timings`), and each start and skip is logged.

    run_stages([TrainingQueue(config), EvaluationStage(config), ...], context)

:mod:`seqtrojan.experiments.reproduce` is the reproduction as such a list.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

from seqtrojan.artifacts import RunLayout
from seqtrojan.timings import Timings

Log = Callable[[str], None]


@dataclass(frozen=True)
class StageContext:
    """What every stage runs with: where its outputs go, how it logs, where it records finer timings."""

    layout: RunLayout
    log: Log
    timings: Timings


C = TypeVar("C", bound=StageContext, contravariant=True)
C2 = TypeVar("C2", bound=StageContext)


class Stage(Protocol[C]):
    """One step of a pipeline, done when its outputs exist."""

    @property
    def name(self) -> str:
        """Its key in timings.json and its name in the log."""
        ...

    def done(self, layout: RunLayout) -> bool:
        """Whether its outputs exist (cheap: reads no results)."""
        ...

    def run(self, context: C) -> None:
        """Write its outputs under ``context.layout``."""
        ...


def run_stages(stages: Sequence[Stage[C2]], context: C2) -> list[str]:
    """Run every stage not done, in order, recording each one's wall seconds under its name; return the names of
    the stages that ran."""
    ran = []
    for stage in stages:
        if stage.done(context.layout):
            context.log(f"{stage.name}: done (outputs exist), skipped")
            continue
        t0 = time.perf_counter()
        stage.run(context)
        context.timings.record(stage.name, time.perf_counter() - t0)
        ran.append(stage.name)
    return ran
