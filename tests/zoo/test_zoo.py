"""Zoo jobs are pure and varied; a build writes models, labels and a manifest, resumes, and runs on Ray. A build
survives being killed (its workers die with it, a rerun finishes every model), a corrupt manifest, incomplete model
folders and a failing model, and refuses a rerun with another config."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import StopConfig
from seqtrojan.env import GridSpec
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.jobs import JobsFailed
from seqtrojan.jobs import backends as job_backends
from seqtrojan.train import trainer
from seqtrojan.zoo import build as zoo_build
from seqtrojan.zoo.build import ZooConfig, build_zoo, make_jobs

TINY = ZooConfig(
    clean=2, backdoored=2, total_steps=2048, num_envs=32, eval_episodes=16,
    curricula=((GridSpec(5, 0), GridSpec(5, 1)),), lstm_sizes=((8,), (8, 8)),
)  # fmt: skip
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """A finished TINY zoo, built once (serially); tests that change it work on a copy (:func:`copy_of`)."""
    root = tmp_path_factory.mktemp("built") / "zoo"
    build_zoo(TINY, root, workers=1, log=lambda *_: None)
    return root


def copy_of(zoo: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(zoo, tmp_path / "zoo"))


def manifest_of(zoo: Path) -> list[dict]:
    return json.loads((zoo / "manifest.json").read_text())


def test_jobs_are_a_pure_function_of_the_config(tmp_path):
    a, b = make_jobs(TINY, tmp_path), make_jobs(TINY, tmp_path)
    assert a == b
    assert sorted(j.label for j in a) == ["backdoored", "backdoored", "clean", "clean"]
    big = make_jobs(ZooConfig(clean=10, backdoored=10), tmp_path)
    assert (
        len({j.variation["trigger_value"] for j in big}) >= 2
        and len({tuple(j.variation["lstm_sizes"]) for j in big}) >= 2
    )
    assert len({j.config.run.seed for j in big}) == 20
    with pytest.raises(ConfigError, match="unknown trigger value"):
        ZooConfig(trigger_values=("lava",))


def test_build_writes_models_labels_manifest_and_resumes(built):
    entries = manifest_of(built)
    assert [e["status"] for e in entries] == ["done"] * 4
    for e in entries:
        folder = built / "models" / e["id"]
        _, cfg, card = load_agent(folder)
        truth = json.loads((folder / "label.json").read_text())
        assert truth["label"] == card["label"] == e["label"] == cfg.label
        assert (truth["trigger"] is None) == (e["label"] == "clean")
        assert truth["clean_success"] == card["metrics"]["normal_success"]
        if e["label"] == "backdoored":
            assert truth["attack_success"] == card["metrics"]["trojan_success"] == e["metrics"]["trojan_success"]
            assert truth["functional_backdoor"] == (truth["attack_success"] >= TINY.functional_at)
            assert truth["unintentional_activation"] is None
        else:
            assert truth["attack_success"] is None and truth["functional_backdoor"] is None
            assert truth["unintentional_activation"] == card["metrics"]["trojan_success"] is not None
        assert truth["learned_task"] is True  # learned_at 0 (the default): every model has
    assert json.loads((built / "zoo.json").read_text())["total_steps"] == TINY.total_steps
    logs = []
    build_zoo(TINY, built, workers=1, log=logs.append)
    assert logs[0].startswith("zoo: 4 of 4 models done; training 0")
    assert manifest_of(built) == entries


@pytest.mark.parametrize(
    "manifest",
    ['[{"id": "m0000", "status": "do', '{"m0000": "done"}', "[1, 2]", "pending"],
    ids=["truncated", "mapping", "not-entries", "all-pending"],
)
def test_a_corrupt_or_stale_manifest_is_rebuilt_from_the_model_folders(built, tmp_path, manifest):
    zoo = copy_of(built, tmp_path)
    done = manifest_of(zoo)
    if manifest == "pending":  # what a killed build left: models finished by workers after its last write
        manifest = json.dumps([{"id": e["id"], "label": e["label"], "status": "pending"} for e in done])
    (zoo / "manifest.json").write_text(manifest)
    logs = []
    build_zoo(TINY, zoo, workers=1, log=logs.append)
    assert any(line.startswith("zoo: 4 of 4 models done; training 0") for line in logs)
    rebuilt = manifest_of(zoo)
    assert [e["status"] for e in rebuilt] == ["done"] * 4
    for old, new in zip(done, rebuilt):
        assert {k: new[k] for k in ("id", "label", "variation", "metrics")} == {
            k: old[k] for k in ("id", "label", "variation", "metrics")
        }
    if "pending" not in manifest:
        assert any("manifest.json is corrupt" in line for line in logs)
    assert not list(zoo.glob(".manifest.json.*"))  # no temp file left behind


def test_a_zoo_built_before_the_cell_fields_is_the_same_config(built, tmp_path):
    """zoo.json of a zoo built before ZooConfig had cell and window: no such keys; a rerun is no new config."""
    zoo = copy_of(built, tmp_path)
    stored = json.loads((zoo / "zoo.json").read_text())
    assert not {"cell", "window", "stop", "rollout_steps", "learning_rate", "attacks"} & stored.keys()  # at defaults
    logs: list[str] = []
    build_zoo(TINY, zoo, workers=1, log=logs.append)
    assert any(line.startswith("zoo: 4 of 4 models done; training 0") for line in logs)
    gru = ZooConfig(**{**TINY.__dict__, "cell": "gru"})
    with pytest.raises(ConfigError, match=r'different config: cell \(built with nothing, now "gru"\)'):
        build_zoo(gru, zoo, workers=1, log=lambda *_: None)


def test_zoo_models_stop_early_by_the_rule_and_record_their_steps(tmp_path):
    stop = StopConfig(enabled=True, success=0.5, updates=1, min_episodes=10, confirm_episodes=50)
    cfg = ZooConfig(clean=1, backdoored=0, curricula=((GridSpec(5, 0),),), total_steps=400_000, num_envs=64,
                    eval_episodes=50, stop=stop)  # fmt: skip
    assert make_jobs(cfg, tmp_path)[0].config.stop == stop
    build_zoo(cfg, tmp_path, workers=1, backend="serial", log=lambda *_: None)
    (entry,) = manifest_of(tmp_path)
    assert entry["metrics"]["stopped_early"] and entry["metrics"]["env_steps"] < cfg.total_steps
    assert json.loads((tmp_path / "zoo.json").read_text())["stop"]["enabled"]


def test_zoo_ppo_settings_reach_every_model_and_bad_ones_are_refused(tmp_path):
    cfg = ZooConfig(clean=1, backdoored=1, rollout_steps=32, learning_rate=2e-3)
    assert {(j.config.ppo.rollout_steps, j.config.ppo.learning_rate) for j in make_jobs(cfg, tmp_path)} == {(32, 2e-3)}
    for bad in ({"rollout_steps": 0}, {"rollout_steps": True}, {"learning_rate": 0.0}, {"learning_rate": 1.5}):
        with pytest.raises(ConfigError, match=f"zoo {next(iter(bad))}"):
            ZooConfig(**bad)


def test_a_rerun_with_another_config_is_refused(built, tmp_path):
    zoo = copy_of(built, tmp_path)
    before = {p: p.stat().st_mtime_ns for p in zoo.rglob("*") if p.suffix != ".lock"}
    changed = ZooConfig(**{**TINY.__dict__, "total_steps": 4096, "eval_episodes": 8})
    with pytest.raises(
        ConfigError, match=r"different config: eval_episodes .*, total_steps \(built with 2048, now 4096\)"
    ):
        build_zoo(changed, zoo, workers=1, log=lambda *_: None)
    after = {p: p.stat().st_mtime_ns for p in zoo.rglob("*") if p.suffix != ".lock"}
    assert after == before  # nothing trained, nothing rewritten
    (zoo / "zoo.json").write_text("{broken")
    with pytest.raises(ConfigError, match=r"zoo\.json' is not a zoo config"):
        build_zoo(TINY, zoo, workers=1, log=lambda *_: None)


def test_a_rerun_with_another_functional_threshold_relabels_without_training(built, tmp_path):
    """functional_at decides a finished model's label, never its training: a rerun that changes only it (at the top
    or in a part) stores it and rewrites each poisoned model's functional_backdoor; nothing is trained again."""
    zoo = copy_of(built, tmp_path)
    weights = {p: p.read_bytes() for p in zoo.glob("models/*/model.safetensors")}

    def labels() -> list[dict]:
        found = [json.loads(p.read_text()) for p in sorted(zoo.glob("models/*/label.json"))]
        return [t for t in found if t["label"] == "backdoored"]

    assert any(t["attack_success"] < 1.0 for t in labels())  # so the threshold 1 relabels some model
    for at in (0.0, 1.0):
        logs: list[str] = []
        build_zoo(dataclasses.replace(TINY, functional_at=at), zoo, workers=1, log=logs.append)
        assert any("how models are labelled only (functional_at, learned_at)" in line for line in logs)
        assert any(line.startswith("zoo: 4 of 4 models done; training 0") for line in logs)
        assert json.loads((zoo / "zoo.json").read_text())["functional_at"] == at
        assert [t["functional_backdoor"] for t in labels()] == [t["attack_success"] >= at for t in labels()]
    every = [json.loads(p.read_text()) for p in sorted(zoo.glob("models/*/label.json"))]
    assert all(t["learned_task"] is True for t in every)  # learned_at 0: every model counts
    assert all(t["clean_success"] < 1.0 for t in every)  # so learned_at 1 relabels every model, of both labels
    for at in (1.0, 0.0):
        build_zoo(dataclasses.replace(TINY, learned_at=at), zoo, workers=1, log=lambda *_: None)
        every = [json.loads(p.read_text()) for p in sorted(zoo.glob("models/*/label.json"))]
        assert [t["learned_task"] for t in every] == [at == 0.0] * 4
    assert {p: p.read_bytes() for p in zoo.glob("models/*/model.safetensors")} == weights
    with pytest.raises(ConfigError, match=r"different config: eval_episodes"):  # with a training field: refused
        build_zoo(dataclasses.replace(TINY, functional_at=0.5, eval_episodes=8), zoo, workers=1, log=lambda *_: None)
    for bad in (-0.1, 1.5, True):
        with pytest.raises(ConfigError, match="zoo functional_at must be in"):
            dataclasses.replace(TINY, functional_at=bad)
        with pytest.raises(ConfigError, match="zoo learned_at must be in"):
            dataclasses.replace(TINY, learned_at=bad)


def test_incomplete_model_folders_are_trained_again_and_cores_are_not_oversubscribed(built, tmp_path, monkeypatch):
    zoo = copy_of(built, tmp_path)
    weights = zoo / "models" / "m0001" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])  # a copy cut short; label.json kept
    (zoo / "models" / "m0002" / "label.json").write_text("[]")  # a complete model whose label is malformed
    shutil.rmtree(zoo / "models" / "m0003")  # never finished
    monkeypatch.setattr(job_backends, "available_cpus", lambda: 1)
    torch.set_num_threads(1)
    logs = []
    build_zoo(TINY, zoo, workers=2, log=logs.append)
    assert any(line.startswith("  m0001: incomplete (") for line in logs)
    assert sorted(line.split()[0] for line in logs if " done in " in line) == ["m0001", "m0003"]
    assert any("2 of 4 models done; training 2 with pool backend (1 worker(s) x 1 torch thread(s))" in line
               for line in logs)  # fmt: skip
    assert torch.get_num_threads() == 1  # the build leaves the caller's torch threads as they were
    assert [e["status"] for e in manifest_of(zoo)] == ["done"] * 4
    for job in make_jobs(TINY, zoo):
        load_agent(zoo / "models" / job.model_id)
        assert json.loads((zoo / "models" / job.model_id / "label.json").read_text())["label"] == job.label
    assert not any((zoo / "work").iterdir())


def test_a_build_refuses_to_run_beside_another_build_or_its_workers(built, tmp_path, monkeypatch):
    fcntl = pytest.importorskip("fcntl")

    zoo = copy_of(built, tmp_path)
    with open(zoo / "build.lock", "a") as held:  # another build of this zoo is running
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SeqTrojanError, match=r"another build of zoo .* is running"):
            build_zoo(TINY, zoo, workers=1, log=lambda *_: None)
    monkeypatch.setattr(zoo_build, "WORKERS_EXIT_S", 0.3, raising=False)
    with open(zoo / "workers.lock", "a") as held:  # a worker of an earlier build still runs
        fcntl.flock(held, fcntl.LOCK_SH | fcntl.LOCK_NB)
        held.write("4242\n")
        held.flush()
        with pytest.raises(SeqTrojanError, match=r"worker processes of an earlier build .* still run \(pids 4242\)"):
            build_zoo(TINY, zoo, workers=1, log=lambda *_: None)
    logs = []
    build_zoo(TINY, zoo, workers=1, log=logs.append)  # both gone: the build runs
    assert logs[0].startswith("zoo: 4 of 4 models done")


def built_models(zoo: Path) -> dict[str, dict]:
    """Each model of a finished zoo by id: its manifest entry, its label.json, its card's metrics and recorded
    SHA-256 (less the run's time and worker), and the SHA-256 of its weights file as written."""
    models = {}
    for e in manifest_of(zoo):
        folder = zoo / "models" / e["id"]
        card = json.loads((folder / "card.json").read_text())
        untimed = {k: v for k, v in card["metrics"].items() if k != "train_seconds"}
        models[e["id"]] = {
            "entry": {k: v for k, v in e.items() if k not in ("seconds", "worker", "metrics")},
            "label.json": json.loads((folder / "label.json").read_text()),
            "metrics": ({k: v for k, v in e["metrics"].items() if k != "train_seconds"}, untimed),
            "card": (card["label"], card["env_steps"], card["weights_sha256"]),
            "weights": hashlib.sha256((folder / "model.safetensors").read_bytes()).hexdigest(),
        }
    return models


def test_ray_backend_builds_the_same_models_as_the_serial_backend(tmp_path):
    """The same zoo built on Ray and serially (one torch thread per job on both: a seed fixes a run bitwise only at a
    fixed thread count): the same models, bitwise, under the same ids, with the same manifest entries and labels."""
    pytest.importorskip("ray")
    cfg = ZooConfig(**{**TINY.__dict__, "clean": 1, "backdoored": 1})
    serial = build_zoo(cfg, tmp_path / "serial", backend="serial", threads=1, log=lambda *_: None).parent
    ray = build_zoo(cfg, tmp_path / "ray", workers=2, backend="ray", threads=1, log=lambda *_: None).parent
    expected = built_models(serial)
    assert sorted(expected) == ["m0000", "m0001"] and {m["entry"]["status"] for m in expected.values()} == {"done"}
    assert {m["entry"]["label"] for m in expected.values()} == {"clean", "backdoored"}
    assert len({m["weights"] for m in expected.values()}) == 2  # two different models: a swap would show
    assert built_models(ray) == expected


def test_a_failing_model_is_marked_failed_while_the_others_finish_and_a_rerun_retries_it(built, tmp_path, monkeypatch):
    zoo = copy_of(built, tmp_path)
    for model_id in ("m0001", "m0003"):
        shutil.rmtree(zoo / "models" / model_id)
    train = zoo_build._train_zoo_model

    def failing(job):
        if job.id == "m0001":
            raise ConfigError("a broken job")
        return train(job)

    monkeypatch.setattr(zoo_build, "_train_zoo_model", failing)
    logs = []
    with pytest.raises(JobsFailed, match=r"^1 of 2 zoo model\(s\) failed: m0001: a broken job \("):
        build_zoo(TINY, zoo, workers=1, backend="serial", log=logs.append)
    entries = {e["id"]: e for e in manifest_of(zoo)}
    assert entries["m0001"]["status"] == "failed" and entries["m0001"]["error"] == "a broken job"
    assert [entries[i]["status"] for i in ("m0000", "m0002", "m0003")] == ["done"] * 3  # m0003 trained
    assert any(line.startswith("  m0001 (") and line.endswith("failed: a broken job") for line in logs)
    load_agent(zoo / "models" / "m0003")
    assert not (zoo / "models" / "m0001").exists()
    monkeypatch.setattr(zoo_build, "_train_zoo_model", train)
    logs = []
    build_zoo(TINY, zoo, workers=1, backend="serial", log=logs.append)
    assert logs[0].startswith("zoo: 3 of 4 models done; training 1 with serial backend")
    assert [e["status"] for e in manifest_of(zoo)] == ["done"] * 4


def test_an_unknown_backend_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(
        ConfigError, match=r"jobs\.backend='slurm' is not a backend; use one of \['serial', 'pool', 'ray'\]"
    ):
        build_zoo(TINY, tmp_path / "zoo", backend="slurm", log=lambda *_: None)
    assert not (tmp_path / "zoo").exists()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (dead, not yet reaped by its new parent) counts as dead
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _listed(zoo: Path) -> set[int]:
    """The pids the build's workers wrote into workers.lock."""
    path = zoo / "workers.lock"
    return {int(p) for p in path.read_text().split()} if path.exists() else set()


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(stat.parent.name))
        except (OSError, IndexError, ValueError):
            pass
    return kids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the build's worker processes in /proc")
def test_kill_9_of_a_build_leaves_no_worker_and_a_rerun_finishes_every_model(tmp_path):
    spec = {"clean": 1, "backdoored": 1, "total_steps": 4096, "num_envs": 8, "eval_episodes": 8,
            "lstm_sizes": [[8]], "curricula": [[{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]]}  # fmt: skip
    (tmp_path / "tiny.yaml").write_text(json.dumps(spec))  # JSON is YAML
    zoo = tmp_path / "zoo"
    argv = [sys.executable, "-m", "seqtrojan.cli", "zoo", "build", "--out", str(zoo), "--workers", "2",
            "--config-file", str(tmp_path / "tiny.yaml")]  # fmt: skip
    with open(tmp_path / "build.log", "w") as out:
        build = subprocess.Popen(argv, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 240
        # kill once a worker is mid-training (it has written a checkpoint) and both workers have started
        while not (
            list(zoo.glob("work/m*/checkpoints/latest.txt"))
            and len(_children(build.pid)) >= 2
            and (len(_listed(zoo)) == 2 or not (zoo / "workers.lock").exists())
        ):
            assert build.poll() is None, (tmp_path / "build.log").read_text()
            assert time.monotonic() < deadline, "the build never started training"
            time.sleep(0.05)
        workers = _children(build.pid)
        os.kill(build.pid, signal.SIGKILL)
        build.wait(timeout=30)
        deadline = time.monotonic() + 20
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p in workers if _alive(p)], "worker processes outlived the killed build"
    finally:
        if build.poll() is None:
            build.kill()
            build.wait(timeout=30)
        for pid in workers:  # never leave a stray process behind, whatever happened
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert len(_listed(zoo)) == 2 and _listed(zoo) <= set(workers)  # the workers recorded their pids
    cfg = ZooConfig(**{**ZooConfig().__dict__, **spec, "lstm_sizes": ((8,),),
                       "curricula": ((GridSpec(5, 0), GridSpec(5, 1)),)})  # fmt: skip
    build_zoo(cfg, zoo, workers=1, log=lambda *_: None)
    assert [e["status"] for e in manifest_of(zoo)] == ["done", "done"]
    for job in make_jobs(cfg, zoo):
        _, _, card = load_agent(zoo / "models" / job.model_id)
        assert card["env_steps"] == 4096


def test_a_zoo_of_a_minigrid_env_builds_and_is_scored(tmp_path):
    """``env_preset``: every model is the MiniGrid preset's run with its own seed, widths and trigger (cells of the
    view's far rows, object and colour); the zoo builds, labels its models, and the weight detector scores it
    (without the grid world's input-code features, which a MiniGrid view has none of)."""
    from seqtrojan.defense.offline import detect_zoo

    cfg = ZooConfig(clean=3, backdoored=3, total_steps=512, eval_episodes=4, lstm_sizes=((8,), (8, 8)),
                    env_preset="minigrid_two_goals")  # fmt: skip
    jobs = make_jobs(cfg, tmp_path)
    assert jobs == make_jobs(cfg, tmp_path)  # a pure function of the config
    triggers = {(j.config.env.trigger.object, j.config.env.trigger.color, j.config.env.trigger.cells) for j in jobs}
    assert len(triggers) > 1 and all(r < 2 and c < 5 for t in triggers for r, c in t[2])
    assert {j.config.backdoor.enabled for j in jobs} == {True, False} and all(not j.config.grids for j in jobs)
    build_zoo(cfg, tmp_path, workers=1, backend="serial", log=lambda *_: None)
    models = sorted((tmp_path / "models").iterdir())
    assert len(models) == 6
    truth = json.loads((models[0] / "label.json").read_text())
    assert truth["variation"]["env"] == "seqtrojan/MiniGridTwoGoals-v0"
    backdoored = [json.loads((m / "label.json").read_text()) for m in models]
    assert all(t["trigger"]["value"] == t["variation"]["trigger_value"] for t in backdoored if t["trigger"])
    result = detect_zoo(tmp_path, folds=2)
    assert [s.group for s in result.scores] == ["all", "gate_stats", "spectral"] and not result.rejected
    with pytest.raises(ConfigError, match="must be a Gymnasium env"):
        make_jobs(ZooConfig(clean=1, backdoored=1, env_preset="smoke"), tmp_path / "grid")


@pytest.mark.parametrize(("preset", "patch"), [("popgym_repeat_previous", "vector"), ("minatar_breakout", "box")])
def test_a_zoo_of_a_popgym_or_minatar_env_draws_its_triggers_and_target_actions(tmp_path, preset, patch):
    """POPGym and MinAtar models in the zoo: a box square moved inside the image, a vector patch as the preset
    gives it, a target action drawn among the env's actions; each model's env is one the agents can read."""
    from seqtrojan.world import env_spec

    cfg = ZooConfig(clean=4, backdoored=4, total_steps=512, eval_episodes=4, lstm_sizes=((8,),), env_preset=preset)
    jobs = make_jobs(cfg, tmp_path)
    assert jobs == make_jobs(cfg, tmp_path)
    triggers = [j.config.env.trigger for j in jobs]
    spec = env_spec(jobs[0].config.env)
    assert all(t.patch == patch and 0 <= t.target_action < spec.num_actions for t in triggers)
    assert len({t.target_action for t in triggers}) > 1
    if patch == "box":
        assert len({t.cells for t in triggers}) > 1 and all(0 <= r < 10 and 0 <= c < 10 for t in triggers
                                                            for r, c in t.cells)  # fmt: skip
    for job in jobs[:2]:
        env_spec(job.config.env)  # the drawn trigger fits the observation
        assert job.variation["target_action"] == job.config.env.trigger.target_action
    build_zoo(dataclasses.replace(cfg, clean=1, backdoored=1), tmp_path, workers=1, backend="serial",
              log=lambda *_: None)  # fmt: skip
    assert len(list((tmp_path / "models").iterdir())) == 2


def _label_file(folder: Path, case: str) -> None:
    path = folder / "label.json"
    if case == "FIFO":
        os.mkfifo(path)
    elif case == "oversized":
        path.write_text(json.dumps({"label": "clean", "note": "x" * (64 << 10)}))
    elif case == "deeply nested":
        path.write_text('{"label": "clean", "variation": ' + "[" * 5000 + "]" * 5000 + "}")
    elif case == "duplicate key":
        path.write_text('{"label": "clean", "label": "backdoored"}')


@pytest.mark.parametrize(
    "case, message",
    [("FIFO", "is not a regular file"), ("oversized", "larger than the 65536 bytes"),
     ("deeply nested", "nests lists/objects more than 32 deep"), ("duplicate key", "duplicate key 'label'")],
)  # fmt: skip
def test_label_json_is_read_as_untrusted_input_without_blocking(tmp_path, case, message):
    """label.json is refused in one line, never waited on (a FIFO), never read whole when oversized, never parsed
    into a RecursionError; in any thread, within a second."""
    _label_file(tmp_path, case)
    outcome: list[BaseException | dict] = []

    def read() -> None:
        try:
            outcome.append(zoo_build.read_label(tmp_path))
        except BaseException as err:  # reported below
            outcome.append(err)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout=5)
    assert outcome, "read_label blocked"
    (err,) = outcome
    assert isinstance(err, SeqTrojanError) and message in str(err) and "\n" not in str(err)


def test_pretrained_models_add_their_backdoor_to_their_own_clean_stage(tmp_path, monkeypatch):
    """``pretrain_steps``: every model trains clean first, then its second stage starts from that model (a poisoned
    one adds its backdoor there, a clean one trains on, clean); the first stage's run is removed once the model is
    in place, and a zoo asking for Algorithm 1's mixing is refused before anything trains."""
    cfg = ZooConfig(**{**TINY.__dict__, "clean": 1, "backdoored": 1, "mixing": "fixed", "pretrain_steps": 1024})
    jobs = make_jobs(cfg, tmp_path)
    for job in jobs:
        assert job.pretrain is not None and not job.pretrain.backdoor.enabled
        assert job.pretrain.ppo.total_steps == 1024 and job.config.ppo.total_steps == TINY.total_steps
        assert job.pretrain.run.seed == job.config.run.seed and job.pretrain.agent == job.config.agent
        assert job.config.run.init_from == str(tmp_path / "work" / f"{job.id}_clean" / "model")
        assert job.variation["pretrain_steps"] == 1024
    assert {j.config.backdoor.enabled for j in jobs} == {True, False}
    starts, seen = [], {}

    original = trainer.train_or_resume

    def recording(config):
        starts.append((config.run.name, config.run.init_from, config.backdoor.enabled))
        if config.run.init_from is not None:  # the clean stage's weights as the model's own stage starts
            seen[config.run.name] = (Path(config.run.init_from) / "model.safetensors").stat().st_mtime_ns
        return original(config)

    monkeypatch.setattr(trainer, "train_or_resume", recording)
    build_zoo(cfg, tmp_path, workers=1, backend="serial", log=lambda *_: None)
    for job in jobs:  # the clean stage first, then the model's own stage from it
        mine = [s for s in starts if s[0].startswith(job.id)]
        assert mine == [(f"{job.id}_clean", None, False), (job.id, job.config.run.init_from, job.label == "backdoored")]
        card = json.loads((tmp_path / "models" / job.id / "card.json").read_text())
        assert card["config"]["run"]["init_from"] == job.config.run.init_from
    assert not (tmp_path / "work" / f"{jobs[0].id}_clean").exists()
    for job in jobs:  # both stages' training curves kept outside the model folder, CURVE_FIELDS only
        for name, steps in ((job.id, job.config.ppo.total_steps), (f"{job.id}_clean", 1024)):
            rows = [json.loads(line) for line in (tmp_path / "curves" / f"{name}.jsonl").read_text().splitlines()]
            trojan = name == job.id and job.label == "backdoored"
            fields = zoo_build.CURVE_FIELDS if trojan else zoo_build.CURVE_FIELDS[:2]
            assert rows and all(tuple(r) == fields for r in rows)  # a clean run has no trojan episodes
            assert [r["env_steps"] for r in rows] == sorted(r["env_steps"] for r in rows)
            assert rows[-1]["env_steps"] >= steps
        assert not [p.name for p in job.model_dir.iterdir() if p.suffix == ".jsonl"]  # a detector never reads it
    # a build stopped after a model's clean stage: the rerun reuses that stage and trains only the model's own
    other = make_jobs(cfg, tmp_path / "stopped")[0]
    original(other.pretrain)
    first = (Path(other.config.run.init_from) / "model.safetensors").stat().st_mtime_ns
    starts.clear()
    other.model_dir.parent.mkdir(parents=True)
    zoo_build._train_zoo_model(other)
    assert [s[0] for s in starts] == [f"{other.id}_clean", other.id]  # asked for, found finished
    assert seen[other.id] == first  # not written again
    assert json.loads((other.model_dir / "card.json").read_text())["config"]["run"]["init_from"] == str(
        Path(other.config.run.init_from)
    )
    with pytest.raises(ConfigError, match="zoo pretrain_steps needs the fixed mixing"):
        make_jobs(ZooConfig(**{**cfg.__dict__, "mixing": "running"}), tmp_path / "other")
    with pytest.raises(ConfigError, match="pretrain_steps must be an integer >= 0, got -1"):
        ZooConfig(pretrain_steps=-1)


@pytest.mark.parametrize("key", ["attack_success", "clean_success", "unintentional_activation"])
def test_a_label_s_rates_must_be_numbers_or_null(tmp_path, key):
    (tmp_path / "label.json").write_text(json.dumps({"label": "clean", key: "high"}))
    with pytest.raises(SeqTrojanError, match=f"{key} must be null or a number") as err:
        zoo_build.read_label(tmp_path)
    assert "\n" not in str(err.value)
    (tmp_path / "label.json").write_text(json.dumps({"label": "clean", key: None}))
    assert zoo_build.read_label(tmp_path)["label"] == "clean"  # null, or absent in older labels: accepted


@pytest.mark.parametrize("key", ["functional_backdoor", "learned_task"])
def test_a_label_s_verdicts_must_be_booleans_or_null(tmp_path, key):
    (tmp_path / "label.json").write_text(json.dumps({"label": "clean", key: "yes"}))
    with pytest.raises(SeqTrojanError, match=f"{key} must be null or a boolean") as err:
        zoo_build.read_label(tmp_path)
    assert "\n" not in str(err.value)
    for value in (None, True, False):
        (tmp_path / "label.json").write_text(json.dumps({"label": "clean", key: value}))
        assert zoo_build.read_label(tmp_path)[key] is value


MINIGRID_PART = ZooConfig(clean=2, backdoored=2, seed=100, total_steps=512, eval_episodes=4, lstm_sizes=((8,),),
                          env_preset="minigrid_two_goals", functional_at=0.0)  # fmt: skip
GRID_PART = dataclasses.replace(TINY, clean=3, backdoored=3, functional_at=0.0)


def parts_zoo(**changes) -> ZooConfig:
    fields = {"clean": 5, "backdoored": 5, "parts": (GRID_PART, MINIGRID_PART), **changes}
    return ZooConfig(**fields)


def test_a_zoo_of_parts_holds_each_part_s_models_numbered_on(tmp_path):
    """``parts``: each part's models are the ones it draws as a zoo of its own (seed, label, widths, trigger, env),
    numbered on after the previous part's, with their runs under the zoo; the counts must be the parts' totals and
    no two parts may share training seeds."""
    jobs = make_jobs(parts_zoo(), tmp_path)
    assert [j.id for j in jobs] == [f"m{i:04d}" for i in range(10)]
    for part, own in ((GRID_PART, jobs[:6]), (MINIGRID_PART, jobs[6:])):
        alone = make_jobs(part, tmp_path)
        assert [(j.label, j.variation, j.config.env, j.config.agent) for j in own] == [
            (j.label, j.variation, j.config.env, j.config.agent) for j in alone
        ]
    assert {j.variation.get("env", "grid") for j in jobs[6:]} == {"seqtrojan/MiniGridTwoGoals-v0"}
    assert len({j.config.run.seed for j in jobs}) == 10 and jobs[7].config.run.name == "m0007"
    with pytest.raises(ConfigError, match="clean must be 5 and backdoored 5, got 20 and 20"):
        ZooConfig(parts=(GRID_PART, MINIGRID_PART))
    with pytest.raises(ConfigError, match="parts 0 and 1 share training seeds"):
        parts_zoo(parts=(GRID_PART, dataclasses.replace(MINIGRID_PART, seed=4)))
    with pytest.raises(ConfigError, match="a zoo's holdout is its own"):
        parts_zoo(parts=(GRID_PART, dataclasses.replace(MINIGRID_PART, holdout={"cell": ("gru",)})))
    with pytest.raises(ConfigError, match="must be among the zoo's attacks"):
        parts_zoo(holdout={"attack": ("sequence",)})


def test_a_zoo_of_two_envs_builds_resumes_and_is_scored_by_env(tmp_path):
    """A grid-world part and a MiniGrid part in one zoo (written as YAML, as a preset is): built in installments
    that take the parts in turn, then whole, rebuilt as done, refused with another part, scored with the env as a
    factor of the leaderboard."""
    import yaml

    from seqtrojan.benchmark.leaderboard import run_leaderboard
    from seqtrojan.serde import from_dict, load_yaml, to_dict

    (tmp_path / "zoo.yaml").write_text(yaml.safe_dump(to_dict(parts_zoo())))
    cfg = from_dict(ZooConfig, load_yaml(tmp_path / "zoo.yaml"), "")
    assert cfg == parts_zoo()
    zoo = tmp_path / "zoo"
    log: list[str] = []
    build_zoo(cfg, zoo, workers=1, backend="serial", log=log.append, limit=4)  # an installment takes both parts
    assert sorted(p.name for p in (zoo / "models").iterdir()) == ["m0000", "m0001", "m0006", "m0007"]
    assert "training 4 with serial backend" in log[0] and "6 left for a later build (limit 4)" in log[0]
    log.clear()
    build_zoo(cfg, zoo, workers=1, backend="serial", log=log.append, limit=0)  # checks and relabels, trains none
    assert "4 of 10 models done; training 0" in log[0] and len(list((zoo / "models").iterdir())) == 4
    for bad in (-1, True, 1.5):
        with pytest.raises(ConfigError, match="a build's limit must be a number of models >= 0"):
            build_zoo(cfg, zoo, workers=1, backend="serial", log=lambda *_: None, limit=bad)  # type: ignore[arg-type]
    build_zoo(cfg, zoo, workers=1, backend="serial", log=lambda *_: None)
    log.clear()
    build_zoo(cfg, zoo, workers=1, backend="serial", log=log.append)
    assert "10 of 10 models done" in log[0]
    with pytest.raises(ConfigError, match="parts"):
        build_zoo(parts_zoo(parts=(GRID_PART, dataclasses.replace(MINIGRID_PART, total_steps=1024))), zoo,
                  workers=1, backend="serial", log=lambda *_: None)  # fmt: skip
    board = run_leaderboard(zoo, tmp_path / "board", None, ["metadata_baseline"], rounds=20, log=lambda *_: None)
    envs = {value for split in board.detectors[0].splits for value in split.by_factor["env"]}
    assert envs == {"grid", "seqtrojan/MiniGridTwoGoals-v0"}


def test_a_detector_is_fitted_per_env_on_a_zoo_of_two_envs(tmp_path, monkeypatch):
    """Each env's test models are answered by the fit on that env's train models; an env the train split lacks (held
    out) by the fit on every train model; the fits' sizes are written with the predictions."""
    from seqtrojan.benchmark import detectors as benchmark_detectors
    from seqtrojan.benchmark.leaderboard import ALL_ENVS, run_leaderboard
    from seqtrojan.benchmark.splits import SplitConfig
    from seqtrojan.env.config import EnvConfig

    zoo = tmp_path / "zoo"
    build_zoo(parts_zoo(), zoo, workers=1, backend="serial", log=lambda *_: None)

    @dataclasses.dataclass(frozen=True)
    class GridShare:  # answers the share of grid-world suspects among those it was fitted on
        share: float

        def probability(self, suspect) -> float:
            return self.share

    class Recorder:
        def fit(self, suspects, labels):
            return GridShare(sum(isinstance(s.env, EnvConfig) for s in suspects) / len(suspects))

    registry = benchmark_detectors.DETECTORS
    monkeypatch.setattr(registry, "_entries", dict(registry._entries))
    registry.register("recorder", "records what it was fitted on", Recorder())
    log: list[str] = []
    run_leaderboard(zoo, tmp_path / "a", SplitConfig(test_share=0.34), ["recorder"], rounds=10, log=log.append)
    answers = json.loads((tmp_path / "a" / "predictions" / "recorder.json").read_text())
    env_of = {e["id"]: e["variation"].get("env", "grid") for e in manifest_of(zoo)}
    assert answers["predictions"] and all(
        a["probability"] == (1.0 if env_of[a["model_id"]] == "grid" else 0.0) for a in answers["predictions"]
    )
    assert set(answers["fits"]) == {"grid", "seqtrojan/MiniGridTwoGoals-v0"} and "per env: grid on" in log[-1]
    held = SplitConfig(holdout={"env": ("seqtrojan/MiniGridTwoGoals-v0",)})
    run_leaderboard(zoo, tmp_path / "b", held, ["recorder"], rounds=10, log=lambda *_: None)
    answers = json.loads((tmp_path / "b" / "predictions" / "recorder.json").read_text())
    assert answers["fits"] == {"grid": 2, ALL_ENVS: 2}  # the held-out env's models: the fit on every train model
    assert {a["probability"] for a in answers["predictions"] if a["split"] == "holdout"} == {1.0}


def test_pretrain_stop_stops_only_the_clean_first_stage(tmp_path):
    """``pretrain_stop``: the first stage (the same for both labels) stops once learned; the second keeps the zoo's
    ``stop`` (off here: every model trains its whole second stage, whatever its label)."""
    rule = StopConfig(enabled=True, success=0.95)
    cfg = ZooConfig(**{**TINY.__dict__, "mixing": "fixed", "pretrain_steps": 1024, "pretrain_stop": rule})
    jobs = make_jobs(cfg, tmp_path)
    assert all(j.pretrain.stop == rule and j.config.stop == StopConfig() for j in jobs)
    both = dataclasses.replace(cfg, pretrain_stop=StopConfig(), stop=rule)  # without it: the zoo's stop, both stages
    assert all(j.pretrain.stop == rule and j.config.stop == rule for j in make_jobs(both, tmp_path))
    assert "pretrain_stop" not in TINY.serde_dump() and cfg.serde_dump()["pretrain_stop"]["enabled"]
    with pytest.raises(ConfigError, match="zoo pretrain_stop stops the clean first stage early: set pretrain_steps"):
        ZooConfig(pretrain_stop=rule)
