"""The conv encoder's layers take a kernel size and a stride (``agent.conv_kernels``, ``agent.conv_strides``): the
Nature CNN of Atari agents builds and is recorded in its card; the defaults (2x2, stride 1) build, save and load
exactly what earlier versions did; a bad kernel or stride is refused in one line, from a config and from a card."""

from __future__ import annotations

import copy
import json

import pytest
import torch

from seqtrojan.agent.card import Architecture, parse_card
from seqtrojan.agent.checkpoint import architecture_of, build_agent, load_agent, save_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.world import GymnasiumEnvConfig

NATURE = dict(conv=(32, 64, 64), conv_kernels=(8, 4, 3), conv_strides=(4, 2, 1), encoder=(512,), lstm_sizes=(128,))
ATARI_IMAGE = (84, 84, 1)


def atari_config(**agent) -> ExperimentConfig:
    env = GymnasiumEnvConfig(id="ALE/Breakout-v5", observation="image")
    return ExperimentConfig(env=env, agent=AgentConfig(**{**NATURE, **agent}))


def nature_architecture() -> Architecture:
    return Architecture.of_config(atari_config(), 84 * 84, 4, ATARI_IMAGE)


def test_the_nature_cnn_builds_with_its_kernels_and_strides_and_its_card_gives_its_shapes():
    torch.manual_seed(0)
    arch = nature_architecture()
    agent = build_agent(atari_config(), arch)
    shapes = {k: tuple(v.shape) for k, v in agent.state_dict().items()}
    assert shapes["conv.0.weight"] == (32, 1, 8, 8) and shapes["conv.1.weight"] == (64, 32, 4, 4)
    assert shapes["conv.2.weight"] == (64, 64, 3, 3) and shapes["encoder.0.weight"] == (512, 64 * 7 * 7)
    assert [(c.stride, c.padding) for c in agent.conv] == [((4, 4), (0, 0)), ((2, 2), (0, 0)), ((1, 1), (0, 0))]
    assert arch.tensor_shapes() == shapes and arch.num_parameters == sum(v.numel() for v in agent.state_dict().values())
    assert architecture_of(agent) == arch
    card = arch.to_card()
    assert card["conv"] == [32, 64, 64] and card["image"] == [84, 84, 1]
    assert card["conv_kernels"] == [8, 4, 3] and card["conv_strides"] == [4, 2, 1]
    out = agent.unroll(torch.rand(3, 2, 84 * 84), agent.initial_state(2), torch.zeros(3, 2, dtype=torch.bool))
    assert out.logits.shape == (3, 2, 4) and out.values.shape == (3, 2)


def test_the_nature_cnn_saves_and_loads_with_its_geometry(tmp_path):
    torch.manual_seed(1)
    cfg = atari_config()
    agent = build_agent(cfg, nature_architecture())
    folder = save_agent(tmp_path / "m", agent, cfg, label="clean")
    loaded, saved, card = load_agent(folder)
    assert saved.agent == cfg.agent and loaded.conv_kernels == (8, 4, 3) and loaded.conv_strides == (4, 2, 1)
    assert card["architecture"]["conv_strides"] == [4, 2, 1]
    obs = torch.rand(2, 84 * 84)
    with torch.no_grad():
        a = agent.step(obs, agent.initial_state(2))
        b = loaded.step(obs, loaded.initial_state(2))
    assert torch.equal(a.logits, b.logits) and torch.equal(a.value, b.value)


def test_the_defaults_build_and_record_exactly_what_earlier_versions_did():
    image = (5, 5, 20)
    torch.manual_seed(3)
    plain = RecurrentActorCritic(500, 3, (16,), conv=(8, 16), image=image)
    torch.manual_seed(3)
    spelled = RecurrentActorCritic(500, 3, (16,), conv=(8, 16), image=image, conv_kernels=(2, 2), conv_strides=(1, 1))
    assert plain.conv_kernels == (2, 2) and plain.conv_strides == (1, 1)
    assert plain.state_dict().keys() == spelled.state_dict().keys()
    assert all(torch.equal(v, spelled.state_dict()[k]) for k, v in plain.state_dict().items())
    assert tuple(plain.conv[1].weight.shape) == (16, 8, 2, 2) and plain.cells[0].input_size == 3 * 3 * 16
    arch = architecture_of(plain)
    assert arch == Architecture(500, 3, (16,), conv=(8, 16), image=image)  # the defaults written out either way
    assert arch.to_card() == {"type": "RecurrentActorCritic", "obs_dim": 500, "num_actions": 3, "lstm_sizes": [16],
                              "conv": [8, 16], "image": [5, 5, 20]}  # fmt: skip
    assert "conv_kernels" not in AgentConfig(conv=(8, 16)).serde_dump()  # the saved config as before


@pytest.mark.parametrize(
    ("agent", "message"),
    [
        (dict(conv=(8,), conv_kernels=(0,)), r"agent\.conv_kernels must be one integer in \[1, 32\]"),
        (dict(conv=(8,), conv_kernels=(33,)), r"agent\.conv_kernels must be one integer in \[1, 32\]"),
        (dict(conv=(8,), conv_kernels=(2, 2)), r"per agent\.conv layer \(1\)"),
        (dict(conv=(8,), conv_strides=(17,)), r"agent\.conv_strides must be one integer in \[1, 16\]"),
        (dict(conv=(8,), conv_strides=(True,)), r"agent\.conv_strides must be"),
        (dict(conv_kernels=(3,)), r"per agent\.conv layer \(0\)"),
    ],
)
def test_a_bad_kernel_or_stride_in_a_config_is_refused_in_one_line(agent, message):
    with pytest.raises(ConfigError, match=message) as err:
        AgentConfig(**agent)
    assert "\n" not in str(err.value)


def test_conv_layers_that_do_not_fit_the_image_are_refused():
    with pytest.raises(ConfigError, match=r"kernels \[6\] and strides \[1\] do not fit the 5x5 image"):
        RecurrentActorCritic(25, 3, (8,), conv=(4,), image=(5, 5, 1), conv_kernels=(6,))
    with pytest.raises(ConfigError, match=r"do not fit the 10x10 image"):
        RecurrentActorCritic(100, 3, (8,), conv=(4, 4), image=(10, 10, 1), conv_kernels=(4, 4), conv_strides=(4, 1))
    with pytest.raises(ConfigError, match="each 2x2 layer shrinks the 5x5 image by one, so at most 4 layers"):
        RecurrentActorCritic(500, 3, (16,), conv=(4, 4, 4, 4, 4), image=(5, 5, 20))
    with pytest.raises(ConfigError, match=r"conv kernels \[8\]: one integer per conv layer \(2 layers\)"):
        RecurrentActorCritic(7056, 3, (16,), conv=(4, 4), image=ATARI_IMAGE, conv_kernels=(8,))


def _nature_card() -> dict:
    cfg = atari_config()
    arch = nature_architecture()
    from seqtrojan.serde import to_dict

    return {
        "format": "seqtrojan-model", "format_version": 1, "label": "clean", "weights_sha256": "0" * 64,
        "architecture": arch.to_card(), "config": to_dict(cfg),
        "tensors": {k: list(v) for k, v in arch.tensor_shapes().items()},
    }  # fmt: skip


def test_a_card_records_the_geometry_and_parses_back_to_the_same_architecture():
    assert parse_card(json.dumps(_nature_card())).architecture == nature_architecture()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"conv_kernels": [8, 4, 99]}, r"architecture\.conv_kernels\[2\]"),
        ({"conv_strides": [4, 0, 1]}, r"architecture\.conv_strides\[1\]"),
        ({"conv_kernels": [8, 4]}, r"architecture\.conv_kernels must list one integer per conv layer \(3\)"),
        ({"conv_strides": "4,2,1"}, r"architecture\.conv_strides must list one integer per conv layer"),
        ({"conv_kernels": [8, 4, 30]}, r"leave a row and a column after conv kernels \[8, 4, 30\], strides"),
        ({"conv_strides": [16, 16, 16]}, r"leave a row and a column after conv kernels"),
    ],
)
def test_a_card_with_a_bad_kernel_or_stride_is_refused_in_one_line(change, message):
    card = copy.deepcopy(_nature_card())
    card["architecture"].update(change)
    with pytest.raises(CheckpointError, match=message) as err:
        parse_card(json.dumps(card))
    assert "\n" not in str(err.value)


def test_a_card_whose_geometry_disagrees_with_its_config_is_refused():
    card = copy.deepcopy(_nature_card())
    card["architecture"]["conv_strides"] = [4, 2, 2]  # fits (84 -> 20 -> 9 -> 4), but the config says 4, 2, 1
    with pytest.raises(CheckpointError, match="disagrees with its config"):
        parse_card(json.dumps(card))
    card = copy.deepcopy(_nature_card())
    del card["architecture"]["conv_kernels"]  # absent: 2x2, which the config does not say
    with pytest.raises(CheckpointError, match="disagrees with its config"):
        parse_card(json.dumps(card))
