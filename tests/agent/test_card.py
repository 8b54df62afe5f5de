"""Model cards and safetensors headers as untrusted input: the schema, the bounds and the typed result."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from safetensors.torch import save_file

from seqtrojan.agent import card as card_module
from seqtrojan.agent import checkpoint
from seqtrojan.agent.card import (
    MAX_HEADER_BYTES,
    MAX_JSON_DEPTH,
    MAX_VALUES,
    Architecture,
    ModelCard,
    load_json,
    nesting_depth,
    parse_card,
    read_card,
    read_header,
)
from seqtrojan.agent.checkpoint import build_agent, read_safetensors, save_agent
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.env import EnvConfig
from seqtrojan.errors import CheckpointError

CFG = ExperimentConfig(env=EnvConfig(size=9, holes=4), agent=AgentConfig(lstm_sizes=(16, 8)))


@pytest.fixture
def folder(tmp_path):
    torch.manual_seed(0)
    return save_agent(tmp_path / "m", build_agent(CFG), CFG, label="clean", metrics={"a": 0.5}, env_steps=7)


@pytest.mark.parametrize(
    "cfg",
    [
        CFG,
        ExperimentConfig(env=EnvConfig(view_size=5, actions="eight"), agent=AgentConfig(lstm_sizes=(64,))),
        ExperimentConfig(env=EnvConfig(actions="four_and_stay"), agent=AgentConfig(lstm_sizes=(48, 24, 12))),
    ],
)
def test_architecture_gives_the_networks_tensor_shapes_without_building_it(cfg):
    arch = Architecture(cfg.env.obs_dim, cfg.env.num_actions, cfg.agent.lstm_sizes)
    state = build_agent(cfg).state_dict()
    assert arch.tensor_shapes() == {k: tuple(v.shape) for k, v in state.items()}
    assert arch.num_parameters == sum(v.numel() for v in state.values())


def test_read_card_returns_a_typed_frozen_card(folder):
    card = read_card(folder)
    assert isinstance(card, ModelCard) and checkpoint.read_card is read_card
    assert card.label == "clean" and card.config == CFG and card.env_steps == 7 and card.metrics == {"a": 0.5}
    assert card.architecture == Architecture(CFG.env.obs_dim, CFG.env.num_actions, (16, 8))
    assert card.tensors == card.architecture.tensor_shapes()
    assert card.weights_sha256 == checkpoint.sha256_file(folder / "model.safetensors")
    assert card.data == json.loads((folder / "card.json").read_text())
    with pytest.raises(dataclasses.FrozenInstanceError):
        card.label = "backdoored"  # type: ignore[misc]


def test_save_agent_writes_the_same_card_format(folder):
    data = json.loads((folder / "card.json").read_text())
    assert list(data) == [
        "format", "format_version", "seqtrojan_version", "created", "label", "architecture", "seed", "env_steps",
        "config", "metrics", "tensors", "weights_sha256",
    ]  # fmt: skip
    assert data["format"] == "seqtrojan-model" and data["format_version"] == 1
    assert data["architecture"] == {
        "type": "RecurrentActorCritic",
        "obs_dim": 54,
        "num_actions": 4,
        "lstm_sizes": [16, 8],
    }
    assert data["tensors"]["cells.0.weight_ih"] == [64, 54] and data["seed"] == CFG.run.seed


@pytest.mark.parametrize("error", [TypeError("t"), ValueError("v"), RecursionError("r"), ZeroDivisionError("z")])
def test_any_failure_of_the_config_parser_becomes_one_checkpoint_error(folder, monkeypatch, error):
    def broken(*args, **kwargs):
        raise error

    monkeypatch.setattr(card_module, "from_dict", broken)
    with pytest.raises(CheckpointError, match=f"invalid config: {type(error).__name__}: {error}$"):
        read_card(folder)


def test_nesting_depth_ignores_brackets_inside_strings():
    assert nesting_depth(b"{}") == 1 and nesting_depth(b"1") == 0
    assert nesting_depth(b'{"a": [[1], {"b": []}]}') == 4
    assert nesting_depth(b'["[[[[", "\\"[[[", "\\\\", [[]]]') == 3  # escaped quote and backslash inside strings
    assert nesting_depth(b'["unterminated [[[[') == 1
    assert nesting_depth(b"[" * 100_000) == 100_000


def test_json_is_bounded_before_it_is_parsed():
    assert load_json(b"[" * MAX_JSON_DEPTH + b"]" * MAX_JSON_DEPTH, "x") is not None
    with pytest.raises(CheckpointError, match=f"x nests lists/objects more than {MAX_JSON_DEPTH} deep"):
        load_json(b"[" * (MAX_JSON_DEPTH + 1) + b"]" * (MAX_JSON_DEPTH + 1), "x")
    with pytest.raises(CheckpointError, match=f"more than {MAX_VALUES} values"):
        load_json(b"[" + b"[[0,0]]," * (MAX_VALUES // 2 + 1) + b"0]", "x")
    with pytest.raises(CheckpointError, match="more strings than"):
        load_json(b'{"a": "' + b'\\"' * (4 * MAX_VALUES) + b'"}', "x")
    with pytest.raises(CheckpointError, match="duplicate key 'a'"):
        load_json(b'{"a": 1, "b": {"a": 2, "a": 3}}', "x")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_json(b'{"a": "\xff"}', "x")


def test_card_text_is_parsed_with_the_same_rules(folder):
    text = (folder / "card.json").read_text()
    assert parse_card(text) == read_card(folder)
    with pytest.raises(CheckpointError, match="larger than the 1048576 bytes"):
        parse_card(text + " " * (1 << 20))


def test_header_of_what_safetensors_writes_is_accepted(tmp_path):
    tensors = {
        "w": torch.randn(3, 4, dtype=torch.float64), "rng": torch.zeros(5, dtype=torch.uint8),
        "step": torch.tensor(3.0), "empty": torch.zeros(0, 2), "idx": torch.arange(4),
    }  # fmt: skip
    path = tmp_path / "t.safetensors"
    save_file(tensors, str(path), metadata={"note": "x"})
    header = read_header(path)
    assert header.shapes == {k: list(v.shape) for k, v in tensors.items()} and header.metadata == {"note": "x"}
    assert {k: t.dtype for k, t in header.tensors.items()} == {
        "w": "F64", "rng": "U8", "step": "F32", "empty": "F32", "idx": "I64"
    }  # fmt: skip
    assert sum(t.end - t.begin for t in header.tensors.values()) == header.file_size - 8 - header.header_len
    loaded = read_safetensors(path)
    assert all(torch.equal(loaded[k], v) for k, v in tensors.items())


def _file(tmp_path, header: bytes, data: bytes = b"") -> object:
    path = tmp_path / "h.safetensors"
    path.write_bytes(len(header).to_bytes(8, "little") + header + data)
    return path


@pytest.mark.parametrize(
    ("header", "match"),
    [
        (b"[]", "not a valid safetensors"),  # must start with '{'
        (b'{"a": 1} []', "not valid JSON"),
        (b'{"a": ' + b"[" * 40 + b"]" * 40 + b"}", "nests lists/objects more than 32 deep"),
        (json.dumps({"a": {"dtype": "F32", "shape": [1] * 9, "data_offsets": [0, 4]}}).encode(), "at most 8"),
        (json.dumps({"a": {"dtype": "F32", "shape": [2], "data_offsets": [0, 4]}}).encode(), "need 8 bytes"),
        (json.dumps({"a": {"dtype": "F32", "shape": [1], "data_offsets": [4, 8]}}).encode(), "gap"),
        (json.dumps({"a": {"dtype": "F32", "shape": [1], "data_offsets": [0, 4.0]}}).encode(), "invalid data"),
    ],
)
def test_bad_headers_are_refused(tmp_path, header, match):
    with pytest.raises(CheckpointError, match=match):
        read_header(_file(tmp_path, header, b"\0" * 8))


def test_header_length_is_bounded_before_the_header_is_read(tmp_path, monkeypatch):
    path = _file(tmp_path, b"{" + b" " * MAX_HEADER_BYTES + b"}")
    reads = []
    real_open = type(path).open

    def spy_open(self, *args, **kwargs):
        fh = real_open(self, *args, **kwargs)
        real_read = fh.read
        fh.read = lambda n=-1: reads.append(n) or real_read(n)  # type: ignore[method-assign]
        return fh

    monkeypatch.setattr(type(path), "open", spy_open)
    with pytest.raises(CheckpointError, match=f"header of {MAX_HEADER_BYTES + 2} bytes, more than the limit"):
        read_header(path)
    assert reads == [9]


def test_parameter_count_bounds_the_architecture():
    arch = Architecture(54, 4, (2048, 2048, 2048))
    assert arch.num_parameters == sum(math.prod(s) for s in arch.tensor_shapes().values())
    data = json.loads(json.dumps(_card_dict(arch)))
    with pytest.raises(CheckpointError, match="parameters, more than the limit of 67108864"):
        parse_card(json.dumps(data))


def _card_dict(arch: Architecture) -> dict:
    from seqtrojan.serde import to_dict

    cfg = dataclasses.replace(CFG, agent=AgentConfig(lstm_sizes=arch.lstm_sizes))
    return {
        "format": "seqtrojan-model", "format_version": 1, "label": "clean", "weights_sha256": "0" * 64,
        "architecture": {"type": "RecurrentActorCritic", "obs_dim": arch.obs_dim, "num_actions": arch.num_actions,
                         "lstm_sizes": list(arch.lstm_sizes)},
        "config": to_dict(cfg), "tensors": {k: list(v) for k, v in arch.tensor_shapes().items()},
    }  # fmt: skip
