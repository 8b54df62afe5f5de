"""Model folders and stopped runs written by an earlier seqtrojan (tests/fixtures/legacy/, see its README) load and
resume with today's code: the grid world's card, the Gymnasium runs' ``gym_card.json`` and their run folders (the
old config layout, the old checkpoint's tensors). A legacy card is untrusted input like any other: a tampered one is
refused. And the ``env:`` section's tag: a Gymnasium env takes no grid-world section, an unknown kind is refused."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent, save_agent
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.evaluation.batched import evaluate_on_env
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train.trainer import load_run_config, train
from seqtrojan.world.config import GymnasiumEnvConfig, upgrade_gym_train_layout

LEGACY = Path(__file__).resolve().parent / "fixtures" / "legacy"


@pytest.mark.parametrize(
    ("folder", "kind", "env_id", "label", "architecture"),
    [
        ("grid_lstm", "grid", None, "backdoored", {"obs_dim": 54, "num_actions": 4, "lstm_sizes": [8, 4]}),
        (
            "gym_two_goals", "gymnasium", "seqtrojan/MiniGridTwoGoals-v0", "backdoored",
            {"obs_dim": 500, "num_actions": 3, "lstm_sizes": [8, 4]},
        ),
        (
            "gym_memory_gru_conv", "gymnasium", "MiniGrid-MemoryS7-v0", "clean",
            {"obs_dim": 980, "num_actions": 3, "lstm_sizes": [8], "cell": "gru", "conv": [4], "image": [7, 7, 20]},
        ),
    ],
)  # fmt: skip
def test_every_legacy_model_folder_loads(folder, kind, env_id, label, architecture):
    agent, cfg, card = load_agent(LEGACY / folder)
    assert card["format"] == "seqtrojan-model" and card["label"] == label and cfg.label == label
    assert card["architecture"] == {"type": "RecurrentActorCritic", **architecture}
    assert (agent.obs_dim, agent.num_actions, agent.lstm_sizes) == (
        architecture["obs_dim"], architecture["num_actions"], tuple(architecture["lstm_sizes"]),
    )  # fmt: skip
    if kind == "grid":
        assert cfg.is_grid and isinstance(cfg.env, EnvConfig) and (cfg.env.obs_dim, cfg.env.num_actions) == (54, 4)
    else:
        assert not cfg.is_grid and isinstance(cfg.env, GymnasiumEnvConfig) and cfg.gym_env.kind == "gymnasium"
        assert cfg.gym_env.id == env_id and cfg.gym_env.trigger is not None  # the old top-level trigger, moved
        assert not (LEGACY / folder / "card.json").exists()  # read as it is, never rewritten
    assert agent.cell == architecture.get("cell", "lstm") and cfg.agent.cell == agent.cell
    assert agent.conv_channels == tuple(architecture.get("conv", ())) == cfg.agent.conv
    assert agent.image == (tuple(architecture["image"]) if "image" in architecture else None)
    out = agent.step(torch.zeros(2, agent.obs_dim), agent.initial_state(2), torch.ones(2))
    assert out.logits.shape == (2, agent.num_actions) and bool(torch.isfinite(out.logits).all())


def test_a_legacy_gymnasium_model_runs_in_its_env():
    agent, cfg, _ = load_agent(LEGACY / "gym_two_goals")
    batch = evaluate_on_env(agent, cfg, trojan=True, episodes=4, seed=0, registered_only=True)
    assert batch.success.numel() == 4 and bool(batch.trojan.all())


def _copy(name: str, tmp_path: Path) -> Path:
    """A copy of a legacy run (a resume writes into its folder: never into the fixture)."""
    run_dir = tmp_path / name
    shutil.copytree(LEGACY / name, run_dir)
    return run_dir


def _resume(run_dir: Path):
    cfg = load_run_config(run_dir)
    return train(dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, progress=False)), resume=run_dir)


def test_a_legacy_grid_run_resumes_to_completion(tmp_path):
    run_dir = _copy("grid_run", tmp_path)
    cfg = load_run_config(run_dir)
    assert cfg.is_grid and cfg.ppo.total_steps == 512 and cfg.backdoor.enabled
    result = _resume(run_dir)
    assert result.exact_resume is False  # its checkpoint holds no episodes in flight: fresh ones
    assert result.env_steps == 512 and result.model_dir == run_dir / "model"
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [256, 512]  # the stopped run's row kept, one more
    _, loaded, card = load_agent(result.model_dir)
    assert loaded == load_run_config(run_dir) and card["label"] == "backdoored" and card["env_steps"] == 512
    assert result.evaluation["grid"] == "5x5/1" and {"normal_success", "trojan_success"} <= set(result.evaluation)


def test_a_legacy_gymnasium_run_resumes_exactly_to_completion(tmp_path):
    run_dir = _copy("gym_run", tmp_path)
    cfg = load_run_config(run_dir)  # the old layout: env without kind, trigger at the top
    assert cfg.gym_env.id == "seqtrojan/MiniGridTwoGoals-v0" and cfg.gym_env.trigger is not None
    assert cfg.agent.lstm_sizes == (4, 4) and cfg.ppo.total_steps == 128 and cfg.backdoor.enabled
    result = _resume(run_dir)
    assert result.exact_resume is True  # each env replayed its episode in flight from the old checkpoint
    assert result.env_steps == 128 and result.model_dir == run_dir / "model"
    assert (result.model_dir / "card.json").is_file() and not (result.model_dir / "gym_card.json").exists()
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [(r["env_steps"], r["update"]) for r in rows] == [(64, 1), (128, 2)]
    assert "kind: gymnasium" in (run_dir / "config.yaml").read_text()  # saved again in today's layout
    _, loaded, card = load_agent(result.model_dir)
    assert loaded.env == cfg.env and card["label"] == "backdoored" and card["env_steps"] == 128
    assert result.evaluation["env"] == cfg.gym_env.id and result.evaluation["episodes"] == 10
    assert not (LEGACY / "gym_run" / "model").exists()  # the fixture itself is untouched


def test_a_tampered_legacy_gym_card_naming_a_module_is_refused(tmp_path):
    folder = tmp_path / "gym_two_goals"
    shutil.copytree(LEGACY / "gym_two_goals", folder)
    card_path = folder / "gym_card.json"
    card = json.loads(card_path.read_text())
    card["config"]["env"]["id"] = "os:Foo-v0"
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=r"config\.env\.id='os:Foo-v0' would import a module") as err:
        load_agent(folder)
    assert "gym_card.json" in str(err.value) and "\n" not in str(err.value)


def test_a_card_naming_a_module_is_refused_in_todays_format_too(tmp_path):
    agent, cfg, _ = load_agent(LEGACY / "gym_two_goals")
    folder = save_agent(tmp_path / "m", agent, cfg, label="backdoored")
    assert load_agent(folder)[1] == cfg  # saved again as today's card.json
    card = json.loads((folder / "card.json").read_text())
    card["config"]["env"]["id"] = "os:Foo-v0"
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match="would import a module"):
        load_agent(folder)


def test_a_gymnasium_env_with_a_curriculum_section_is_refused():
    data = {
        "env": {"kind": "gymnasium", "id": "seqtrojan/MiniGridTwoGoals-v0"},
        "curriculum": {"stages": [{"size": 5, "holes": 0}]},
    }
    with pytest.raises(ConfigError, match=r"curriculum is a grid-world section .* drop the curriculum section"):
        from_dict(ExperimentConfig, data, "")
    del data["curriculum"]
    assert from_dict(ExperimentConfig, data, "").num_stages == 1  # without it, the config is fine


def test_env_sections_are_told_apart_by_their_kind():
    with pytest.raises(ConfigError, match=r"env\.kind='mujoco' is not one of \['grid', 'gymnasium'\]"):
        from_dict(ExperimentConfig, {"env": {"kind": "mujoco", "id": "Ant-v4"}}, "")
    with pytest.raises(ConfigError, match=r"a gymnasium section starts with kind: gymnasium"):
        from_dict(ExperimentConfig, {"env": {"id": "CartPole-v1"}}, "")  # the old layout, in a config one writes
    assert from_dict(ExperimentConfig, {"env": {"kind": "grid", "size": 9}}, "").grid_env.size == 9
    assert from_dict(ExperimentConfig, {"env": {"size": 9}}, "").env == EnvConfig(size=9)  # no kind: the grid


def test_the_old_gymnasium_layout_is_upgraded_and_nothing_else():
    old = load_yaml(LEGACY / "gym_run" / "config.yaml")
    assert "kind" not in old["env"] and "trigger" in old
    new = upgrade_gym_train_layout(old)
    assert new["env"]["kind"] == "gymnasium" and new["env"]["trigger"] == old["trigger"] and "trigger" not in new
    assert from_dict(ExperimentConfig, new, "") == load_run_config(LEGACY / "gym_run")
    grid = load_yaml(LEGACY / "grid_run" / "config.yaml")
    assert upgrade_gym_train_layout(grid) == grid and upgrade_gym_train_layout(new) == new
