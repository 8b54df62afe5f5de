"""The job backends: serial, pool and Ray give the same models (bitwise, one torch thread each); finished jobs are
not trained again; a failing job is reported with its id while the others finish; workers never oversubscribe the
cores; the CLI and the reproduce config choose the backend; a two-node Ray cluster runs a zoo's jobs."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from seqtrojan import cli
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.env import GridSpec
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.reproduce import ReproduceConfig
from seqtrojan.jobs import (
    JobsConfig,
    JobsFailed,
    PoolBackend,
    SerialBackend,
    TrainJob,
    make_backend,
    raise_failures,
    worker_plan,
)
from seqtrojan.serde import from_dict
from seqtrojan.zoo.build import ZooConfig, build_zoo, make_jobs

ROOT = Path(__file__).resolve().parents[2]


def tiny(out: Path, name: str, seed: int, backdoor: bool = False, device: str = "cpu") -> TrainJob:
    """A job of two PPO updates on 5x5 with no holes (checkpoints after the first and at the end)."""
    config = ExperimentConfig(
        env=EnvConfig(size=5, holes=0),
        agent=AgentConfig(lstm_sizes=(8,)),
        ppo=PPOConfig(total_steps=2048, num_envs=32, rollout_steps=32),
        backdoor=BackdoorConfig(enabled=backdoor),
        run=RunConfig(out_dir=str(out), name=name, seed=seed, device=device, progress=False, eval_episodes=8,
                      checkpoint_every=1024),
    )  # fmt: skip
    return TrainJob(name, config)


def tiny_jobs(out: Path) -> list[TrainJob]:
    return [tiny(out, "clean_s0", 0), tiny(out, "clean_s1", 1), tiny(out, "backdoor_s0", 0, backdoor=True)]


def weights(model: Path) -> dict[str, torch.Tensor]:
    return load_file(str(model / "model.safetensors"))


def assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = weights(a), weights(b)
    assert wa.keys() == wb.keys()
    for key in wa:
        assert torch.equal(wa[key], wb[key]), key


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory) -> tuple[Path, list]:
    """The tiny jobs trained once in this process, one torch thread: the reference the other backends must match."""
    out = tmp_path_factory.mktemp("serial")
    results = SerialBackend(threads=1).run(tiny_jobs(out))
    return out, results


def test_serial_trains_every_job_in_order_and_leaves_the_threads_as_they_were(serial_run):
    out, results = serial_run
    assert [r.id for r in results] == ["clean_s0", "clean_s1", "backdoor_s0"]
    assert all(r.ok and r.trained for r in results)
    assert all(r.worker.endswith(f":{os.getpid()}") for r in results)  # in this process
    for r, job in zip(results, tiny_jobs(out)):
        assert r.model == job.model_dir and (r.model / "card.json").exists()
    assert torch.get_num_threads() == 1  # as conftest set it
    assert not torch.equal(*(weights(out / n / "model")["cells.0.weight_ih"] for n in ("clean_s0", "clean_s1")))


def test_pool_gives_bitwise_the_serial_models_and_a_rerun_trains_nothing(serial_run, tmp_path):
    reference, _ = serial_run
    jobs = tiny_jobs(tmp_path)
    arrived = []
    results = PoolBackend(workers=2, threads=1).run(jobs, arrived.append)
    assert [r.id for r in results] == [j.id for j in jobs]  # job order, whatever the order they finished in
    assert sorted(r.id for r in arrived) == sorted(j.id for j in jobs)
    assert all(r.ok and r.trained for r in results)
    assert all(int(r.worker.rsplit(":", 1)[1]) != os.getpid() for r in results)  # in worker processes
    for job in jobs:
        assert_same_weights(job.model_dir, reference / job.id / "model")
    stamps = {j.id: (j.model_dir / "model.safetensors").stat().st_mtime_ns for j in jobs}

    again = PoolBackend(workers=2, threads=1).run(jobs)
    assert [(r.id, r.ok, r.trained, r.model) for r in again] == [(j.id, True, False, j.model_dir) for j in jobs]
    assert all(r.worker.endswith(f":{os.getpid()}") for r in again)  # skipped here, no worker started
    assert stamps == {j.id: (j.model_dir / "model.safetensors").stat().st_mtime_ns for j in jobs}

    # a job stopped after its last checkpoint (its model folder gone) resumes from it, to the same model
    shutil.rmtree(jobs[2].model_dir)
    resumed = SerialBackend(threads=1).run(jobs)
    assert [r.trained for r in resumed] == [False, False, True]
    assert_same_weights(jobs[2].model_dir, reference / jobs[2].id / "model")


def test_a_failing_job_is_reported_with_its_id_while_the_others_finish(tmp_path):
    jobs = [tiny(tmp_path, "good_s0", 0), tiny(tmp_path, "broken", 0, device="cuda:99"), tiny(tmp_path, "good_s1", 1)]
    results = PoolBackend(workers=2, threads=1).run(jobs)
    assert [r.id for r in results] == ["good_s0", "broken", "good_s1"]
    good, broken, other = results
    assert good.ok and other.ok and (good.model / "card.json").exists() and (other.model / "card.json").exists()
    assert not broken.ok and broken.model is None and "run.device='cuda:99'" in broken.error
    assert "\n" not in broken.error
    with pytest.raises(JobsFailed, match=r"^1 of 3 job\(s\) failed: broken: run\.device='cuda:99'") as err:
        raise_failures(results)
    assert "\n" not in str(err.value)
    raise_failures([good, other])  # nothing failed: nothing raised


def test_jobs_are_checked_before_anything_runs(tmp_path):
    job = tiny(tmp_path, "a", 0)
    with pytest.raises(ConfigError, match="two jobs have the id 'a'"):
        SerialBackend().run([job, job])
    twin = TrainJob("b", job.config)
    with pytest.raises(ConfigError, match=r"two jobs would train into '.*/a' \(job 'b'\)"):
        PoolBackend().run([job, twin])
    assert not (tmp_path / "a").exists()
    with pytest.raises(ConfigError, match="needs a run name"):
        TrainJob("c", ExperimentConfig())
    bad_configs = [
        ({"backend": "slurm"}, "not a backend"),
        ({"workers": 0}, r"jobs\.workers must be"),
        ({"threads": 0}, r"jobs\.threads must be"),
        ({"ray_address": " "}, r"jobs\.ray_address"),
    ]
    for bad, message in bad_configs:
        with pytest.raises(ConfigError, match=message):
            JobsConfig(**bad)


def test_worker_plan_never_oversubscribes_the_cores():
    for cpus in range(1, 9):
        for workers in range(1, 10):
            for jobs in (1, 3, 40):
                for threads in (None, 1, 2, 3, 16):
                    n, t = worker_plan(workers, jobs, cpus, threads)
                    assert 1 <= n <= min(workers, jobs) and t >= 1 and n * t <= cpus, (cpus, workers, jobs, threads)
                    if threads is not None:
                        assert t == min(threads, cpus)
    assert worker_plan(4, 40, 2) == (2, 1)
    assert worker_plan(1, 40, 8) == (1, 8)
    assert worker_plan(2, 40, 16) == (2, 8)
    assert worker_plan(8, 40, 8, threads=3) == (2, 3)


def test_the_cli_and_the_reproduce_config_choose_the_backend(tmp_path, monkeypatch):
    from seqtrojan.experiments import reproduce as reproduce_module
    from seqtrojan.zoo import build as zoo_build

    assert from_dict(ReproduceConfig, {}).jobs == JobsConfig()
    assert from_dict(ReproduceConfig, {"zoo_workers": 3}).jobs == JobsConfig(workers=3)  # an older scale file
    with pytest.raises(ConfigError, match=r"zoo_workers=3 and jobs\.workers=4 disagree"):
        from_dict(ReproduceConfig, {"zoo_workers": 3, "jobs": {"workers": 4}})
    seen = {}
    monkeypatch.setattr(reproduce_module, "reproduce", lambda config, out, scale: seen.update(jobs=config.jobs))
    argv = ["reproduce", "--scale", "smoke", "--out", str(tmp_path), "--backend", "ray", "--workers", "3",
            "--ray-address", "127.0.0.1:6379"]  # fmt: skip
    assert cli.main(argv) == 0
    assert seen["jobs"] == JobsConfig(backend="ray", workers=3, ray_address="127.0.0.1:6379")
    assert cli.main(["reproduce", "--scale", "smoke", "--out", str(tmp_path), "--threads", "1"]) == 0
    assert seen["jobs"] == JobsConfig(threads=1)  # the scale file's pool of 2, one thread each
    monkeypatch.setattr(zoo_build, "build_zoo", lambda cfg, out, **kw: seen.update(zoo=kw) or out / "manifest.json")
    assert cli.main(["zoo", "build", "--out", str(tmp_path), "--backend", "serial", "--workers", "1"]) == 0
    from seqtrojan.experiments.attacks import RECIPES

    assert seen["zoo"] == {"workers": 1, "backend": "serial", "ray_address": None, "threads": None, "recipes": RECIPES,
                           "limit": None, "progress": True}  # fmt: skip
    assert make_backend(JobsConfig(backend="serial")).name == "serial"
    assert (
        make_backend(JobsConfig(backend="ray", ray_address="10.0.0.5:6379"))
        .describe(4)
        .startswith("the Ray cluster at 10.0.0.5:6379, 1 CPU(s)")
    )


# ---------------------------------------------------------------------- a two-node Ray cluster

RAY_TINY = {"clean": 1, "backdoored": 1, "total_steps": 2048, "num_envs": 32, "eval_episodes": 8,
            "lstm_sizes": [[8]], "curricula": [[{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]]}  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(procs: list[subprocess.Popen], marker: str) -> None:
    """End the Ray processes this test started, by id: SIGTERM to each ``ray start --block`` (it stops the
    processes it started), then SIGKILL to their process groups and to any process naming this test's temp dir."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=30)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if marker.encode() in cmdline.read_bytes():
                os.kill(int(cmdline.parent.name), signal.SIGKILL)
        except (OSError, ValueError):
            pass


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Ray clusters of several nodes need Linux")
def test_a_two_node_ray_cluster_builds_a_zoo_like_the_serial_backend(tmp_path):
    pytest.importorskip("ray")
    ray_exe = str(Path(sys.executable).parent / "ray")
    port = _free_port()
    address = f"127.0.0.1:{port}"
    temp = tempfile.mkdtemp(prefix="stray", dir="/tmp")  # short: Ray's socket paths live under it
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN": secrets.token_hex(32)}  # fmt: skip
    node = ["--num-cpus=1", "--num-gpus=0", "--node-ip-address=127.0.0.1", "--object-store-memory=100000000",
            "--disable-usage-stats", "--block"]  # fmt: skip
    procs: list[subprocess.Popen] = []

    def start(args: list[str], log: str) -> None:
        with open(tmp_path / log, "w") as fh:
            procs.append(subprocess.Popen([ray_exe, "start", *args, *node], stdout=fh, stderr=subprocess.STDOUT,
                                          env=env, start_new_session=True))  # fmt: skip

    def logs() -> str:
        return "\n".join(p.read_text()[-3000:] for p in sorted(tmp_path.glob("*.log")))

    (tmp_path / "tiny.yaml").write_text(json.dumps(RAY_TINY))
    zoo = tmp_path / "ray_zoo"
    try:
        start(["--head", f"--port={port}", "--include-dashboard=false", f"--temp-dir={temp}"], "head.log")
        start([f"--address={address}"], "worker.log")
        wait_for_nodes = (
            "import sys, time, ray\n"
            f"ray.init(address={address!r}, log_to_driver=False)\n"
            "deadline = time.monotonic() + 150\n"
            "while sum(n['Alive'] and n['Resources'].get('CPU') == 1 for n in ray.nodes()) < 2:\n"
            "    assert time.monotonic() < deadline, ray.nodes()\n"
            "    time.sleep(0.5)\n"
        )
        deadline = time.monotonic() + 180
        while True:  # the head may not listen yet: retry until both nodes are up
            assert all(p.poll() is None for p in procs), logs()
            check = subprocess.run([sys.executable, "-c", wait_for_nodes], env=env, capture_output=True, text=True,
                                   timeout=240)  # fmt: skip
            if check.returncode == 0:
                break
            assert time.monotonic() < deadline, check.stderr[-3000:] + logs()
            time.sleep(2)
        argv = [sys.executable, "-m", "seqtrojan.cli", "zoo", "build", "--out", str(zoo), "--backend", "ray",
                "--ray-address", address, "--config-file", str(tmp_path / "tiny.yaml")]  # fmt: skip
        with open(tmp_path / "build.log", "w") as fh:
            build = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
            try:
                assert build.wait(timeout=400) == 0, logs()
            finally:
                if build.poll() is None:
                    build.kill()
                    build.wait(timeout=30)
    finally:
        _stop(procs, temp)
        shutil.rmtree(temp, ignore_errors=True)
    assert "with ray backend (the Ray cluster at 127.0.0.1:" in (tmp_path / "build.log").read_text()
    entries = json.loads((zoo / "manifest.json").read_text())
    assert [e["status"] for e in entries] == ["done", "done"]
    assert all(int(e["worker"].rsplit(":", 1)[1]) != build.pid for e in entries)  # trained by Ray workers

    cfg = ZooConfig(**{**ZooConfig().__dict__, **RAY_TINY, "lstm_sizes": ((8,),),
                       "curricula": ((GridSpec(5, 0), GridSpec(5, 1)),)})  # fmt: skip
    reference = tmp_path / "serial_zoo"
    build_zoo(cfg, reference, backend="serial", threads=1, log=lambda *_: None)
    for job in make_jobs(cfg, zoo):
        assert_same_weights(zoo / "models" / job.id, reference / "models" / job.id)
