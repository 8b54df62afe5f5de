"""Output folders: a file given as --out is refused in one line; one writer per folder (a second one is refused in
one line naming the holder's pid), and a holder killed with SIGKILL releases the folder."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import yaml

from seqtrojan.cli import main
from seqtrojan.config import ExperimentConfig, PPOConfig
from seqtrojan.errors import ConfigError
from seqtrojan.folders import FolderInUse, folder_lock, make_output_folder
from seqtrojan.serde import to_dict

HOLDER = """\
import sys, time
from pathlib import Path
from seqtrojan.folders import folder_lock
with folder_lock(Path(sys.argv[1])):
    print("held", flush=True)
    time.sleep(60)
"""


def _holder(folder) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_one_writer_per_folder_and_a_killed_holder_releases_it(tmp_path):
    proc = _holder(tmp_path)
    try:
        message = rf"run folder '{tmp_path}' is in use by another seqtrojan process \(pid {proc.pid}\)"
        with pytest.raises(FolderInUse, match=message), folder_lock(tmp_path):
            pass
    finally:
        proc.kill()  # SIGKILL: no cleanup runs in the holder
        proc.wait()
    with folder_lock(tmp_path):  # the kernel released the lock with its holder
        assert (tmp_path / ".lock").read_text().strip().isdigit()


def test_a_second_training_of_a_held_run_folder_is_refused_in_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    cfg = ExperimentConfig(ppo=PPOConfig(num_envs=4, rollout_steps=4, num_minibatches=1))
    (run / "config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    proc = _holder(run)
    try:
        assert main(["train", "--resume", str(run), "--run.no-progress"]) == 2
    finally:
        proc.kill()
        proc.wait()
    err = capsys.readouterr().err
    assert f"is in use by another seqtrojan process (pid {proc.pid})" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in run.iterdir()) == [".lock", "config.yaml"]  # nothing written by the refused one


def test_an_output_path_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(ConfigError, match=r"--out '.*f' exists and is not a folder"):
        make_output_folder(tmp_path / "f", "--out")
    assert make_output_folder(tmp_path / "a" / "b", "--out").is_dir()


def test_a_held_run_folder_is_not_cleared_by_a_pipeline_and_an_import_into_a_held_folder_is_refused(tmp_path):
    """train_or_resume clears a run folder left before a first checkpoint only when nobody writes it; an import
    into a folder another import holds is refused, and nothing of the holder's is touched."""
    from seqtrojan.agent.imports import import_agent
    from seqtrojan.train.trainer import train_or_resume

    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "metrics.jsonl").write_text("{}\n")  # the holder's files
    cfg = ExperimentConfig(ppo=PPOConfig(num_envs=4, rollout_steps=4, num_minibatches=1))
    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, out_dir=str(tmp_path / "runs"), name="r"))
    target = tmp_path / "imported"
    target.mkdir()
    holders = [_holder(run), _holder(target)]
    try:
        with pytest.raises(FolderInUse, match="is in use by another seqtrojan process"):
            train_or_resume(cfg)
        with pytest.raises(ConfigError, match="already exists and is not an empty folder"):
            import_agent("sb3", tmp_path / "missing.zip", target)
    finally:
        for proc in holders:
            proc.kill()
            proc.wait()
    assert (run / "metrics.jsonl").read_text() == "{}\n"
    assert sorted(p.name for p in target.iterdir()) == [".lock"]
