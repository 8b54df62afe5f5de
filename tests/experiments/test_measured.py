"""Measuring every trained agent as a job on the backend: in parallel on the pool, kept, re-measured when cut short."""

from __future__ import annotations

from functools import partial

from seqtrojan.config import ExperimentConfig, RunConfig
from seqtrojan.experiment_results import SweepPoint
from seqtrojan.experiments.measured import measure_all
from seqtrojan.jobs import JobsConfig, TrainJob, make_backend
from seqtrojan.stats import Rate


def test_measurements_run_on_the_pool_are_kept_and_one_cut_short_is_measured_again(tmp_path):
    jobs = [TrainJob(f"a{i}", ExperimentConfig(run=RunConfig(out_dir=str(tmp_path), name=f"a{i}"))) for i in range(3)]
    paths = [tmp_path / "measured" / f"a{i}.json" for i in range(3)]
    measures = [partial(SweepPoint, "7x7/3", Rate(i, 10)) for i in range(3)]  # picklable: the pool's workers run them
    backend = make_backend(JobsConfig(backend="pool", workers=2, threads=1))
    logs: list[str] = []
    got = measure_all(backend, jobs, paths, SweepPoint, measures, logs.append)
    assert [p.activation for p in got] == [Rate(0, 10), Rate(1, 10), Rate(2, 10)]
    assert sum("measured in" in line for line in logs) == 3 and all(p.exists() for p in paths)
    paths[1].write_text(paths[1].read_text()[:5])  # cut short, as by a kill mid-write
    logs.clear()
    assert measure_all(backend, jobs, paths, SweepPoint, measures, logs.append)[1].activation == Rate(1, 10)
    assert "a1 again" in logs[0] and sum("measured in" in line for line in logs) == 1
