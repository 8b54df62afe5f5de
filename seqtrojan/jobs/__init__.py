"""One job backend for every stage that trains many agents (learning curves, the adversary's trade-off, the zoo).

A job is a pure, picklable :class:`TrainJob` (an id and the config of one run); :func:`run_job` makes it finished
(reuse, resume from its checkpoint, or restart) and returns a :class:`JobResult`. A :class:`JobBackend` runs many:
``serial``, a local process ``pool`` (the default) or ``ray`` (a local instance or a cluster), chosen by a
:class:`JobsConfig` through :func:`make_backend`.
"""

from seqtrojan.jobs.backends import (
    BACKENDS,
    JobBackend,
    JobsConfig,
    PoolBackend,
    RayBackend,
    SerialBackend,
    available_cpus,
    make_backend,
    worker_plan,
)
from seqtrojan.jobs.job import JobResult, JobsFailed, TrainJob, describe_error, raise_failures, run_job

__all__ = [
    "BACKENDS",
    "JobBackend",
    "JobResult",
    "JobsConfig",
    "JobsFailed",
    "PoolBackend",
    "RayBackend",
    "SerialBackend",
    "TrainJob",
    "available_cpus",
    "describe_error",
    "make_backend",
    "raise_failures",
    "run_job",
    "worker_plan",
]
