"""Importing agents trained elsewhere: sb3-contrib RecurrentPPO zips and CleanRL LSTM state dicts.

The imported policy must give the original's action distribution step for step (to 1e-5), the seqtrojan tools must
run on it, and every refused file must be refused with one clear line before anything is written.
"""

from __future__ import annotations

import dataclasses
import io
import json
import pickle
import struct
import zipfile

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

import seqtrojan  # noqa: F401  (registers the gymnasium ids)
from seqtrojan.agent import imports
from seqtrojan.agent.card import Architecture, parse_card, read_card
from seqtrojan.agent.checkpoint import architecture_of, build_agent, load_agent, save_agent
from seqtrojan.agent.imports import import_agent
from seqtrojan.cli import main
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.defense.monitor import MonitorConfig, StateMonitor, measure_monitor
from seqtrojan.env import EnvConfig, GridSpec
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml, to_dict

GRID = GridSpec(5, 0)
ENV_KWARGS = {"size": 5, "holes": 0}

SB3_VARIANTS = {
    # sb3-contrib's default: a separate critic LSTM (the value is not imported)
    "separate_critic": {"lstm_hidden_size": 16, "net_arch": {"pi": [16], "vf": [16]}},
    # a shared LSTM, two layers, relu, two policy layers: every part imported exactly
    "shared": {
        "lstm_hidden_size": 12,
        "n_lstm_layers": 2,
        "shared_lstm": True,
        "enable_critic_lstm": False,
        "net_arch": {"pi": [16, 8], "vf": [8]},
        "activation_fn": nn.ReLU,
    },
    # a feed-forward critic and no MLP layers
    "linear_critic": {"lstm_hidden_size": 8, "enable_critic_lstm": False, "net_arch": []},
}


def _train_sb3(tmp_path_factory, name: str):
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env("seqtrojan/Normal-v0", n_envs=4, seed=0, env_kwargs=ENV_KWARGS)
    model = RecurrentPPO(
        "MlpLstmPolicy", venv, n_steps=32, batch_size=64, n_epochs=2, learning_rate=3e-3,
        policy_kwargs=SB3_VARIANTS[name], seed=0, device="cpu",
    )  # fmt: skip
    model.learn(256)  # two updates: weights away from their initial values, in about a second
    path = tmp_path_factory.mktemp(f"sb3_{name}") / "model.zip"
    model.save(path)
    return model, path


@pytest.fixture(scope="module")
def sb3_models(tmp_path_factory):
    """``get(variant)``: (variant, trained sb3 model, its zip, the imported model folder), each trained once."""
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            model, path = _train_sb3(tmp_path_factory, name)
            cache[name] = name, model, path, import_agent("sb3", path, path.parent / "imported", label="backdoored")
        return cache[name]

    return get


@pytest.fixture(scope="module", params=list(SB3_VARIANTS))
def sb3_model(request, sb3_models):
    return sb3_models(request.param)


@pytest.fixture(scope="module")
def sb3_default(sb3_models):
    """sb3-contrib's default layout (a separate critic LSTM)."""
    return sb3_models("separate_critic")


def _episode_observations(steps: int, batch: int, seed: int, policy=None) -> tuple[np.ndarray, np.ndarray]:
    """Observations (T, B, obs_dim) of ``batch`` envs run for ``steps`` steps (random actions), and the episode
    starts (T, B): several episodes per env, so the state is reset in the middle of the sequence."""
    envs = [gym.make("seqtrojan/Normal-v0", **ENV_KWARGS) for _ in range(batch)]
    rng = np.random.default_rng(seed)
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    all_obs, starts = [], []
    start = np.ones(batch, dtype=bool)
    for _ in range(steps):
        all_obs.append(obs.copy())
        starts.append(start.copy())
        for i, env in enumerate(envs):
            o, _, terminated, truncated, _ = env.step(int(rng.integers(4)))
            start[i] = terminated or truncated or rng.random() < 0.05  # also a few cut-short episodes
            obs[i] = env.reset()[0] if start[i] else o
    return np.stack(all_obs), np.stack(starts)


def _sb3_log_probs(model, obs: np.ndarray, starts: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """sb3's own step-by-step forward: log-probabilities (T, B, A) and values (T, B) (its critic's, from
    predict_values with the critic's own LSTM state)."""
    policy = model.policy
    policy.set_training_mode(False)
    layers, hidden = policy.lstm_hidden_state_shape[0], policy.lstm_hidden_state_shape[2]
    batch = obs.shape[1]
    pi = (torch.zeros(layers, batch, hidden), torch.zeros(layers, batch, hidden))
    vf = (torch.zeros(layers, batch, hidden), torch.zeros(layers, batch, hidden))
    logps, values = [], []
    with torch.no_grad():
        for t in range(obs.shape[0]):
            x = torch.as_tensor(obs[t])
            start = torch.as_tensor(starts[t], dtype=torch.float32)
            values.append(policy.predict_values(x, vf if policy.lstm_critic is not None else pi, start).squeeze(-1))
            if policy.lstm_critic is not None:
                _, vf = policy._process_sequence(x, vf, start, policy.lstm_critic)
            dist, pi = policy.get_distribution(x, pi, start)
            logps.append(dist.distribution.logits)  # torch's Categorical keeps normalised logits
    return torch.stack(logps), torch.stack(values)


def _our_outputs(agent, obs: np.ndarray, starts: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    state = agent.initial_state(obs.shape[1])
    logits, values = [], []
    with torch.no_grad():
        for t in range(obs.shape[0]):
            out = agent.step(torch.as_tensor(obs[t]), state, torch.as_tensor(starts[t]))
            state = out.state
            logits.append(out.logits)
            values.append(out.value)
    return torch.stack(logits), torch.stack(values)


# ---------------------------------------------------------------------- sb3: exact policy


def test_imported_sb3_agent_gives_the_same_action_distribution_step_by_step(sb3_model):
    name, model, _, out = sb3_model
    agent, _, card = load_agent(out)
    obs, starts = _episode_observations(steps=80, batch=4, seed=3)
    assert starts[1:].any()  # resets inside the sequence
    sb3_logp, sb3_values = _sb3_log_probs(model, obs, starts)
    for backend in ("torch", "auto"):  # the plain and the fused C++ LSTM kernels
        agent.set_lstm_backend(backend)
        logits, values = _our_outputs(agent, obs, starts)
        ours = torch.log_softmax(logits, -1)
        assert float((ours - sb3_logp).abs().max()) < 1e-5, (name, backend)
        with torch.no_grad():
            unrolled = agent.unroll(torch.as_tensor(obs), agent.initial_state(4), torch.as_tensor(starts))
        assert float((torch.log_softmax(unrolled.logits, -1) - sb3_logp).abs().max()) < 1e-5
        if name == "shared":  # the value is imported exactly too
            assert card["provenance"]["value"] == "imported"
            assert float((values - sb3_values).abs().max()) < 1e-5
        else:  # a separate critic is not imported: the value head is zero
            assert card["provenance"]["value"] == "zeroed"
            assert float(values.abs().max()) == 0.0


def test_imported_sb3_card_records_the_architecture_and_provenance(sb3_model):
    name, model, path, out = sb3_model
    card = read_card(out)
    kwargs = SB3_VARIANTS[name]
    layers, hidden = kwargs.get("n_lstm_layers", 1), kwargs["lstm_hidden_size"]
    arch = kwargs["net_arch"]
    pi, vf = (tuple(arch["pi"]), tuple(arch["vf"])) if isinstance(arch, dict) else (tuple(arch), tuple(arch))
    activation = "relu" if kwargs.get("activation_fn") is nn.ReLU else "tanh"
    assert card.architecture == Architecture(
        54, 4, (hidden,) * layers, policy_mlp=pi, value_mlp=vf, mlp_activation=activation
    )
    assert card.config.agent == AgentConfig(lstm_sizes=(hidden,) * layers, policy_mlp=pi, value_mlp=vf,
                                            mlp_activation=activation)  # fmt: skip
    assert card.label == "backdoored" and card.config.backdoor.enabled and card.env_steps == model.num_timesteps
    prov = card.provenance
    assert prov is not None and prov["imported_from"] == "sb3" and prov["label_stated"] is True
    assert prov["source_file"] == "model.zip" and prov["source_sha256"] == imports._sha256(path)
    assert prov["details"]["critic"] == {"separate_critic": "lstm", "shared": "shared", "linear_critic": "linear"}[name]


def test_seqtrojan_tools_run_on_an_imported_sb3_agent(sb3_default):
    _, _, _, out = sb3_default
    agent, cfg, _ = load_agent(out)
    for trojan in (False, True):
        batch = evaluate_agent(agent, cfg.env, GRID, trojan=trojan, episodes=32, seed=0)
        rate = outcome_rate(batch, "user_goal")
        assert rate.n == 32 and 0 <= rate.value <= 1
    options = MonitorConfig(calibration_episodes=40, eval_episodes=16, false_alarm_target=0.1)
    monitor = StateMonitor.calibrate(agent, cfg.env, GRID, options)
    assert [m.numel() for m in monitor.mean] == [2 * 16]
    result = measure_monitor(agent, cfg.env, GRID, monitor, options)
    assert result.episodes == 16 and result.normal_alarm.false_alarm.n == 16


def test_cli_imports_an_sb3_zip_and_evaluates_it(sb3_default, tmp_path, capsys):
    _, _, path, _ = sb3_default
    assert main(["import", str(path), "--from", "sb3", "--out", str(tmp_path / "m")]) == 0
    printed = capsys.readouterr().out
    assert "not stated" in printed and "value head: zero" in printed
    card = read_card(tmp_path / "m")
    assert card.label == "unknown" and card.provenance is not None and card.provenance["label_stated"] is False
    assert not card.config.backdoor.enabled
    code = main(["evaluate", "--models", str(tmp_path / "m"), "--configs", "5x5/0", "--episodes", "16",
                 "--out", str(tmp_path / "eval")])  # fmt: skip
    assert code == 0 and (tmp_path / "eval" / "evaluation.json").is_file()
    rows = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    # a suspect of unknown lineage is evaluated in the trojan env too; one stated clean is not
    assert {(r["label"], r["env"]) for r in rows} == {("unknown", "normal"), ("unknown", "trojan")}
    assert main(["import", str(path), "--from", "sb3", "--out", str(tmp_path / "c"), "--label", "clean"]) == 0
    assert main(["evaluate", "--models", str(tmp_path / "c"), "--configs", "5x5/0", "--episodes", "16",
                 "--out", str(tmp_path / "eval_c")]) == 0  # fmt: skip
    rows = json.loads((tmp_path / "eval_c" / "evaluation.json").read_text())
    assert {(r["label"], r["env"]) for r in rows} == {("clean", "normal")}
    assert main(["import", str(path), "--from", "sb3", "--out", str(tmp_path / "m")]) == 2  # not over a model
    assert "already exists" in capsys.readouterr().err


# ---------------------------------------------------------------------- CleanRL


class CleanRLAgent(nn.Module):
    """CleanRL's ppo_atari_lstm.py ``Agent`` with an MLP in place of the CNN."""

    def __init__(self, obs_dim: int, actions: int, encoder=(32, 24), hidden=16, layers=1, act=nn.ReLU):
        super().__init__()
        mods: list[nn.Module] = []
        for n_in, width in zip((obs_dim, *encoder[:-1]), encoder):
            mods += [nn.Linear(n_in, width), act()]
        self.network = nn.Sequential(*mods)
        self.lstm = nn.LSTM(encoder[-1] if encoder else obs_dim, hidden, num_layers=layers)
        self.actor = nn.Linear(hidden, actions)
        self.critic = nn.Linear(hidden, 1)

    def get_states(self, x, lstm_state, done):
        hidden = self.network(x)
        batch_size = lstm_state[0].shape[1]
        hidden = hidden.reshape((-1, batch_size, self.lstm.input_size))
        done = done.reshape((-1, batch_size))
        new_hidden = []
        for h, d in zip(hidden, done):
            h, lstm_state = self.lstm(
                h.unsqueeze(0),
                ((1.0 - d).view(1, -1, 1) * lstm_state[0], (1.0 - d).view(1, -1, 1) * lstm_state[1]),
            )
            new_hidden += [h]
        return torch.flatten(torch.cat(new_hidden), 0, 1), lstm_state


@pytest.mark.parametrize(
    "encoder, layers, act, activation",
    [((32, 24), 1, nn.ReLU, "relu"), ((), 2, nn.ReLU, "relu"), ((20,), 1, nn.Tanh, "tanh")],
)
def test_cleanrl_state_dict_round_trip(tmp_path, encoder, layers, act, activation):
    torch.manual_seed(1)
    original = CleanRLAgent(54, 4, encoder, 16, layers, act)
    path = tmp_path / "agent.pt"
    torch.save(original.state_dict(), path)
    out = import_agent("cleanrl", path, tmp_path / "m", obs_dim=54, num_actions=4, activation=activation)
    agent, cfg, card = load_agent(out)
    assert cfg.agent == AgentConfig(lstm_sizes=(16,) * layers, encoder=encoder, encoder_activation=activation)
    assert card["provenance"]["value"] == "imported" and card["provenance"]["imported_from"] == "cleanrl"
    obs, starts = _episode_observations(steps=60, batch=3, seed=5)
    state = (torch.zeros(layers, 3, 16), torch.zeros(layers, 3, 16))
    logits, values = [], []
    with torch.no_grad():
        for t in range(obs.shape[0]):
            h, state = original.get_states(torch.as_tensor(obs[t]), state, torch.as_tensor(starts[t]).float())
            logits.append(original.actor(h))
            values.append(original.critic(h).squeeze(-1))
    ours_logits, ours_values = _our_outputs(agent, obs, starts)
    assert float((ours_logits - torch.stack(logits)).abs().max()) < 1e-5
    assert float((ours_values - torch.stack(values)).abs().max()) < 1e-5


def test_cleanrl_refuses_shapes_that_do_not_match(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "agent.pt"
    torch.save(CleanRLAgent(54, 4).state_dict(), path)
    with pytest.raises(CheckpointError, match=r"reads 54 observation inputs, not --obs-dim 60"):
        import_agent("cleanrl", path, tmp_path / "a", obs_dim=60, num_actions=4)
    with pytest.raises(CheckpointError, match=r"'actor.weight' has shape \[4, 16\], expected \[5, 16\]"):
        import_agent("cleanrl", path, tmp_path / "b", obs_dim=54, num_actions=5)
    sd = CleanRLAgent(54, 4).state_dict()
    sd["lstm.weight_hh_l0"] = torch.zeros(64, 15)
    torch.save(sd, path)
    with pytest.raises(CheckpointError, match=r"'lstm.weight_ih_l0' has shape \[64, 24\], expected \[60, 24\]"):
        import_agent("cleanrl", path, tmp_path / "c", obs_dim=54, num_actions=4)
    sd = CleanRLAgent(54, 4).state_dict()
    sd["extra.weight"] = torch.zeros(3)
    torch.save(sd, path)
    with pytest.raises(CheckpointError, match=r"tensor\(s\) this layout does not have: \['extra.weight'\]"):
        import_agent("cleanrl", path, tmp_path / "d", obs_dim=54, num_actions=4)
    with pytest.raises(ConfigError, match="needs --obs-dim and --actions"):
        import_agent("cleanrl", path, tmp_path / "e")
    assert not any((tmp_path / x).exists() for x in "abcde")


# ---------------------------------------------------------------------- refusals (sb3)


@pytest.fixture(scope="module")
def sb3_zip(sb3_default):
    """The bytes of each entry of a real sb3 zip, to build broken ones from."""
    path = sb3_default[2]
    with zipfile.ZipFile(path) as z:
        return {name: z.read(name) for name in z.namelist()}


def _write_zip(path, entries: dict[str, bytes], compression=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compression) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


def _edit_data(entries: dict[str, bytes], edit) -> dict[str, bytes]:
    data = json.loads(entries["data"])
    edit(data)
    return {**entries, "data": json.dumps(data).encode()}


class Payload:
    """Stands in for any pickled object: unpickling it would import and call code."""

    def __reduce__(self):
        return (print, ("unpickled!",))


def _torch_archive(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _refusals(entries: dict[str, bytes]) -> dict[str, tuple[dict[str, bytes], str]]:
    sd = torch.load(io.BytesIO(entries["policy.pth"]), weights_only=True)
    wrong = dict(sd)
    wrong["action_net.weight"] = torch.zeros(4, 7)
    box = {":type:": "<class 'gymnasium.spaces.box.Box'>", ":serialized:": "gAR=", "dtype": "float32", "_shape": [2]}
    pickled = _torch_archive({"policy": Payload()})
    return {
        "pickled object": (
            {**entries, "policy.pth": pickled},
            r"holds more than weights \(torch.load\(weights_only=True\) refused it: UnpicklingError",
        ),
        "raw pickle": ({**entries, "policy.pth": pickle.dumps(Payload())}, "not a torch zip archive"),
        "continuous actions": (
            _edit_data(entries, lambda d: d.update(action_space=box)),
            r"the action space is \"<class 'gymnasium.spaces.box.Box'>\", not Discrete",
        ),
        "continuous weights": (
            {**entries, "policy.pth": _torch_archive({**sd, "log_std": torch.zeros(2)})},
            "continuous action distribution",
        ),
        "shape mismatch": ({**entries, "policy.pth": _torch_archive(wrong)}, r"'action_net.weight' has shape \[4, 7\]"),
        "declared actions": (
            _edit_data(entries, lambda d: d["action_space"].update(n="5")),
            "the action space has 5 actions but action_net.weight has 4 rows",
        ),
        "observation shape": (
            _edit_data(entries, lambda d: d["observation_space"].update(_shape=[7, 7, 3])),
            r"the observation space has shape \[7, 7, 3\] \(147 inputs\) but lstm_actor.weight_ih_l0 reads 54",
        ),
        "missing data": ({k: v for k, v in entries.items() if k != "data"}, "has no 'data' entry"),
        "missing policy": ({k: v for k, v in entries.items() if k != "policy.pth"}, "has no 'policy.pth' entry"),
        "not LSTM": (
            {**entries, "policy.pth": _torch_archive({k: v for k, v in sd.items() if "lstm" not in k})},
            "no lstm_actor weights: not a recurrent policy",
        ),
        "feed-forward policy class": (
            _edit_data(entries, lambda d: d["policy_class"].update(__module__="stable_baselines3.common.policies")),
            "the policy class comes from 'stable_baselines3.common.policies'",
        ),
        "kwargs disagree": (
            _edit_data(entries, lambda d: d["policy_kwargs"].update(lstm_hidden_size=99)),
            "policy_kwargs.lstm_hidden_size is 99 but the weights have 16",
        ),
        "not a zip": ({}, "not a valid zip file"),
    }


@pytest.mark.parametrize(
    "case",
    ["pickled object", "raw pickle", "continuous actions", "continuous weights", "shape mismatch", "declared actions",
     "observation shape", "missing data", "missing policy", "not LSTM", "feed-forward policy class",
     "kwargs disagree", "not a zip"],
)  # fmt: skip
def test_sb3_refusals_name_the_problem_and_write_nothing(sb3_zip, tmp_path, capsys, case):
    entries, message = _refusals(sb3_zip)[case]
    path = tmp_path / "bad.zip"
    if case == "not a zip":
        path.write_bytes(b"not a zip at all")
    else:
        _write_zip(path, entries)
    with pytest.raises(CheckpointError, match=message):
        import_agent("sb3", path, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert "unpickled!" not in capsys.readouterr().out
    assert main(["import", str(path), "--from", "sb3", "--out", str(tmp_path / "out")]) == 2  # one line, exit 2
    err = capsys.readouterr().err
    assert err.startswith("seqtrojan import: error: ") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_sb3_refuses_an_oversized_entry_before_reading_it(sb3_zip, tmp_path, monkeypatch):
    bomb = _write_zip(tmp_path / "bomb.zip", {**sb3_zip, "data": b" " * (4 << 20)}, zipfile.ZIP_DEFLATED)
    assert bomb.stat().st_size < 100_000  # 4 MiB of spaces, compressed
    monkeypatch.setattr(imports, "MAX_DATA_BYTES", 1 << 20)
    opened = []
    monkeypatch.setattr(zipfile.ZipFile, "open", lambda self, *a, **k: opened.append(a) or 1 / 0)
    with pytest.raises(CheckpointError, match=r"'data' entry of .* unpacks to 4194304 bytes, more than the limit"):
        import_agent("sb3", bomb, tmp_path / "out")
    assert not opened and not (tmp_path / "out").exists()  # refused from the declared size, nothing decompressed
    monkeypatch.undo()
    monkeypatch.setattr(imports, "MAX_WEIGHTS_BYTES", 10_000)
    with pytest.raises(CheckpointError, match=r"'policy.pth' entry of .* more than the limit of 10000"):
        import_agent("sb3", _write_zip(tmp_path / "big.zip", sb3_zip), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_sb3_needs_an_env_with_the_agents_observation(sb3_default, tmp_path):
    _, _, path, _ = sb3_default
    cfg = ExperimentConfig(env=EnvConfig(view_size=5))
    with pytest.raises(CheckpointError, match=r"reads 54 inputs .* gives 150 inputs \(view 5x5\).*env.view_size: 3"):
        import_agent("sb3", path, tmp_path / "m", config=cfg)
    assert not (tmp_path / "m").exists()


# ---------------------------------------------------------------------- cards: new fields, old cards

NEW_AGENT = AgentConfig(lstm_sizes=(12, 8), encoder=(20,), encoder_activation="tanh", policy_mlp=(10, 6),
                        value_mlp=(5,), mlp_activation="relu")  # fmt: skip


def test_new_architecture_fields_round_trip_through_save_and_load(tmp_path):
    cfg = ExperimentConfig(agent=NEW_AGENT)
    torch.manual_seed(0)
    agent = build_agent(cfg).eval()
    arch = Architecture.of_config(cfg)
    assert architecture_of(agent) == arch
    assert arch.tensor_shapes() == {k: tuple(v.shape) for k, v in agent.state_dict().items()}
    assert arch.num_parameters == sum(p.numel() for p in agent.parameters())
    save_agent(tmp_path / "m", agent, cfg, label="clean")
    loaded, loaded_cfg, card = load_agent(tmp_path / "m")
    assert loaded_cfg == cfg and loaded_cfg.agent == NEW_AGENT
    assert card["architecture"] == {
        "type": "RecurrentActorCritic", "obs_dim": 54, "num_actions": 4, "lstm_sizes": [12, 8], "encoder": [20],
        "encoder_activation": "tanh", "policy_mlp": [10, 6], "value_mlp": [5], "mlp_activation": "relu",
    }  # fmt: skip
    assert "provenance" not in card
    obs = torch.rand(7, 3, 54)
    starts = torch.zeros(7, 3, dtype=torch.bool)
    starts[3, 1] = True
    with torch.no_grad():
        a = agent.unroll(obs, agent.initial_state(3), starts)
        b = loaded.unroll(obs, loaded.initial_state(3), starts)
    assert torch.equal(a.logits, b.logits) and torch.equal(a.values, b.values)
    # step and unroll compute the same function with the optional parts too
    logits, values = _our_outputs(loaded, obs.numpy(), starts.numpy())
    assert float((logits - b.logits).abs().max()) < 1e-5 and float((values - b.values).abs().max()) < 1e-5


def test_default_networks_keep_their_exact_card_and_weights(tmp_path):
    """No optional part: the saved config and architecture have exactly the keys earlier versions wrote, and the
    weights a seed gives are those of the paper's network (cells, then the two heads)."""
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(16, 8)))
    assert list(to_dict(cfg)["agent"]) == ["lstm_sizes", "forget_bias", "memory"]
    torch.manual_seed(0)
    agent = build_agent(cfg)
    assert list(agent.state_dict()) == [
        *(f"cells.{i}.{p}" for i in range(2) for p in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")),
        "policy_head.weight", "policy_head.bias", "value_head.weight", "value_head.bias",
    ]  # fmt: skip
    torch.manual_seed(0)
    reference = _paper_network(54, 4, (16, 8))
    for name, tensor in reference.state_dict().items():
        assert torch.equal(agent.state_dict()[name], tensor), name
    save_agent(tmp_path / "m", agent, cfg, label="clean")
    card = json.loads((tmp_path / "m" / "card.json").read_text())
    assert card["architecture"] == {"type": "RecurrentActorCritic", "obs_dim": 54, "num_actions": 4,
                                    "lstm_sizes": [16, 8]}  # fmt: skip
    assert list(card["config"]["agent"]) == ["lstm_sizes", "forget_bias", "memory"] and "provenance" not in card


def _paper_network(obs_dim, actions, sizes, forget_bias=1.0):
    """The network as earlier versions built it (cells, heads, then their initialisation)."""
    net = nn.Module()
    net.cells = nn.ModuleList(nn.LSTMCell(i, w) for i, w in zip((obs_dim, *sizes[:-1]), sizes))
    net.policy_head = nn.Linear(sizes[-1], actions)
    net.value_head = nn.Linear(sizes[-1], 1)
    for cell in net.cells:
        nn.init.orthogonal_(cell.weight_ih)
        nn.init.orthogonal_(cell.weight_hh)
        nn.init.zeros_(cell.bias_ih)
        nn.init.zeros_(cell.bias_hh)
        with torch.no_grad():
            cell.bias_ih[cell.hidden_size : 2 * cell.hidden_size] = forget_bias
    nn.init.orthogonal_(net.policy_head.weight, gain=0.01)
    nn.init.zeros_(net.policy_head.bias)
    nn.init.orthogonal_(net.value_head.weight, gain=1.0)
    nn.init.zeros_(net.value_head.bias)
    return net


def test_old_cards_still_load(tmp_path):
    """A card as earlier versions wrote it (no optional architecture keys, no provenance) loads unchanged."""
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,)))
    torch.manual_seed(0)
    save_agent(tmp_path / "m", build_agent(cfg), cfg, label="backdoored", metrics={"trojan_success": 0.9})
    data = json.loads((tmp_path / "m" / "card.json").read_text())
    old_keys = ["format", "format_version", "seqtrojan_version", "created", "label", "architecture", "seed",
                "env_steps", "config", "metrics", "tensors", "weights_sha256"]  # fmt: skip
    assert list(data) == old_keys and set(data["architecture"]) == {"type", "obs_dim", "num_actions", "lstm_sizes"}
    _, loaded_cfg, card = load_agent(tmp_path / "m")
    assert loaded_cfg == cfg and card["label"] == "backdoored" and read_card(tmp_path / "m").provenance is None


def _card(**changes) -> dict:
    cfg = ExperimentConfig(agent=NEW_AGENT)
    arch = Architecture.of_config(cfg)
    card = {
        "format": "seqtrojan-model", "format_version": 1, "label": "clean", "architecture": arch.to_card(),
        "config": to_dict(cfg), "tensors": {k: list(v) for k, v in arch.tensor_shapes().items()},
        "weights_sha256": "0" * 64,
        "provenance": {"imported_from": "sb3", "source_file": "m.zip", "source_sha256": "a" * 64,
                       "label_stated": False, "value": "zeroed", "details": {"critic": "lstm", "shape": [54]}},
    }  # fmt: skip
    for path, value in changes.items():
        *parents, key = path.split("__")
        target = card
        for p in parents:
            target = target[p]
        target[key] = value
    return card


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"architecture__encoder": [0]}, r"architecture.encoder\[0\] must be an integer in \[1, 4096\], got 0"),
        ({"architecture__policy_mlp": "10"}, "architecture.policy_mlp must be a list"),
        ({"architecture__value_mlp": [1] * 9}, "architecture.value_mlp must be a list of at most 8"),
        ({"architecture__mlp_activation": "gelu"}, "architecture.mlp_activation must be one of"),
        ({"architecture__head": [3]}, r"unknown \['head'\]"),
        ({"architecture__encoder": [21]}, "disagrees with its config"),
        ({"provenance__imported_from": "keras"}, "provenance.imported_from must be one of"),
        ({"provenance__label_stated": "no"}, "provenance.label_stated must be true or false"),
        ({"provenance__value": "approx"}, "provenance.value must be one of"),
        ({"provenance__source_sha256": "x"}, "provenance.source_sha256 must be 64 lowercase hex digits"),
        ({"provenance__details": {"a": {"b": 1}}}, r"provenance.details\['a'\] must be a number"),
        ({"provenance__extra": 1}, r"provenance must have exactly the keys .* unknown \['extra'\]"),
        ({"provenance": [1]}, "provenance must be a mapping or null"),
    ],
)
def test_cards_validate_the_new_fields(changes, message):
    parse_card(json.dumps(_card()))  # the unchanged card is valid
    with pytest.raises(CheckpointError, match=message):
        parse_card(json.dumps(_card(**changes)))


def test_agent_config_validates_the_new_fields():
    with pytest.raises(ConfigError, match=r"agent.policy_mlp must be 0 to 8 widths in \[1, 4096\], got \(0,\)"):
        AgentConfig(policy_mlp=(0,))
    with pytest.raises(ConfigError, match=r"agent\.encoder_activation must be one of"):
        AgentConfig(encoder_activation="gelu")  # type: ignore[arg-type]
    assert dataclasses.replace(NEW_AGENT) == NEW_AGENT


@pytest.mark.parametrize("header_len", [640, 19280, 19280 + 65536])
def test_safetensors_headers_whose_length_looks_like_pickle_or_zip_still_load(tmp_path, header_len):
    """A header length of 128 + 256 k starts the file with 0x80 (a pickle's first byte) and one of 19280 + 65536 k
    with "PK" (a zip's): such files are safetensors all the same (an imported model's header hit the second)."""
    from seqtrojan.agent.card import read_header

    header = json.dumps({"a": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}}).encode()
    header += b" " * (header_len - len(header))
    path = tmp_path / "w.safetensors"
    path.write_bytes(header_len.to_bytes(8, "little") + header + np.zeros(2, np.float32).tobytes())
    assert path.read_bytes()[:1] == b"\x80" or path.read_bytes()[:2] == b"PK"
    assert read_header(path).shapes == {"a": [2]}


# ---------------------------------------------------------------------- agents trained on other Gymnasium envs

GYM_PRESET = "minigrid_two_goals"
"""the MiniGrid two-goal room (6x6, 5x5 view: 500 one-hot inputs, 3 actions) under its trigger"""
SB3_GYM_KWARGS = {"lstm_hidden_size": 32, "net_arch": {"pi": [32], "vf": [32]}}


def _gym_preset(name: str = GYM_PRESET) -> ExperimentConfig:
    """A shipped Gymnasium preset as ``--config NAME`` reads it."""
    return from_dict(ExperimentConfig, load_yaml(resolve_preset(name)), "")


@pytest.fixture(scope="module")
def sb3_minigrid(tmp_path_factory):
    """(run config, sb3 model, its zip): a RecurrentPPO trained for 2,048 steps on the two-goal room wrapped exactly
    as the trainer wraps it (make_gym_env: MiniGrid's info, the trigger, the one-hot view)."""
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from seqtrojan.world.gymnasium import make_gym_env

    cfg = _gym_preset()
    venv = DummyVecEnv([lambda: make_gym_env(cfg.gym_env, "train", trojan_probability=0.5) for _ in range(4)])
    venv.seed(0)
    model = RecurrentPPO(
        "MlpLstmPolicy", venv, n_steps=128, batch_size=128, n_epochs=2, learning_rate=1e-3,
        policy_kwargs=SB3_GYM_KWARGS, seed=0, device="cpu",
    )  # fmt: skip
    model.learn(2048)
    path = tmp_path_factory.mktemp("sb3_minigrid") / "two_goals.zip"
    model.save(path)
    return cfg, model, path


def _gym_observations(cfg, steps: int, batch: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Observations (T, B, obs_dim) of ``batch`` of the run's envs (every other episode a trojan one, so trigger
    patches appear) under random actions, and the episode starts (T, B)."""
    from seqtrojan.world.gymnasium import make_gym_env

    envs = [make_gym_env(cfg.gym_env, "eval", trojan_probability=0.5) for _ in range(batch)]
    rng = np.random.default_rng(seed)
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    all_obs, starts = [], []
    start = np.ones(batch, dtype=bool)
    for _ in range(steps):
        all_obs.append(obs.copy())
        starts.append(start.copy())
        for i, env in enumerate(envs):
            o, _, terminated, truncated, _ = env.step(int(rng.integers(3)))
            start[i] = terminated or truncated
            obs[i] = env.reset()[0] if start[i] else o
    return np.stack(all_obs), np.stack(starts)


def test_an_sb3_agent_trained_on_minigrid_imports_as_a_gym_model_with_the_same_policy(sb3_minigrid, tmp_path, capsys):
    from seqtrojan.evaluation.env_report import run_outcomes

    cfg, model, path = sb3_minigrid
    out = tmp_path / "gym"
    assert main(["import", str(path), "--from", "sb3", "--config", GYM_PRESET, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "for the Gymnasium env seqtrojan/MiniGridTwoGoals-v0" in printed and "obs_dim=500" in printed
    assert "not stated" in printed and "value head: zero" in printed
    assert sorted(p.name for p in out.iterdir()) == ["card.json", "model.safetensors"]
    agent, loaded, card = load_agent(out)
    assert (loaded.env, loaded.ppo) == (cfg.env, cfg.ppo) and loaded.gym_env.trigger is not None
    assert loaded.agent == AgentConfig(lstm_sizes=(32,), policy_mlp=(32,), value_mlp=(32,))
    assert card["label"] == "unknown" and not loaded.backdoor.enabled and card["env_steps"] == model.num_timesteps
    prov = card["provenance"]
    assert prov["imported_from"] == "sb3" and prov["source_sha256"] == imports._sha256(path)
    assert prov["label_stated"] is False and prov["value"] == "zeroed" and prov["details"]["observation_shape"] == [500]

    obs, starts = _gym_observations(cfg, steps=60, batch=4, seed=5)
    assert starts[1:].any() and obs.shape == (60, 4, 500)
    sb3_logp, _ = _sb3_log_probs(model, obs, starts)
    logits, values = _our_outputs(agent, obs, starts)
    assert float((torch.log_softmax(logits, -1) - sb3_logp).abs().max()) < 1e-5
    assert float(values.abs().max()) == 0.0

    normal = run_outcomes(agent, loaded, trojan=False, episodes=32, seed=0)
    trojan = run_outcomes(agent, loaded, trojan=True, episodes=32, seed=0)
    assert normal.success.n == trojan.success.n == 32 and bool(trojan.batch.trojan.all())
    assert trojan.persistence([0])[0].adversary.n > 0


def test_a_gym_import_is_checked_against_the_env_the_config_builds(sb3_minigrid, tmp_path):
    cfg, _, path = sb3_minigrid
    with pytest.raises(CheckpointError, match=r"reads 500 inputs and chooses among 3 actions, but the config's "
                       r"env \(.*Memory.*\) gives 980 inputs and 3 actions"):  # fmt: skip
        import_agent("sb3", path, tmp_path / "m", config=_gym_preset("minigrid_memory"))
    untriggered = ExperimentConfig(env=dataclasses.replace(cfg.gym_env, trigger=None))
    with pytest.raises(ConfigError, match=r"--label backdoored: backdoor\.enabled needs env\.trigger"):
        import_agent("sb3", path, tmp_path / "m", config=untriggered, label="backdoored")
    assert not (tmp_path / "m").exists()
    # the label stated, through the command line
    argv = ["import", str(path), "--from", "sb3", "--config", GYM_PRESET, "--label", "backdoored", "--out"]
    assert main([*argv, str(tmp_path / "b")]) == 0
    _, loaded, card = load_agent(tmp_path / "b")
    assert card["label"] == "backdoored" and loaded.backdoor == cfg.backdoor and card["provenance"]["label_stated"]
    assert loaded.env == cfg.env


# ---------------------------------------------------------------------- refusals: sizes, bombs, values (#28)


def _lying_zip(path, payload: bytes, declared: int):
    """A zip whose 'data' entry's headers (local and central) declare ``declared`` bytes but whose deflated data
    unpacks to ``payload`` (a zip bomb with a lying size header)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("data", payload)
        z.writestr("policy.pth", b"PK")
    raw = bytearray(path.read_bytes())
    struct.pack_into("<I", raw, 22, declared)  # the local header's uncompressed size
    struct.pack_into("<I", raw, raw.index(b"PK\x01\x02") + 24, declared)  # the central directory's
    path.write_bytes(bytes(raw))
    return path


def _cleanrl_file(path, **changes):
    torch.manual_seed(0)
    sd = {**CleanRLAgent(54, 4).state_dict(), **changes}
    torch.save(sd, path)
    return path


def _deflated_torch_file(path):
    buf = io.BytesIO(_torch_archive(CleanRLAgent(54, 4).state_dict()))
    with zipfile.ZipFile(buf) as src, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info))
    return path


NAN_BIAS = torch.tensor([0.0, float("nan"), 0.0, 0.0])
BOUNDED_IMPORTS = {
    # case: (source, file maker, patched limits, message)
    "lying zip header": (
        "sb3", lambda p: _lying_zip(p, b" " * (8 << 20), 1000), {}, r"'data' entry of .* cannot be read: Bad CRC",
    ),
    "tensor over the cap": (
        "cleanrl", lambda p: _cleanrl_file(p, **{"critic.bias": torch.zeros(5000)}), {"MAX_PARAMETERS": 4096},
        r"tensor 'critic.bias' has dtype torch.float32 and shape \[5000\] .* at most 8 dimensions and 4096 numbers",
    ),
    "file over the cap": (
        "cleanrl", _cleanrl_file, {"MAX_FILE_PARAMETERS": 1000}, r"holds \d+ numbers in its tensors, more than .* 1000",
    ),
    "network over the cap": (
        "cleanrl", _cleanrl_file, {"MAX_PARAMETERS": 3000},
        r"the imported network would have \d+ parameters, more than the limit of 3000",
    ),
    "NaN weight": ("cleanrl", lambda p: _cleanrl_file(p, **{"actor.bias": NAN_BIAS}), {}, "NaN or infinite values"),
    "infinite weight": (
        "cleanrl", lambda p: _cleanrl_file(p, **{"critic.bias": torch.tensor([float("inf")])}), {},
        r"NaN or infinite values \(imported as \['value_head.bias'\]\)",
    ),
    "compressed torch archive": ("cleanrl", _deflated_torch_file, {}, "compressed entries"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BOUNDED_IMPORTS))
def test_import_refuses_unbounded_or_non_finite_weights_before_building(tmp_path, monkeypatch, capsys, case):
    source, make, limits, message = BOUNDED_IMPORTS[case]
    path = make(tmp_path / ("in.zip" if source == "sb3" else "in.pt"))
    for name, value in limits.items():
        monkeypatch.setattr(imports, name, value)
    monkeypatch.setattr(imports, "build_agent", lambda *a, **k: pytest.fail("the network was built"))
    returned = []
    read = zipfile.ZipExtFile.read
    spy = lambda self, n=-1: returned.append(len(out := read(self, n))) or out  # noqa: E731
    monkeypatch.setattr(zipfile.ZipExtFile, "read", spy)
    with pytest.raises(CheckpointError, match=message):
        import_agent(source, path, tmp_path / "out", obs_dim=54, num_actions=4)
    assert sum(returned) <= 1001  # a lying header: never more than it declares (+1) is decompressed
    flags = ["--obs-dim", "54", "--actions", "4"] if source == "cleanrl" else []
    assert main(["import", str(path), "--from", source, "--out", str(tmp_path / "out"), *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith("seqtrojan import: error: ") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()
