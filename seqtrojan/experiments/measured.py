"""What the studies that train many agents and then measure each one share (the matrix, the sequence-model
comparison): train what is not trained yet on a job backend, and measure each agent once, its measurement saved
atomically so that a stopped study resumes where it stopped."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from seqtrojan.errors import ConfigError
from seqtrojan.jobs import JobBackend, JobResult, TrainJob, raise_failures
from seqtrojan.serde import load_json, save_json

T = TypeVar("T")
Log = Callable[[str], None]


def train_all(backend: JobBackend, jobs: Sequence[TrainJob], what: str, log: Log) -> None:
    """Train the jobs not done yet (finished ones are kept), logging each; raise if any failed."""

    def on_result(r: JobResult) -> None:
        if not r.ok:
            log(f"  {r.id} failed: {r.error}")
        elif r.trained:
            log(f"  {r.id} trained in {r.seconds:.0f} s")

    todo = sum(not job.done() for job in jobs)
    if todo:
        log(f"training {todo} {what}(s) on the {backend.name} backend ({backend.describe(todo)}) ...")
    raise_failures(backend.run(list(jobs), on_result), what)


def measured_once(path: Path, kind: type[T], measure: Callable[[], T], what: str, log: Log) -> T:
    """The measurement saved at ``path`` by an earlier call, else ``measure()`` saved there atomically (a stop
    mid-write leaves no half-written file; one that does not load is measured again)."""
    if path.exists():
        try:
            return load_json(kind, path)
        except ConfigError as err:
            log(f"  measuring again: {err}")
    log(f"measuring {what} ...")
    value = measure()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_json(value, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)
    return value
