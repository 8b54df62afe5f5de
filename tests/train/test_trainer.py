"""The training loop's artifacts: run directory, logs, checkpoints, model card, stop and resume."""

from __future__ import annotations

import csv
import dataclasses
import errno
import json
import signal
from pathlib import Path

import pytest
import torch

from seqtrojan.agent import checkpoint as checkpoint_module
from seqtrojan.agent.checkpoint import load_agent, read_safetensors
from seqtrojan.config import BackdoorConfig, PPOConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.train import trainer as trainer_module
from seqtrojan.train.trainer import load_run_config, train, train_or_resume
from tests.train.resume import logged_rows, straight_and_resumed


def test_run_directory_holds_config_logs_checkpoints_and_model(smoke_config):
    result = train(smoke_config)
    run = result.run_dir
    assert load_run_config(run) == smoke_config
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [2048 * (i + 1) for i in range(8)]
    assert {"losses/policy_loss", "charts/steps_per_second", "curriculum/stage"} <= set(rows[-1])
    with (run / "metrics.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 8
    assert any((run / "tb").glob("events.out.tfevents.*"))
    assert (run / "checkpoints" / "latest.txt").read_text().strip() == "step_000000016384"
    _, config, card = load_agent(result.model_dir)
    assert config == smoke_config and card["label"] == "clean" and card["env_steps"] == 16384
    evaluation = json.loads((run / "evaluation.json").read_text())
    # the card's metrics are the evaluation of the saved model: re-evaluating the reloaded model gives them again
    reloaded, _, _ = load_agent(result.model_dir)
    again = trainer_module.evaluate_final(reloaded, smoke_config, torch.device("cpu"))
    assert card["metrics"]["normal_success"] == evaluation["normal_success"] == again["normal_success"]
    successes = again["normal_success"] * 200  # a count of the 200 episodes (the rate is a float32 mean)
    assert {k: card["metrics"][k] for k in again} == again and successes == pytest.approx(round(successes), abs=1e-3)
    assert evaluation["grid"] == "5x5/1" and evaluation["episodes"] == 200


def test_the_card_records_the_kernels_and_threads_that_trained_the_model(smoke_config, monkeypatch):
    """The same config and seed give other weights on the PyTorch path than on the C++ kernels, or with other
    thread counts: the card says which ran, also when the kernels could not be built and the run fell back."""
    from seqtrojan.agent import fast_lstm

    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, threads=1, name="auto"))
    card = load_agent(train(cfg).model_dir)[2]
    expected = "cpp" if fast_lstm.extension() is not None else "torch"
    assert (card["metrics"]["kernels"], card["metrics"]["torch_threads"]) == (expected, 1)
    monkeypatch.setattr(fast_lstm, "extension", lambda: None)  # a build that failed or took too long
    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name="fallback"))
    assert load_agent(train(cfg).model_dir)[2]["metrics"]["kernels"] == "torch"


def test_stopped_run_resumes_without_losing_finished_updates(smoke_config):
    seen = []

    def stop_after_three(scalars):
        seen.append(scalars["env_steps"])
        if len(seen) == 3:
            raise KeyboardInterrupt
        return False

    with pytest.raises(KeyboardInterrupt, match="resume with --resume"):
        train(smoke_config, callback=stop_after_three)
    (run,) = Path(smoke_config.run.out_dir).iterdir()
    assert (run / "checkpoints" / "latest.txt").read_text().strip() == "step_000000006144"
    saved, _, _ = load_agent(run / "checkpoints" / "step_000000006144")
    resumed_from = []
    result = train(load_run_config(run), resume=run, callback=lambda s: resumed_from.append(s["env_steps"]) or False)
    assert resumed_from[0] == 8192 and result.env_steps == 16384
    steps = [json.loads(line)["env_steps"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2048 * (i + 1) for i in range(8)]  # no duplicated and no missing rows
    state = json.loads((run / "checkpoints" / "step_000000006144" / "trainer.json").read_text())
    assert state["update"] == 3 and state["env_steps"] == 6144
    assert any(not torch.equal(a, b) for a, b in zip(saved.parameters(), load_agent(result.model_dir)[0].parameters()))


def test_train_or_resume_finishes_a_stopped_run_and_then_reuses_it(smoke_config):
    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, name="job"))
    run = Path(cfg.run.out_dir) / "job"
    calls = []

    def stop_after_two(scalars):
        calls.append(scalars["env_steps"])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return False

    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=stop_after_two)  # stopped: a checkpoint at 4096 steps, no model yet
    model, trained = train_or_resume(cfg)  # resumes from the checkpoint at 4096 steps
    assert trained and json.loads((model / "card.json").read_text())["env_steps"] == 16384
    steps = [json.loads(line)["env_steps"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2048 * (i + 1) for i in range(8)]
    mtime = (model / "card.json").stat().st_mtime
    assert train_or_resume(cfg) == (model, False) and (model / "card.json").stat().st_mtime == mtime
    fresh = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name="fresh"))
    (Path(cfg.run.out_dir) / "fresh").mkdir()
    (Path(cfg.run.out_dir) / "fresh" / "config.yaml").write_text("stopped before its first checkpoint")
    model, trained = train_or_resume(fresh)
    assert trained and load_run_config(model.parent) == fresh


def test_resume_restores_weights_and_optimizer_exactly(smoke_config, monkeypatch):
    """A run stopped by SIGTERM after 3 updates and resumed ends bitwise equal to the same run trained straight
    through: weights, Adam state (exp_avg, exp_avg_sq, step), random generators, curriculum, mixing and log rows.
    The checkpoint keeps the episodes in flight (the grid core's episode tensors and the collector's carried
    observations, states and returns), so the resumed run continues them exactly; everything else it must get from
    the checkpoint too. The curriculum promotes at update
    4 only when its window still holds the episodes of updates 1 to 3, and the backdoor's running mixing carries
    P_c and P_t across the stop."""
    cfg = dataclasses.replace(
        smoke_config,
        backdoor=BackdoorConfig(enabled=True),
        curriculum=dataclasses.replace(smoke_config.curriculum, promote_at=0.05, min_episodes=190),
        run=dataclasses.replace(smoke_config.run, eval_episodes=8),
    )

    def at_stop(run: Path) -> None:
        assert (run / "checkpoints" / "latest.txt").read_text().strip() == "step_000000006144"
        saved = read_safetensors(run / "checkpoints" / "step_000000006144" / "trainer.safetensors")
        assert int(saved["optim.0.step"]) == 3 * cfg.ppo.update_epochs * cfg.ppo.num_minibatches

    straight, resumed = straight_and_resumed(cfg, monkeypatch, at_stop)

    assert resumed.env_steps == straight.env_steps == 16384 and resumed.stage == straight.stage
    a, _, _ = load_agent(straight.model_dir)
    b, _, _ = load_agent(resumed.model_dir)
    assert a.state_dict().keys() == b.state_dict().keys()
    for name, tensor in a.state_dict().items():
        assert torch.equal(tensor, b.state_dict()[name]), name
    final = "checkpoints/step_000000016384"
    ta = read_safetensors(straight.run_dir / final / "trainer.safetensors")
    tb = read_safetensors(resumed.run_dir / final / "trainer.safetensors")
    n_params = len(list(a.parameters()))
    adam = {f"optim.{i}.{k}" for i in range(n_params) for k in ("exp_avg", "exp_avg_sq", "step")}
    in_flight = {k for k in ta if k.startswith(("env.", "collector."))}
    assert {"env.pos", "env.grid", "env.keys", "collector.obs", "collector.h.0"} <= in_flight
    assert ta.keys() == tb.keys() == adam | {"rng.collector", "rng.update"} | in_flight
    for name, tensor in ta.items():
        assert torch.equal(tensor, tb[name]), name
    assert int(ta["optim.0.step"]) == 8 * cfg.ppo.update_epochs * cfg.ppo.num_minibatches
    sa = json.loads((straight.run_dir / final / "trainer.json").read_text())
    sb = json.loads((resumed.run_dir / final / "trainer.json").read_text())
    for key in ("env_steps", "update", "curriculum", "mixing", "optimizer_param_groups"):
        assert sa[key] == sb[key], key

    logged = logged_rows(resumed.run_dir)
    assert [r["env_steps"] for r in logged] == [2048 * (i + 1) for i in range(8)]  # no duplicates, none missing
    assert [r["update"] for r in logged] == list(range(1, 9))
    assert logged == logged_rows(straight.run_dir)
    # promoted at update 4, the first after the stop, on the window of updates 1-4 (205 normal and 198 trojan
    # episodes of stage 0 against min_episodes 190): update 4's own 64 and 48 would be too few without the
    # pre-stop episodes the checkpoint carries
    assert [r["curriculum/stage"] for r in logged] == [0, 0, 0, 1, 1, 1, 1, 1]


def test_backdoored_run_is_labelled_and_evaluated_in_both_envs(smoke_config):
    cfg = dataclasses.replace(smoke_config, backdoor=BackdoorConfig(enabled=True, mixing="exact", eval_episodes=16))
    result = train(cfg)
    _, _, card = load_agent(result.model_dir)
    assert card["label"] == "backdoored"
    assert {"normal_success", "trojan_success", "greedy_trojan_success"} <= set(card["metrics"])
    for line in (result.run_dir / "metrics.jsonl").read_text().splitlines():
        row = json.loads(line)  # Algorithm 1 on the exact re-measurements (16 episodes each) logged beside it
        p_c, p_t = row["mixing/P_c"], row["mixing/P_t"]
        assert (p_c * 16).is_integer() and (p_t * 16).is_integer(), row
        assert row["mixing/p_trojan"] == min(1.0, max(0.0, 0.5 - (p_t - p_c))), row


def test_a_model_fine_tuned_from_a_backdoored_one_keeps_its_label_through_a_resume(smoke_config):
    backdoored = _short_run(dataclasses.replace(smoke_config, backdoor=BackdoorConfig(enabled=True)), "planted", 2048)
    starts = {
        "backdoored": train(backdoored).model_dir,
        "clean": train(_short_run(smoke_config, "clean", 2048)).model_dir,
    }
    for label, start in starts.items():
        cfg = _short_run(smoke_config, f"tuned_{label}", 6144)  # no backdoor of its own: the defender's fine-tuning
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, init_from=str(start), checkpoint_every=2048))
        updates: list[int] = []

        def stop_after_two(scalars, updates=updates):
            updates.append(scalars["env_steps"])
            if len(updates) == 2:
                raise KeyboardInterrupt
            return False

        with pytest.raises(KeyboardInterrupt):
            train(cfg, callback=stop_after_two)
        run = Path(cfg.run.out_dir) / cfg.run.name
        assert load_agent(run / "checkpoints" / "step_000000004096")[2]["label"] == label
        result = train(load_run_config(run), resume=run)  # the label comes from the checkpoint
        assert load_agent(result.model_dir)[2]["label"] == label


def test_existing_run_directory_is_not_overwritten(smoke_config):
    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, name="fixed"))
    train(dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=2048)))
    with pytest.raises(ConfigError, match="already holds a run"):
        train(cfg)


def test_bad_training_configs_are_refused(smoke_config):
    with pytest.raises(ConfigError, match="bptt_length=24 must divide"):
        PPOConfig(rollout_steps=64, bptt_length=24)
    with pytest.raises(ConfigError, match="num_minibatches=3 must divide"):
        PPOConfig(num_envs=64, rollout_steps=32, num_minibatches=3)
    if not torch.cuda.is_available():
        cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, device="cuda"))
        with pytest.raises(ConfigError, match="no CUDA device"):
            train(cfg)


def _short_run(smoke_config, name: str, total_steps: int):
    return dataclasses.replace(
        smoke_config,
        ppo=dataclasses.replace(smoke_config.ppo, total_steps=total_steps),
        run=dataclasses.replace(smoke_config.run, name=name, eval_episodes=8),
    )


def test_a_fresh_start_after_a_kill_before_the_first_checkpoint_rewrites_the_logs(smoke_config):
    cfg = _short_run(smoke_config, "job", 8192)  # checkpoint_every 8192: none before the end
    run = Path(cfg.run.out_dir) / "job"

    class Killed(Exception):
        """Stands for SIGKILL: the process ends where it is, writing nothing more."""

    def killed_after_two(scalars):
        if scalars["update"] == 2:
            raise Killed
        return False

    sigterm = signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(Killed):
            train(cfg, callback=killed_after_two)
    finally:
        signal.signal(signal.SIGTERM, sigterm)  # the killed "process" would not have left its handler behind
    assert not (run / "checkpoints").exists() and len((run / "metrics.jsonl").read_text().splitlines()) == 2

    train(cfg)  # the same name again: no checkpoint, so a fresh start
    steps = [json.loads(line)["env_steps"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2048, 4096, 6144, 8192]
    with (run / "metrics.csv").open() as fh:
        assert [int(r["env_steps"]) for r in csv.DictReader(fh)] == steps
    assert len(list((run / "tb").glob("events.out.tfevents.*"))) == 1


def test_an_override_given_on_resume_is_saved_in_the_runs_config_yaml(smoke_config, capsys):
    from seqtrojan.cli import main

    cfg = _short_run(smoke_config, "short", 4096)
    run = train(cfg).run_dir
    assert main(["train", "--resume", str(run), "--ppo.total-steps", "8192"]) == 0
    extended = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=8192))
    _, card_config, card = load_agent(run / "model")
    assert card["env_steps"] == 8192 and card_config == extended
    assert load_run_config(run) == extended  # what a later resume starts from


def test_a_cuda_index_past_the_available_devices_is_refused_before_anything_is_written(smoke_config, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    cfg = dataclasses.replace(smoke_config, run=dataclasses.replace(smoke_config.run, device="cuda:3"))
    with pytest.raises(ConfigError, match=r"run\.device='cuda:3' but only 1 CUDA device\(s\) are available"):
        train(cfg)
    assert not Path(cfg.run.out_dir).exists()


def test_an_unknown_mixing_rule_is_refused_before_the_run_folder_exists(tmp_path, smoke_config):
    run = dataclasses.replace(smoke_config.run, out_dir=str(tmp_path), name="refused")
    cfg = dataclasses.replace(smoke_config, backdoor=BackdoorConfig(enabled=True, mixing="halves"), run=run)
    with pytest.raises(ConfigError, match=r"unknown mixing 'halves'; known: exact, running, fixed"):
        train(cfg)
    assert not (tmp_path / "refused").exists()


@pytest.mark.parametrize("fails", ["trainer.safetensors", "model.safetensors"])
def test_a_full_disk_is_one_line_and_keeps_the_previous_checkpoint(smoke_config, monkeypatch, fails):
    cfg = dataclasses.replace(
        smoke_config, ppo=dataclasses.replace(smoke_config.ppo, total_steps=1024, num_envs=16, rollout_steps=32,
                                              num_minibatches=1, update_epochs=1),
        run=dataclasses.replace(smoke_config.run, name="r", checkpoint_every=512, eval_episodes=0),
    )  # fmt: skip
    module = trainer_module if fails == "trainer.safetensors" else checkpoint_module
    real, calls = module.save_file, []

    def save_file(tensors, path):
        calls.append(path)
        if len(calls) == 2:
            Path(path).write_bytes(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        real(tensors, path)

    monkeypatch.setattr(module, "save_file", save_file)
    message = r"^disk full while writing the (checkpoint|model) '.*': No space left"
    with pytest.raises(CheckpointError, match=message) as e:
        train(cfg)
    assert "\n" not in str(e.value)
    checkpoints = Path(cfg.run.out_dir) / "r" / "checkpoints"
    latest = (checkpoints / "latest.txt").read_text().strip()
    assert sorted(p.name for p in checkpoints.iterdir()) == ["latest.txt", latest]  # the partial one is gone
    assert not list(checkpoints.rglob("*.tmp"))
    load_agent(checkpoints / latest)  # the previous checkpoint is whole
