"""The `seqtrojan` command through its real entry point (a subprocess, as a user runs it)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from seqtrojan.cli import main
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


def test_evaluate_analyze_defend_and_zoo_commands_on_tiny_models(tmp_path):
    """Every downstream command through the entry point, on agents trained for a few thousand steps."""
    train = ["train", "--config", str(ROOT / "configs" / "smoke.yaml"), "--run.out-dir", str(tmp_path),
             "--ppo.total-steps", "4096", "--run.no-progress", "--agent.lstm-sizes", "16", "8"]  # fmt: skip
    assert seqtrojan(*train, "--run.name", "clean").returncode == 0
    out = seqtrojan(*train, "--run.name", "backdoor", "--backdoor.enabled", "--backdoor.eval-episodes", "16")
    assert out.returncode == 0, out.stderr
    clean, backdoor = tmp_path / "clean" / "model", tmp_path / "backdoor" / "model"
    assert json.loads((backdoor / "card.json").read_text())["label"] == "backdoored"

    out = seqtrojan("evaluate", "--models", str(clean), str(backdoor), "--configs", "7x7/0,9x9/4",
                    "--episodes", "16", "--out", str(tmp_path / "eval"))  # fmt: skip
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    cells = {(r["agent"], r["env"]) for r in rows}
    assert cells == {("clean", "normal"), ("backdoor", "normal"), ("backdoor", "trojan")}

    out = seqtrojan(
        "analyze", "--clean", str(clean), "--backdoor", str(backdoor), "--out", str(tmp_path / "analysis"),
        "--config.size", "7", "--config.holes", "2", "3", "--config.episodes", "40", "--config.trigger-step", "2",
        "--config.rule.min-episodes", "5", "--config.rule.late-start", "3", "--config.rule.late-end", "6",
        "--config.intervention-episodes", "16", "--config.unintentional-configs", "7x7/0",
        "--config.unintentional-episodes", "16", "--config.layout-search.size", "7", "--config.layout-search.holes",
        "3", "--config.layout-search.population", "4", "--config.layout-search.rollouts", "2",
        "--config.layout-search.generations", "1", "--config.layout-search.elite", "2",
        "--config.layout-search.restarts", "1", "--config.sequence-search.length", "4",
        "--config.sequence-search.restarts", "2", "--config.sequence-search.steps", "2",
        "--config.walk-search.size", "7", "--config.walk-search.length", "4", "--config.walk-search.restarts", "2",
        "--config.walk-search.steps", "2",
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "step-type units: clean" in out.stdout and (tmp_path / "analysis" / "analysis.json").exists()

    defense = tmp_path / "defense.yaml"  # --config-file sets the starting values, --config.* flags override them
    defense.write_text(
        "monitor: {calibration_episodes: 40, false_alarm_target: 0.05, eval_episodes: 64}\n"
        "mitigation: {finetune_steps: 2048, calibration_episodes: 32, eval_episodes: 16}\noracle_episodes: 40\n"
    )
    out = seqtrojan("defend", "--model", str(backdoor), "--out", str(tmp_path / "defense"), "--config-file",
                    str(defense), "--config.monitor.eval-episodes", "16")  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "monitor on" in out.stdout
    assert json.loads((tmp_path / "defense" / "defense.json").read_text())["monitor"]["episodes"] == 16

    zoo = tmp_path / "zoo"
    spec = tmp_path / "zoo.yaml"
    spec.write_text("clean: 3\nbackdoored: 3\ntotal_steps: 2048\nnum_envs: 32\neval_episodes: 16\n"
                    "lstm_sizes: [[8]]\ncurricula: [[{size: 5, holes: 0}]]\n")  # fmt: skip
    out = seqtrojan("zoo", "build", "--out", str(zoo), "--config-file", str(spec), "--workers", "1")
    assert out.returncode == 0, out.stderr
    # a corrupt model is refused, the rest goes on
    (zoo / "models" / "m0000" / "model.safetensors").write_bytes(b"not a model")
    out = seqtrojan("zoo", "detect", "--zoo", str(zoo), "--folds", "2")
    assert out.returncode == 0, out.stderr
    assert "ROC-AUC" in out.stdout and "rejected m0000" in out.stdout
    assert [h["key"] for h in json.loads((zoo / "detection.json").read_text())["held_out"]] == [
        "lstm_sizes", "trigger_value", "curriculum"]  # fmt: skip


def _options_and_help(help_text: str) -> dict[str, str]:
    """Each option of a tyro help page (printed one panel wide) -> the first line of its help text."""
    lines = [line.strip().strip("│").strip() for line in help_text.splitlines()]
    options, i = {}, 0
    while i < len(lines):
        if lines[i].startswith("-"):
            names = [lines[i]]  # a boolean's '--x, --no-x' may wrap onto a second line
            while i + 1 < len(lines) and (names[-1].endswith(",") or lines[i + 1].startswith("--")):
                i += 1
                names.append(lines[i])
            same_line = re.split(r"\s{2,}", names[-1], maxsplit=1)  # a short option's help starts on its own line
            if len(same_line) == 2:
                names[-1] = same_line[0]
                options[" ".join(names)] = same_line[1]
            else:
                options[" ".join(names)] = lines[i + 1] if i + 1 < len(lines) else ""
        i += 1
    return options


def test_train_help_lists_config_and_resume_and_every_option_has_help():
    out = subprocess.run(
        [sys.executable, "-m", "seqtrojan.cli", "train", "--help"], capture_output=True, text=True, cwd=ROOT,
        env={**os.environ, "COLUMNS": "80", "NO_COLOR": "1"}, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    options = _options_and_help(out.stdout)
    assert len(options) > 50 and "--ppo.learning-rate FLOAT" in options  # the parse found the options
    assert any(name.startswith("--config ") for name in options) and "clean_7x7" in out.stdout
    assert any(name.startswith("--resume ") for name in options)
    # tyro prints '(default: ...)' alone under an option that has no help text
    bare = [name for name, text in options.items() if not text or text.startswith("(default")]
    assert not bare, f"options without help text: {bare}"


def test_train_finds_a_shipped_preset_by_name_from_any_folder(tmp_path):
    out = seqtrojan(
        "train", "--config", "smoke", "--run.out-dir", "out", "--run.name", "r", "--ppo.total-steps", "4096",
        "--run.no-progress", cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    card = json.loads((tmp_path / "out" / "r" / "model" / "card.json").read_text())
    assert card["config"]["env"]["size"] == 5 and card["config"]["ppo"]["num_envs"] == 64  # smoke's, not defaults


MITIGATIONS_WITHOUT_TUNING = ("before", "pruned", "state_bounds", "reset_goal_units_oracle")
"""what defend reports with no fine-tuning steps (the oracle's unit reset only where goal units were found)"""


@pytest.mark.parametrize(
    ("preset", "env_id", "persistence"),
    [
        ("minigrid_two_goals", "seqtrojan/MiniGridTwoGoals-v0", "persistence k=5"),
        ("popgym_repeat_previous", "popgym-RepeatPreviousEasy-v0", "action persistence k=5"),
        ("minatar_breakout", "MinAtar/Breakout-v1", "action persistence k=5"),
    ],
)
def test_one_cli_for_every_env_from_an_empty_folder(tmp_path, capsys, monkeypatch, preset, env_id, persistence):
    """MiniGrid, POPGym and MinAtar presets through the same commands as the grid world: train, evaluate, analyze,
    defend."""
    monkeypatch.chdir(tmp_path)
    argv = ["train", "--config", preset, "--ppo.total-steps", "2048", "--run.out-dir", "R",
            "--run.name", "mg", "--run.eval-episodes", "8", "--run.no-progress"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"success on {env_id} (trojan env, 8 episodes)" in out
    card = json.loads((tmp_path / "R" / "mg" / "model" / "card.json").read_text())
    assert card["format"] == "seqtrojan-model" and card["config"]["env"]["kind"] == "gymnasium"
    assert not (tmp_path / "R" / "mg" / "model" / "gym_card.json").exists()
    assert main(["evaluate", "--models", "R/mg/model", "--episodes", "6", "--out", "E"]) == 0
    assert persistence in capsys.readouterr().out
    report = json.loads((tmp_path / "E" / "mg" / "env_evaluation.json").read_text())
    assert report["episodes"] == 6 and report["trojan_success"]["n"] == 6
    argv = ["analyze", "--backdoor", "R/mg/model", "--episodes", "6", "--intervention-episodes", "4",
            "--selection-episodes", "4", "--rule.min-episodes", "1", "--rule.response-window", "1",
            "--rule.late-start", "1", "--rule.late-end", "2", "--out", "A"]  # fmt: skip
    assert main(argv) == 0 and (tmp_path / "A" / "goal_switch.json").is_file()
    argv = ["defend", "--model", "R/mg/model", "--config.monitor.calibration-episodes", "40",
            "--config.monitor.false-alarm-target", "0.1", "--config.monitor.eval-episodes", "6",
            "--config.mitigation.finetune-steps", "0", "--config.mitigation.calibration-episodes", "8",
            "--config.mitigation.eval-episodes", "6", "--config.oracle-episodes", "10",
            "--config.mitigation.state-bounds.quantile", "0.2", "--out", "D"]  # fmt: skip
    assert main(argv) == 0
    defense = json.loads((tmp_path / "D" / "defense.json").read_text())
    assert defense["grid"] == env_id
    assert {"before", "pruned", "state_bounds"} <= set(defense["mitigation"]) <= {*MITIGATIONS_WITHOUT_TUNING}
    assert "[0.2, 0.8] quantiles" in defense["mitigation"]["state_bounds"]["title"]


def test_the_gymnasium_commands_are_folded_into_the_one_cli(capsys):
    assert main(["--help"]) == 0
    commands = re.findall(r"^  ([a-z-]+) ", capsys.readouterr().out, flags=re.M)
    assert len(commands) <= 12 and "train" in commands and "evaluate" in commands
    assert not [c for c in commands if c.startswith("gym") or c == "train-gym"]
    assert main(["train-gym"]) == 2 and "unknown command 'train-gym'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        ("env:\n  kind: atari\n", "env.kind='atari' is not one of ['grid', 'gymnasium']"),
        ("env:\n  kind: gymnasium\n  id: NoSuchEnv-v9\n", "env.id='NoSuchEnv-v9' cannot be made"),
        (
            "env:\n  kind: gymnasium\n  id: MiniGrid-MemoryS7-v0\ncurriculum:\n  stages: [{size: 5, holes: 0}]\n",
            "curriculum is a grid-world section",
        ),
        ("env:\n  id: MiniGrid-MemoryS7-v0\n", "a gymnasium section starts with kind: gymnasium"),
    ],
)
def test_bad_env_sections_are_refused_in_one_line_and_write_nothing(tmp_path, capsys, yaml_text, message):
    config = tmp_path / "bad.yaml"
    config.write_text(yaml_text)
    assert main(["train", "--config", str(config), "--run.out-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("command", ["matrix", "cells"])
def test_the_studies_explain_every_option(command):
    out = subprocess.run(
        [sys.executable, "-m", "seqtrojan.cli", command, "--help"], capture_output=True, text=True, cwd=ROOT,
        env={**os.environ, "COLUMNS": "80", "NO_COLOR": "1"}, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    options = _options_and_help(out.stdout)
    assert any(name.startswith("--workers ") for name in options)  # the parse found the options
    bare = [name for name, text in options.items() if not text or text.startswith("(default")]
    assert not bare, f"options without help text: {bare}"


def test_the_minigrid_matrix_preset_is_a_matrix_config(capsys):
    with pytest.raises(SystemExit) as code:
        main(["matrix", "--config", "matrix_minigrid_smoke", "--help"])
    assert code.value.code == 0 and "--config" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["../escaped", "a/b", "a\\b", "..", ".hidden", ""])
def test_a_run_name_must_be_a_plain_folder_name(tmp_path, capsys, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    runs = tmp_path / "out" / "runs"
    assert main(["train", "--config", "smoke", "--run.out-dir", str(runs), "--run.name", name]) == 2
    err = capsys.readouterr().err
    assert "run.name must be a plain folder name" in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == []  # nothing written, inside out_dir or beside it


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["train", "--ppo.totl-steps", "5"], "unrecognized option --ppo.totl-steps; did you mean --ppo.total-steps?"),
     (["train", "--env.hols=3"], "unrecognized option --env.hols; did you mean --env.holes?"),
     (["evaluate", "--models", "m", "--episodez", "5"], "unrecognized option --episodez; did you mean --episodes?"),
     (["import", "a.zip", "--from", "sb3", "--out", "o", "--obs-dimm", "3"], "did you mean --obs-dim?"),
     (["zoo", "detect", "--fold", "3"], "unrecognized option --fold; did you mean --folds?"),
     (["train", "--ppo.clip-coef", "0"], "ppo.clip_coef must be a number > 0, got 0.0")],
    ids=["train", "train=", "evaluate", "import", "zoo detect", "value refused while parsing"],
)  # fmt: skip
def test_a_misspelt_option_or_a_refused_value_is_named_in_one_line(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"seqtrojan {argv[0]}") and message in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["reproduce", "--out", "afile"], "--out 'afile' exists and is not a folder"),
     (["matrix", "--out", "afile"], "--out 'afile' exists and is not a folder"),
     (["cells", "--out", "afile"], "--out 'afile' exists and is not a folder"),
     (["train", "--config", "smoke", "--run.out-dir", "afile"], "cannot be created: Not a directory"),
     (["train", "--config", "smoke", "--run.out-dir", "runs", "--run.init-from", "nowhere"],
      "no card.json in 'nowhere'"),
     (["train", "--config", "smoke", "--run.out-dir", "runs", "--ppo.num-envs", "65536", "--ppo.rollout-steps",
       "4096"], "exceeds the 8 GiB a rollout buffer may take")],
    ids=["reproduce", "matrix", "cells", "train out_dir", "train init_from", "train rollout memory"],
)  # fmt: skip
def test_refused_outputs_and_configs_write_nothing(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert [p.name for p in tmp_path.iterdir()] == ["afile"]


def test_a_full_disk_while_logging_is_one_line_and_keeps_finished_work(tmp_path, monkeypatch, capsys):
    """Checkpoints and models report a full disk themselves; any other write (a log line) ends in one line too."""
    import errno

    from seqtrojan.train import logger

    calls = []
    real = logger.RunLogger.log

    def log(self, step, scalars):
        calls.append(step)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.jsonl_path))
        real(self, step, scalars)

    monkeypatch.setattr(logger.RunLogger, "log", log)
    code = main(["train", "--config", str(ROOT / "configs" / "smoke.yaml"), "--ppo.total-steps", "4096",
                 "--run.out-dir", str(tmp_path), "--run.name", "r", "--run.eval-episodes", "0",
                 "--run.no-progress"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert err.startswith("seqtrojan train: error: disk full (") and "metrics.jsonl" in err
    assert len((tmp_path / "r" / "metrics.jsonl").read_text().splitlines()) == 1  # the finished update's line
