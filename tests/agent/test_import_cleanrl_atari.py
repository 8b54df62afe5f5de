"""Importing CleanRL's actual Atari LSTM agent (``ppo_atari_lstm.py``: the Nature CNN, an LSTM of 128, actor and
critic): its state dict maps onto our network exactly, which gives the same logits and values on the same frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.imports import import_agent, read_cleanrl
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml

ATARI_IMAGE = (84, 84, 1)
OBS_DIM = 84 * 84


def layer_init(layer, std=np.sqrt(2), bias_const=0.0):  # noqa: B008 (CleanRL's own signature)
    """CleanRL's ``layer_init``."""
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class CleanRLAtariAgent(nn.Module):
    """CleanRL's ``ppo_atari_lstm.py`` ``Agent``, as it defines it (``envs.single_action_space.n`` given as
    ``actions``)."""

    def __init__(self, actions: int):
        super().__init__()
        self.network = nn.Sequential(
            layer_init(nn.Conv2d(1, 32, 8, stride=4)),
            nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)),
            nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)),
            nn.ReLU(),
            nn.Flatten(),
            layer_init(nn.Linear(64 * 7 * 7, 512)),
            nn.ReLU(),
        )
        self.lstm = nn.LSTM(512, 128)
        for name, param in self.lstm.named_parameters():
            if "bias" in name:
                nn.init.constant_(param, 0)
            elif "weight" in name:
                nn.init.orthogonal_(param, 1.0)
        self.actor = layer_init(nn.Linear(128, actions), std=0.01)
        self.critic = layer_init(nn.Linear(128, 1), std=1)

    def get_states(self, x, lstm_state, done):
        hidden = self.network(x / 255.0)

        # LSTM logic
        batch_size = lstm_state[0].shape[1]
        hidden = hidden.reshape((-1, batch_size, self.lstm.input_size))
        done = done.reshape((-1, batch_size))
        new_hidden = []
        for h, d in zip(hidden, done):
            h, lstm_state = self.lstm(
                h.unsqueeze(0),
                (
                    (1.0 - d).view(1, -1, 1) * lstm_state[0],
                    (1.0 - d).view(1, -1, 1) * lstm_state[1],
                ),
            )
            new_hidden += [h]
        new_hidden = torch.flatten(torch.cat(new_hidden), 0, 1)
        return new_hidden, lstm_state


def trained_looking(actions: int, seed: int = 0) -> CleanRLAtariAgent:
    """CleanRL's agent with every parameter moved off its initial value (zero biases included), so that every
    tensor's mapping shows in the outputs."""
    torch.manual_seed(seed)
    agent = CleanRLAtariAgent(actions)
    with torch.no_grad():
        for p in agent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return agent


def frames(steps: int, batch: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """uint8 frames (T, B, 1, 84, 84) as CleanRL's envs give them (``FrameStack(1)``: channel first), moving blobs on
    noise, and episode starts (T, B) with resets in the middle."""
    rng = np.random.default_rng(seed)
    out = rng.integers(0, 60, size=(steps, batch, 1, 84, 84), dtype=np.uint8)
    for t in range(steps):
        for b in range(batch):
            r, c = (7 * t + 11 * b) % 76, (5 * t + 3 * b) % 76
            out[t, b, 0, r : r + 8, c : c + 8] = 200 + (t % 50)
    starts = rng.random((steps, batch)) < 0.1
    starts[0] = True
    return out, starts


def cleanrl_outputs(agent: CleanRLAtariAgent, x: np.ndarray, starts: np.ndarray):
    """Logits (T, B, A) and values (T, B) from CleanRL's own forward, one step at a time as its rollout does."""
    batch = x.shape[1]
    state = (torch.zeros(1, batch, 128), torch.zeros(1, batch, 128))
    logits, values = [], []
    with torch.no_grad():
        for t in range(x.shape[0]):
            hidden, state = agent.get_states(torch.Tensor(x[t]), state, torch.Tensor(starts[t].astype(np.float32)))
            logits.append(agent.actor(hidden))
            values.append(agent.critic(hidden).squeeze(-1))
    return torch.stack(logits), torch.stack(values)


def our_outputs(agent, x: np.ndarray, starts: np.ndarray, unroll: bool = False):
    """Our network on the same frames as the Atari family gives them: (84, 84, 1) scaled to [0, 1] (Gymnasium's
    ``AtariPreprocessing(scale_obs=True)``: float32 / 255), flattened."""
    obs = torch.as_tensor(np.asarray(x, dtype=np.float32) / 255.0).reshape(x.shape[0], x.shape[1], -1)
    done = torch.as_tensor(starts)
    with torch.no_grad():
        if unroll:
            out = agent.unroll(obs, agent.initial_state(x.shape[1]), done)
            return out.logits, out.values
        state, logits, values = agent.initial_state(x.shape[1]), [], []
        for t in range(x.shape[0]):
            step = agent.step(obs[t], state, done[t])
            state = step.state
            logits.append(step.logits)
            values.append(step.value)
    return torch.stack(logits), torch.stack(values)


def needs_atari() -> None:
    """The import for the Atari presets makes their env once (its spaces): ale-py and OpenCV."""
    pytest.importorskip("ale_py", reason="the Atari family needs pip install 'seqtrojan[atari]'")
    pytest.importorskip("cv2", reason="the Atari family needs pip install 'seqtrojan[atari]'")


def test_cleanrls_atari_lstm_agent_imports_exactly(tmp_path):
    needs_atari()
    original = trained_looking(actions=4)
    path = tmp_path / "ppo_atari_lstm.cleanrl_model"
    torch.save(original.state_dict(), path)
    imported = read_cleanrl(path, OBS_DIM, 4, image=ATARI_IMAGE)
    assert imported.agent == AgentConfig(
        lstm_sizes=(128,), encoder=(512,), conv=(32, 64, 64), conv_kernels=(8, 4, 3), conv_strides=(4, 2, 1)
    )
    assert imported.value == "imported" and imported.details["conv_strides"] == [4, 2, 1]
    cfg = from_dict(ExperimentConfig, load_yaml(resolve_preset("atari_breakout")), "")
    out = import_agent("cleanrl", path, tmp_path / "m", config=cfg, obs_dim=OBS_DIM, num_actions=4)
    agent, loaded, card = load_agent(out)
    assert loaded.agent == imported.agent and card["architecture"]["conv_kernels"] == [8, 4, 3]
    assert card["architecture"]["image"] == [84, 84, 1] and card["label"] == "unknown"
    x, starts = frames(steps=24, batch=3, seed=1)
    assert starts[1:].any()  # resets inside the sequence
    want_logits, want_values = cleanrl_outputs(original, x, starts)
    for backend in ("torch", "auto"):  # the plain and the fused C++ LSTM kernels
        agent.set_lstm_backend(backend)
        for unroll in (False, True):
            logits, values = our_outputs(agent, x, starts, unroll)
            assert float((logits - want_logits).abs().max()) < 1e-5
            assert float((values - want_values).abs().max()) < 1e-5
            assert torch.equal(logits.argmax(-1), want_logits.argmax(-1))


def test_the_import_command_reads_a_cleanrl_atari_agent_for_the_atari_preset(tmp_path, capsys):
    from seqtrojan.cli import main

    needs_atari()
    path = tmp_path / "agent.pt"
    torch.save(trained_looking(actions=6, seed=2).state_dict(), path)
    argv = ["import", str(path), "--from", "cleanrl", "--obs-dim", str(OBS_DIM), "--actions", "6", "--config",
            "atari_pong", "--out", str(tmp_path / "pong")]  # fmt: skip
    assert main(argv) == 0
    assert "conv_kernels=[8, 4, 3], conv_strides=[4, 2, 1]" in capsys.readouterr().out
    card = json.loads((tmp_path / "pong" / "card.json").read_text())
    assert card["config"]["env"]["id"] == "ALE/Pong-v5" and card["provenance"]["imported_from"] == "cleanrl"


def test_a_cleanrl_cnn_is_refused_in_one_line_where_it_does_not_fit(tmp_path):
    path = tmp_path / "agent.pt"
    sd = trained_looking(actions=4).state_dict()
    torch.save(sd, path)
    cases = [
        (dict(image=None), CheckpointError, "a CNN agent reads an image; pass --config"),
        (dict(image=(84, 84, 4), obs_dim=4 * OBS_DIM), CheckpointError, "network.0 reads 1 channels, but the env"),
        (dict(image=(42, 42, 1), obs_dim=42 * 42), CheckpointError, r"network.7 has weight \[512, 3136\].*from 64"),
        (dict(conv_strides=(4, 2)), ConfigError, "one integer in"),
        (dict(conv_strides=(2, 2, 1)), CheckpointError, r"network.7 has weight \[512, 3136\].*do not chain from"),
    ]
    for changes, error, message in cases:
        options = {"image": ATARI_IMAGE, "obs_dim": OBS_DIM, **changes}
        obs_dim = options.pop("obs_dim")
        with pytest.raises(error, match=message) as err:
            read_cleanrl(path, obs_dim, 4, **options)
        assert "\n" not in str(err.value)
    odd = dict(sd)
    odd["network.2.weight"] = torch.zeros(64, 32, 4, 3)  # not a square kernel
    torch.save(odd, path)
    with pytest.raises(CheckpointError, match=r"network.2 has weight \[64, 32, 4, 3\].*square kernel"):
        read_cleanrl(path, OBS_DIM, 4, image=ATARI_IMAGE)
    other = {k.replace("network.7.", "network.9."): v for k, v in sd.items()}  # a Linear where none belongs
    torch.save(other, path)
    with pytest.raises(CheckpointError, match=r"the layers under network sit at \[0, 2, 4, 9\]"):
        read_cleanrl(path, OBS_DIM, 4, image=ATARI_IMAGE)
    small = nn.Sequential(nn.Conv2d(1, 8, 5, stride=3), nn.ReLU(), nn.Flatten(), nn.Linear(8 * 27 * 27, 16), nn.ReLU())
    lstm = nn.LSTM(16, 8)
    custom = {**{f"network.{k}": v for k, v in small.state_dict().items()},
              **{f"lstm.{k}": v for k, v in lstm.state_dict().items()},
              "actor.weight": torch.zeros(4, 8), "actor.bias": torch.zeros(4), "critic.weight": torch.zeros(1, 8),
              "critic.bias": torch.zeros(1)}  # fmt: skip
    torch.save(custom, path)
    with pytest.raises(ConfigError, match=r"not CleanRL's Nature CNN .* pass --conv-strides"):
        read_cleanrl(path, OBS_DIM, 4, image=ATARI_IMAGE)
    assert read_cleanrl(path, OBS_DIM, 4, image=ATARI_IMAGE, conv_strides=(3,)).agent.conv_strides == (3,)
