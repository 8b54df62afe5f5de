"""The `seqtrojan` command through its real entry point (a subprocess, as a user runs it)."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import ROOT


def seqtrojan(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "seqtrojan.cli", *args], capture_output=True, text=True, cwd=cwd or ROOT, timeout=600
    )


def test_help_lists_the_commands():
    out = seqtrojan("--help")
    assert out.returncode == 0 and "train" in out.stdout and "demo" in out.stdout


def test_unknown_command_fails_clearly():
    out = seqtrojan("frobnicate")
    assert out.returncode == 2 and "unknown command 'frobnicate'" in out.stderr


def test_train_smoke_preset_with_overrides(tmp_path):
    out = seqtrojan(
        "train", "--config", str(ROOT / "configs" / "smoke.yaml"), "--run.out-dir", str(tmp_path),
        "--run.name", "cli", "--ppo.total-steps", "4096", "--run.no-progress",
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "success on 5x5/1 (normal env, 200 episodes)" in out.stdout
    card = json.loads((tmp_path / "cli" / "model" / "card.json").read_text())
    assert card["env_steps"] == 4096 and card["config"]["ppo"]["total_steps"] == 4096


def test_train_resume_continues_a_run(tmp_path):
    common = ["--config", str(ROOT / "configs" / "smoke.yaml"), "--run.out-dir", str(tmp_path), "--run.name", "r"]
    assert seqtrojan("train", *common, "--ppo.total-steps", "4096", "--run.no-progress").returncode == 0
    out = seqtrojan("train", "--resume", str(tmp_path / "r"), "--ppo.total-steps", "8192", "--run.no-progress")
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "r" / "model" / "card.json").read_text())["env_steps"] == 8192


def test_bad_config_values_and_files_fail_with_the_value_named(tmp_path):
    out = seqtrojan("train", "--env.holes", "40", "--run.out-dir", str(tmp_path))
    assert out.returncode != 0 and "size=7, holes=40" in out.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo:\n  learning_rat: 0.1\n")
    out = seqtrojan("train", "--config", str(bad))
    assert out.returncode == 2 and "unknown config key(s) ['learning_rat'] in ppo" in out.stderr
    out = seqtrojan("train", "--config", str(tmp_path / "missing.yaml"))
    assert out.returncode == 2 and "does not exist" in out.stderr


def test_demo_writes_its_outputs(tmp_path):
    out = seqtrojan("demo", "--out", str(tmp_path / "demo"), "--episodes", "64")
    assert out.returncode == 0, out.stderr
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert summary["agents"]["oracle/trojan"]["success"] == 1.0
    assert (tmp_path / "demo" / "trajectories.png").stat().st_size > 1000
