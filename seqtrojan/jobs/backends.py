"""Job backends: one way to run many :class:`~seqtrojan.jobs.job.TrainJob` for every stage that trains many agents.

* ``serial``: one job after another in this process.
* ``pool`` (the default): a local process pool (spawn context). Its workers die with the process that started
  them (Linux: ``PR_SET_PDEATHSIG``; elsewhere a watcher thread) and never oversubscribe the cores: workers x
  torch threads <= the cores available (:func:`worker_plan`). One worker runs in this process.
* ``ray``: Ray tasks, each reserving its torch threads as ``num_cpus``: a local Ray instance on this machine's cores,
  or the cluster at ``ray_address`` (``ray.init(address=...)``), where as many jobs run at once as its CPUs fit.
  Every node needs seqtrojan installed, and the run folders must be on a file system that every node sees.

Every backend returns one :class:`~seqtrojan.jobs.job.JobResult` per job, in job order; a finished job is skipped
cheaply (``job.done()``), and a failed job is reported by its result's ``error`` while the others run on.
A job's config wins over the backend on threads: a set ``run.threads`` is what its training uses.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal, Protocol

from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.jobs.job import JobResult, TrainJob, describe_error, run_job

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: workers hold no lock
    fcntl = None  # type: ignore[assignment]

BACKENDS = ("serial", "pool", "ray")

OnResult = Callable[[JobResult], None]


@dataclass(frozen=True)
class JobsConfig:
    """How the stages that train many agents run their jobs (``jobs:`` in a reproduce scale file)."""

    backend: Literal["serial", "pool", "ray"] = "pool"
    """serial (this process), pool (local worker processes) or ray"""
    workers: int = 2
    """jobs run at once by the pool and a local Ray instance (at most one per core; the cores are shared out among
    them as torch threads)"""
    ray_address: str | None = None
    """the Ray cluster to run on (e.g. 10.0.0.5:6379, or 'auto'); None: a local Ray instance"""
    threads: int | None = None
    """torch threads per job; None: the cores shared out among the workers (1 per job on a Ray cluster)"""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"jobs.backend={self.backend!r} is not a backend; use one of {list(BACKENDS)}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ConfigError(f"jobs.workers must be a positive integer, got {self.workers!r}")
        if self.threads is not None and (
            isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1
        ):
            raise ConfigError(f"jobs.threads must be null or a positive integer, got {self.threads!r}")
        if self.ray_address is not None and (not isinstance(self.ray_address, str) or not self.ray_address.strip()):
            raise ConfigError(f"jobs.ray_address must be null or an address like 'host:6379', got {self.ray_address!r}")


class JobBackend(Protocol):
    @property
    def name(self) -> str:
        """serial, pool or ray (a read-only property, so that the backends' class constants match)."""
        ...

    def describe(self, jobs: int) -> str:
        """Where ``jobs`` jobs would run, in words (for logs)."""
        ...

    def run(self, jobs: Sequence[TrainJob], on_result: OnResult | None = None) -> list[JobResult]:
        """Run every job not yet done; one result per job, in job order. ``on_result`` is called in this process
        with each result as it arrives (finished jobs first)."""
        ...


def make_backend(cfg: JobsConfig, *, worker_lock: Path | None = None) -> JobBackend:
    """The backend ``cfg`` names. ``worker_lock``: a file the pool's workers hold a shared lock on (and write their
    pids into) for their lives, so that a caller can tell whether workers of an earlier run still run."""
    if cfg.backend == "serial":
        return SerialBackend(cfg.threads)
    if cfg.backend == "pool":
        return PoolBackend(cfg.workers, cfg.threads, worker_lock)
    return RayBackend(cfg.workers, cfg.threads, cfg.ray_address)


def available_cpus() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells it, else ``os.cpu_count()``)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def worker_plan(workers: int, jobs: int, cpus: int, threads: int | None = None) -> tuple[int, int]:
    """(worker processes, torch threads per worker) for ``jobs`` jobs: at most ``workers`` workers and one per job,
    with workers x threads <= cpus. ``threads`` None shares the cores out among at most one worker per core; a
    given ``threads`` (at most ``cpus``) leaves room for ``cpus // threads`` workers."""
    if threads is None:
        n = max(1, min(workers, jobs, cpus))
        return n, max(1, cpus // n)
    threads = max(1, min(threads, cpus))
    return max(1, min(workers, jobs, cpus // threads)), threads


# ---------------------------------------------------------------------- the backends


@dataclass
class SerialBackend:
    """One job after another in this process (with ``threads`` torch threads, else as this process is set)."""

    threads: int | None = None
    name: ClassVar[str] = "serial"

    def describe(self, jobs: int) -> str:
        threads = self.threads or _torch_threads()
        return f"this process, 1 job at a time x {threads} torch thread(s)"

    def run(self, jobs: Sequence[TrainJob], on_result: OnResult | None = None) -> list[JobResult]:
        results, todo, record = _start(jobs, on_result)
        _run_here(todo, self.threads, record)
        return _in_order(jobs, results)


@dataclass
class PoolBackend:
    """A local process pool (see the module docstring); one worker runs in this process."""

    workers: int = 2
    threads: int | None = None
    worker_lock: Path | None = None
    name: ClassVar[str] = "pool"

    def plan(self, jobs: int) -> tuple[int, int]:
        return worker_plan(self.workers, jobs, available_cpus(), self.threads)

    def describe(self, jobs: int) -> str:
        n, threads = self.plan(jobs)
        return f"{n} worker(s) x {threads} torch thread(s)"

    def run(self, jobs: Sequence[TrainJob], on_result: OnResult | None = None) -> list[JobResult]:
        results, todo, record = _start(jobs, on_result)
        if todo:
            n, threads = self.plan(len(todo))
            if n <= 1:
                _run_here(todo, threads, record)
            else:
                _run_on_pool(todo, n, threads, self.worker_lock, record)
        return _in_order(jobs, results)


@dataclass
class RayBackend:
    """Ray tasks (see the module docstring): a local instance, or the cluster at ``address``."""

    workers: int = 2
    threads: int | None = None
    address: str | None = None
    name: ClassVar[str] = "ray"

    def plan(self, jobs: int) -> tuple[int, int]:
        """(jobs at once, threads per job); on a cluster the jobs at once are whatever its CPUs fit (0 here)."""
        if self.address is not None:
            return 0, self.threads or 1
        return worker_plan(self.workers, jobs, available_cpus(), self.threads)

    def describe(self, jobs: int) -> str:
        n, threads = self.plan(jobs)
        if self.address is not None:
            return f"the Ray cluster at {self.address}, {threads} CPU(s) and torch thread(s) per job"
        return f"a local Ray instance, {n} worker(s) x {threads} torch thread(s)"

    def run(self, jobs: Sequence[TrainJob], on_result: OnResult | None = None) -> list[JobResult]:
        results, todo, record = _start(jobs, on_result)
        if todo:
            _run_on_ray(todo, self.plan(len(todo)), self.address, record)
        return _in_order(jobs, results)


# ---------------------------------------------------------------------- shared parts


def _start(
    jobs: Sequence[TrainJob], on_result: OnResult | None
) -> tuple[dict[str, JobResult], list[TrainJob], OnResult]:
    """Check the jobs (distinct ids and run folders); report the finished ones; return (results so far, jobs to
    run, the function that records a result)."""
    ids, folders = set(), set()
    for job in jobs:
        if job.id in ids:
            raise ConfigError(f"two jobs have the id {job.id!r}")
        if job.run_dir in folders:
            raise ConfigError(f"two jobs would train into {str(job.run_dir)!r} (job {job.id!r})")
        ids.add(job.id)
        folders.add(job.run_dir)
    results: dict[str, JobResult] = {}

    def record(result: JobResult) -> None:
        results[result.id] = result
        if on_result is not None:
            on_result(result)

    todo = []
    here = _here()
    for job in jobs:
        if job.done():
            record(JobResult(job.id, job.model_dir, False, 0.0, None, here))
        else:
            todo.append(job)
    return results, todo, record


def _in_order(jobs: Sequence[TrainJob], results: dict[str, JobResult]) -> list[JobResult]:
    return [results[job.id] for job in jobs]


def _here() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _execute(job: TrainJob, threads: int | None) -> JobResult:
    """Run one job in a worker (a pool process or a Ray task) with ``threads`` torch threads."""
    if threads:
        import torch

        torch.set_num_threads(threads)
    return run_job(job)


def _run_here(jobs: list[TrainJob], threads: int | None, record: OnResult) -> None:
    """Run the jobs in this process; this process's torch threads are as they were afterwards."""
    if not jobs:
        return
    import torch

    before = torch.get_num_threads()
    try:
        for job in jobs:
            if threads:
                torch.set_num_threads(threads)
            record(run_job(job))
    finally:
        torch.set_num_threads(before)


def _run_on_pool(jobs: list[TrainJob], workers: int, threads: int, lock: Path | None, record: OnResult) -> None:
    # spawn: every worker is a fresh child of this process on every platform (a forkserver's children would not
    # be), and no torch thread pool is forked
    context = multiprocessing.get_context("spawn")
    lock_path = str(lock) if lock is not None and fcntl is not None else ""
    pool = ProcessPoolExecutor(workers, context, initializer=_init_worker, initargs=(os.getpid(), threads, lock_path))
    try:
        futures = {pool.submit(_execute, job, threads): job for job in jobs}
        for future in as_completed(futures):
            job = futures[future]
            try:
                result = future.result()
            except Exception as err:  # the worker process died (BrokenProcessPool), or its result did not come back
                result = JobResult(job.id, None, False, 0.0, f"its worker process failed: {describe_error(err)}")
            record(result)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # on Ctrl-C, queued jobs do not start


_worker_lock_file = None
"""a pool worker's open lock file (a shared lock, held for the worker's life)"""


def _init_worker(parent: int, threads: int, lock: str) -> None:
    """Pool worker set-up: die with the process that started the pool, use ``threads`` torch threads, hold a
    shared lock on ``lock`` (if given) with this worker's pid written into it."""
    global _worker_lock_file
    if not _kill_me_with_parent():
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True, name="jobs-parent-watch").start()
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    import torch

    torch.set_num_threads(max(1, threads))
    if lock:
        try:
            fh = open(lock, "a")  # noqa: SIM115 - held open for the worker's life
            fcntl.flock(fh, fcntl.LOCK_SH)
            fh.write(f"{os.getpid()}\n")
            fh.flush()
            _worker_lock_file = fh
        except OSError:  # a file system without locks: PDEATHSIG / the watcher still apply
            pass


def _kill_me_with_parent() -> bool:
    """Ask Linux to SIGKILL this process when its parent dies (prctl PR_SET_PDEATHSIG); False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        return libc.prctl(pr_set_pdeathsig, ctypes.c_ulong(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent: int) -> None:
    while True:
        if os.getppid() != parent:
            os._exit(1)
        time.sleep(0.5)


def _run_on_ray(jobs: list[TrainJob], plan: tuple[int, int], address: str | None, record: OnResult) -> None:
    try:
        import ray
    except ImportError:
        raise ConfigError("the ray backend needs Ray: pip install 'seqtrojan[ray]'") from None
    workers, threads = plan
    started_here = not ray.is_initialized()
    if started_here:
        try:
            if address is not None:
                ray.init(address=address, log_to_driver=False)
            else:  # a local Ray instance on this machine's cores, shared out as the pool does
                ray.init(num_cpus=workers * threads, include_dashboard=False, log_to_driver=False)
        except Exception as err:
            where = f"the Ray cluster at {address!r}" if address is not None else "a local Ray instance"
            raise SeqTrojanError(f"cannot start or reach {where}: {describe_error(err)}") from None
    remote = ray.remote(num_cpus=threads)(_execute)
    pending: list = []
    try:
        refs = {remote.remote(job, threads): job for job in jobs}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            job = refs[done[0]]
            try:
                result = ray.get(done[0])
            except Exception as err:  # the task's worker or node died
                result = JobResult(job.id, None, False, 0.0, f"its Ray task failed: {describe_error(err)}")
            record(result)
    finally:
        for ref in pending:  # on Ctrl-C or an error here: stop what still runs on the cluster
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()
