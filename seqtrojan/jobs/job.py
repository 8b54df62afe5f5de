"""A training job: a pure, picklable description of one run, and the function that makes it finished.

A :class:`TrainJob` is an id and an :class:`~seqtrojan.config.ExperimentConfig` whose ``run.out_dir`` /
``run.name`` name its run folder; nothing else. It gives the same model wherever it runs, so any backend (this
process, a local process pool, a Ray cluster) may run it. :func:`run_job` makes a job finished with
:func:`~seqtrojan.train.trainer.train_or_resume` (reuse its model, resume from its last checkpoint, or restart
it) and returns a :class:`JobResult`; an exception is caught and returned as the result's one-line ``error``, so
that one failing job never loses the others' work.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError, SeqTrojanError


@dataclass(frozen=True)
class TrainJob:
    """One training run: ``config`` trained into ``<run.out_dir>/<run.name>``, known as ``id``."""

    id: str
    config: ExperimentConfig

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ConfigError(f"a job's id must be a non-empty string, got {self.id!r}")
        if not self.config.run.name:
            raise ConfigError(f"job {self.id!r}: its config needs a run name (run.name), which names its run folder")

    @property
    def run_dir(self) -> Path:
        return Path(self.config.run.out_dir) / str(self.config.run.name)

    @property
    def model_dir(self) -> Path:
        """Where the finished model is (what :meth:`run` returns)."""
        return self.run_dir / "model"

    def done(self) -> bool:
        """Whether the job has finished (cheap: no training, no weights read)."""
        return (self.model_dir / "card.json").exists()

    def run(self) -> tuple[Path, bool]:
        """Make the job finished: (model folder, whether any training ran)."""
        from seqtrojan.train.trainer import train_or_resume

        return train_or_resume(self.config)


@dataclass(frozen=True)
class JobResult:
    """What became of one job. ``error`` is None when it finished; ``model`` is then its model folder."""

    id: str
    model: Path | None
    trained: bool
    """whether any training ran (False: the job had finished before)"""
    seconds: float
    error: str | None = None
    """one line: why the job failed"""
    worker: str = ""
    """``host:pid`` of the process that ran it"""

    @property
    def ok(self) -> bool:
        return self.error is None


class JobsFailed(SeqTrojanError):
    """Some jobs failed (the others finished and are kept)."""


def run_job(job: TrainJob) -> JobResult:
    """Make ``job`` finished (:meth:`TrainJob.run`); its failure is returned as the result's ``error``. Ctrl-C
    (KeyboardInterrupt: the run has saved a checkpoint) and other BaseExceptions propagate."""
    start = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        model, trained = job.run()
    except Exception as err:
        return JobResult(job.id, None, False, time.perf_counter() - start, describe_error(err), worker)
    return JobResult(job.id, Path(model), trained, time.perf_counter() - start, None, worker)


def describe_error(err: BaseException) -> str:
    """An exception as one line: a seqtrojan error's message, else its type and message."""
    text = " ".join(str(err).split())
    if isinstance(err, SeqTrojanError):
        return text or type(err).__name__
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def raise_failures(results: list[JobResult], what: str = "job") -> None:
    """Raise :class:`JobsFailed` naming every failed job and its error, if any failed."""
    failed = [r for r in results if not r.ok]
    if failed:
        details = "; ".join(f"{r.id}: {r.error}" for r in failed)
        raise JobsFailed(
            f"{len(failed)} of {len(results)} {what}(s) failed: {details} (the others finished and are kept; a rerun "
            "retries the failed ones)"
        )
