"""Model files: safetensors + JSON card round trip; pickles, corrupt files and mismatched cards are refused."""

from __future__ import annotations

import json
import pickle

import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent, load_agent, save_agent
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.env import EnvConfig
from seqtrojan.errors import CheckpointError

CFG = ExperimentConfig(env=EnvConfig(size=9, holes=4), agent=AgentConfig(lstm_sizes=(16, 8)))


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(0)
    agent = build_agent(CFG)
    folder = save_agent(tmp_path / "m", agent, CFG, label="backdoored", metrics={"x": 1.0}, env_steps=42)
    return agent, folder


def test_round_trip_restores_weights_config_and_card(saved):
    agent, folder = saved
    loaded, config, card = load_agent(folder)
    assert config == CFG
    assert card["label"] == "backdoored" and card["env_steps"] == 42 and card["metrics"] == {"x": 1.0}
    assert card["architecture"]["lstm_sizes"] == [16, 8]
    obs = torch.randn(3, CFG.env.obs_dim)
    a = agent.step(obs, agent.initial_state(3)).logits
    b = loaded.step(obs, loaded.initial_state(3)).logits
    torch.testing.assert_close(a, b)


def test_pickled_files_are_refused(tmp_path, saved):
    agent, folder = saved
    pt = tmp_path / "model.pt"
    torch.save(agent.state_dict(), pt)
    with pytest.raises(CheckpointError, match="pickled"):
        load_agent(pt)
    (folder / "model.safetensors").write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(CheckpointError, match="pickle"):
        load_agent(folder)
    torch.save(agent.state_dict(), folder / "model.safetensors")  # a torch zip under the right name
    with pytest.raises(CheckpointError, match="pickle/zip"):
        load_agent(folder)


def test_corrupt_and_truncated_weights_are_refused(saved):
    _, folder = saved
    data = (folder / "model.safetensors").read_bytes()
    (folder / "model.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"corrupt|truncated"):
        load_agent(folder)
    (folder / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="not a valid safetensors"):
        load_agent(folder)


def test_card_that_does_not_match_its_weights_is_refused(saved):
    _, folder = saved
    card = json.loads((folder / "card.json").read_text())
    card["tensors"]["cells.0.weight_hh"] = [32, 16]
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=r"cells.0.weight_hh.*shape \[64, 16\] but the card says \[32, 16\]"):
        load_agent(folder)


def test_weights_swapped_after_the_card_was_written_are_refused(saved, tmp_path):
    _, folder = saved
    torch.manual_seed(1)
    other = save_agent(tmp_path / "other", build_agent(CFG), CFG, label="clean")
    (folder / "model.safetensors").write_bytes((other / "model.safetensors").read_bytes())
    with pytest.raises(CheckpointError, match="SHA-256"):
        load_agent(folder)


def test_missing_or_foreign_cards_are_refused(saved, tmp_path):
    _, folder = saved
    with pytest.raises(CheckpointError, match=r"no card\.json"):
        load_agent(tmp_path)
    (folder / "card.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_agent(folder)
    (folder / "card.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(CheckpointError, match="not a seqtrojan model card"):
        load_agent(folder)


def test_config_in_card_is_checked(saved):
    _, folder = saved
    card = json.loads((folder / "card.json").read_text())
    card["config"]["env"]["size"] = 8
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=r"invalid config.*size=8"):
        load_agent(folder)
