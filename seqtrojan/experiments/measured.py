"""What the studies that train many agents and then measure each one share (the matrix, the sequence-model
comparison): train what is not trained yet on a job backend, then measure every agent not measured yet on the same
backend, each measurement saved atomically so that a stopped study resumes where it stopped."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from seqtrojan.errors import ConfigError
from seqtrojan.jobs import JobBackend, JobResult, TrainJob, raise_failures
from seqtrojan.serde import load_json, save_json

T = TypeVar("T")
Log = Callable[[str], None]


def train_all(backend: JobBackend, jobs: Sequence[TrainJob], what: str, log: Log) -> None:
    """Train the jobs not done yet (finished ones are kept), logging each; raise if any failed."""
    todo = sum(not job.done() for job in jobs)
    if todo:
        log(f"training {todo} {what}(s) on the {backend.name} backend ({backend.describe(todo)}) ...")
    raise_failures(backend.run(list(jobs), _logger(log, "trained")), what)


@dataclass(frozen=True)
class MeasureJob(TrainJob):
    """Measuring one trained agent (its training job's id and config) into ``path``, as a job for the backends:
    ``measure`` is a picklable callable (a module-level function with its arguments bound, e.g. by
    :func:`functools.partial`) returning a result of type ``kind``."""

    path: str = ""
    kind: type | None = None
    measure: Callable[[], Any] | None = None

    def done(self) -> bool:
        return _saved(Path(self.path), self.kind) is not None

    def run(self) -> tuple[Path, bool]:
        assert self.measure is not None
        path = Path(self.path)
        value = self.measure()
        path.parent.mkdir(parents=True, exist_ok=True)
        save_json(value, path.with_suffix(".tmp"))
        path.with_suffix(".tmp").replace(path)  # a stop mid-write leaves no half-written measurement
        return path, True


def measure_all(
    backend: JobBackend,
    trained: Sequence[TrainJob],
    paths: Sequence[Path],
    kind: type[T],
    measures: Sequence[Callable[[], T]],
    log: Log,
) -> list[T]:
    """Each trained agent's measurement: the one saved by an earlier call, else ``measures[i]()`` run as a job on
    ``backend`` and saved at ``paths[i]``. A saved file that does not load (cut short by a kill) is measured again."""
    for path in paths:
        if path.exists() and _saved(path, kind) is None:
            log(f"  measuring {path.stem} again: its saved measurement does not load")
    jobs = [
        MeasureJob(job.id, job.config, str(path), kind, measure) for job, path, measure in zip(trained, paths, measures)
    ]
    todo = sum(not job.done() for job in jobs)
    if todo:
        log(f"measuring {todo} agent(s) on the {backend.name} backend ({backend.describe(todo)}) ...")
    raise_failures(backend.run(jobs, _logger(log, "measured")), "measurement")
    return [load_json(kind, path) for path in paths]


def _saved(path: Path, kind: type | None) -> Any:
    if kind is None or not path.exists():
        return None
    try:
        return load_json(kind, path)
    except ConfigError:
        return None


def _logger(log: Log, verb: str) -> Callable[[JobResult], None]:
    def on_result(r: JobResult) -> None:
        if not r.ok:
            log(f"  {r.id} failed: {r.error}")
        elif r.trained:
            log(f"  {r.id} {verb} in {r.seconds:.0f} s")

    return on_result
