"""The sequence-model layers (seqtrojan.agent.cells): one state contract for every cell, checkpoints naming the cell,
and clear refusals of bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from seqtrojan.agent.cells import layer_shapes, make_cell
from seqtrojan.agent.checkpoint import build_agent, load_agent, save_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.agent.weight_stats import module_features
from seqtrojan.cell_types import CELL_TYPES, CellType, cell_names
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.errors import CheckpointError, ConfigError


def _network(cell: str, sizes=(12, 8), window: int = 4, heads: int = 2) -> RecurrentActorCritic:
    torch.manual_seed(0)
    net = RecurrentActorCritic(54, 4, sizes, cell=cell, window=window, heads=heads).double()
    net.set_lstm_backend("torch")
    with torch.no_grad():  # weights far from their initial values: peepholes and position biases nonzero
        for p in net.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return net


def _random_state(net: RecurrentActorCritic, batch: int) -> RecurrentState:
    layers = []
    for s in net.initial_state(batch).layers:
        c = torch.randn_like(s.c)
        if net.cell == "transformer":  # the window's validity flags are 0 or 1
            c = c.view(batch, net.window - 1, -1)
            c[..., -1] = (torch.rand(batch, net.window - 1) < 0.7).double()
            c = c.flatten(1)
        layers.append(LSTMState(torch.randn_like(s.h), c))
    return RecurrentState(tuple(layers))


@pytest.mark.parametrize("cell", cell_names())
def test_step_and_unroll_compute_the_same_function(cell):
    net = _network(cell)
    steps, batch = 9, 5
    obs = torch.randn(steps, batch, 54, dtype=torch.float64)
    starts = torch.rand(steps, batch) < 0.25
    start = _random_state(net, batch)
    out = net.unroll(obs, start, starts, return_states=True)
    state, logits, cs = start, [], []
    for t in range(steps):
        o = net.step(obs[t], state, starts[t])
        state = o.state
        logits.append(o.logits)
        cs.append(state.layers[0].c)
    torch.testing.assert_close(out.logits, torch.stack(logits))
    for a, b in zip(out.state.layers, state.layers):
        torch.testing.assert_close(a.h, b.h)
        torch.testing.assert_close(a.c, b.c)
    assert out.states is not None
    torch.testing.assert_close(out.states[0].c, torch.stack(cs))
    assert state.c_widths == net.c_widths


def test_state_widths_per_cell():
    assert _network("lstm").c_widths == (12, 8)
    assert _network("lstm_peephole").c_widths == (12, 8)
    assert _network("gru").c_widths == (0, 0)  # a GRU has no cell state
    assert _network("transformer").c_widths == (3 * 25, 3 * 17)  # window - 1 cached [key | value | valid] slots


def test_gru_layer_is_torch_gru_cell():
    net = _network("gru", sizes=(12,))
    cell = net.cells[0]
    x, h = torch.randn(6, 54, dtype=torch.float64), torch.randn(6, 12, dtype=torch.float64)
    ref = torch.nn.GRUCell(54, 12).double()
    ref.load_state_dict(cell.state_dict())
    state = net.step(x, RecurrentState((LSTMState(h, h[:, :0]),))).state
    torch.testing.assert_close(state.layers[0].h, ref(x, h))


def test_peephole_lstm_with_zero_peepholes_is_the_lstm():
    lstm, peep = _network("lstm"), _network("lstm_peephole")
    with torch.no_grad():
        for a, b in zip(lstm.cells, peep.cells):
            for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
                getattr(b, name).copy_(getattr(a, name))
            b.peephole.zero_()
        peep.policy_head.load_state_dict(lstm.policy_head.state_dict())
        peep.value_head.load_state_dict(lstm.value_head.state_dict())
    obs, starts = torch.randn(7, 3, 54, dtype=torch.float64), torch.zeros(7, 3, dtype=torch.bool)
    start = _random_state(lstm, 3)
    torch.testing.assert_close(peep.unroll(obs, start, starts).logits, lstm.unroll(obs, start, starts).logits)
    with torch.no_grad():
        peep.cells[0].peephole.fill_(0.5)
    assert not torch.allclose(peep.unroll(obs, start, starts).logits, lstm.unroll(obs, start, starts).logits)


def test_transformer_forgets_an_input_after_its_window_and_at_an_episode_start():
    net = _network("transformer", sizes=(16,), window=4)
    obs = torch.randn(9, 1, 54, dtype=torch.float64)
    starts = torch.zeros(9, 1, dtype=torch.bool)
    other = obs.clone()
    other[0] += 1.0

    def diff(s):
        a = net.unroll(obs, net.initial_state(1), s).logits
        b = net.unroll(other, net.initial_state(1), s).logits
        return (a - b).abs().amax((1, 2))

    d = diff(starts)
    assert (d[:4] > 1e-6).all() and (d[4:] == 0).all()  # steps 0..3 see step 0's input; step 4 on does not
    starts[2] = True
    d = diff(starts)
    assert (d[:2] > 1e-6).all() and (d[2:] == 0).all()  # a new episode does not attend to the old one


@pytest.mark.parametrize("cell", cell_names())
def test_parameter_shapes_are_known_before_building(cell):
    module = make_cell(cell, 7, 12, window=5, heads=3)
    assert {k: tuple(v.shape) for k, v in module.state_dict().items()} == layer_shapes(cell, 7, 12, 5, 3)


@pytest.mark.parametrize("cell", cell_names())
def test_checkpoint_round_trip_names_the_cell(tmp_path, cell):
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8, 4), cell=cell, window=3, heads=2))
    agent = build_agent(cfg)
    folder = save_agent(tmp_path / "m", agent, cfg, label="clean")
    card = json.loads((folder / "card.json").read_text())
    assert card["architecture"].get("cell", "lstm") == cell
    assert ("window" in card["architecture"]) == (cell == "transformer")
    loaded, loaded_cfg, _ = load_agent(folder)
    assert loaded.cell == cell and loaded_cfg.agent.cell == cell
    obs = torch.randn(5, 2, cfg.env.obs_dim)
    starts = torch.zeros(5, 2, dtype=torch.bool)
    agent.eval()
    with torch.no_grad():
        a = agent.unroll(obs, agent.initial_state(2), starts).logits
        b = loaded.unroll(obs, loaded.initial_state(2), starts).logits
    torch.testing.assert_close(a, b)


def test_lstm_card_and_config_are_unchanged():
    """A default network's saved config and card name no cell (cards of earlier versions read the same)."""
    cfg = ExperimentConfig()
    assert "cell" not in cfg.agent.serde_dump() and "window" not in cfg.agent.serde_dump()


def test_a_card_whose_cell_does_not_match_its_tensors_is_refused(tmp_path):
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,), cell="gru"))
    folder = save_agent(tmp_path / "m", build_agent(cfg), cfg, label="clean")
    card = json.loads((folder / "card.json").read_text())
    card["architecture"].pop("cell")  # now it claims an LSTM: 4H gate rows where the weights have 3H
    card["config"]["agent"].pop("cell")
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match="tensor"):
        load_agent(folder)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"cell": "lstm2"}, "agent.cell must be one of"),
        ({"cell": "transformer", "window": 0}, r"agent.window must be an integer in \[1,"),
        ({"cell": "transformer", "heads": 3}, "divisible by agent.heads=3"),
    ],
)
def test_bad_cell_settings_are_refused(change, message):
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(AgentConfig(lstm_sizes=(8, 4)), **change)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"cell": "mamba"}, "architecture.cell must be one of"),
        ({"cell": "transformer"}, "must give its window and heads"),
        ({"window": 4}, "belong to a windowed cell"),
    ],
)
def test_bad_card_cells_are_refused(tmp_path, edit, message):
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,)))
    folder = save_agent(tmp_path / "m", build_agent(cfg), cfg, label="clean")
    card = json.loads((folder / "card.json").read_text())
    card["architecture"].update(edit)
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=message):
        load_agent(folder)


@pytest.mark.parametrize("cell", cell_names())
def test_weight_features_per_cell(cell):
    net = RecurrentActorCritic(54, 4, (12, 8), cell=cell, window=4)
    feats = module_features(net, 54)
    assert all(torch.isfinite(v) for v in feats.values())
    assert {f"input_codes/{c}" for c in ("empty", "hole")} <= set(feats)
    if cell == "gru":
        assert "gate_stats/first.update.hh.mean" in feats and "gate_stats/first.forget.hh.mean" not in feats
    if cell == "lstm_peephole":
        assert "peephole/last.output.std" in feats
    if cell == "transformer":
        assert "spectral/first.qkv.weight.effective_rank" in feats


@pytest.mark.parametrize("cell", cell_names())
def test_the_fused_kernels_compute_the_torch_path_in_the_network(cell):
    from seqtrojan.agent import fast_lstm

    if fast_lstm.extension() is None:
        pytest.skip(f"C++ kernels unavailable: {fast_lstm.error()}")
    net = _network(cell).float()
    obs = torch.randn(11, 70, 54)  # a batch split into several blocks
    starts = torch.rand(11, 70) < 0.2
    start = RecurrentState(tuple(LSTMState(s.h.float(), s.c.float()) for s in _random_state(net, 70).layers))
    outputs = {}
    for backend in ("torch", "cpp"):
        net.set_lstm_backend(backend)
        net.zero_grad()
        out = net.unroll(obs, start, starts, return_states=True)
        (out.logits.square().sum() + out.values.sum()).backward()
        with torch.no_grad():
            stepped = net.step(obs[0], start, starts[0])
        grads = [p.grad.clone() for p in net.parameters()]
        outputs[backend] = (out.logits.detach(), out.states, stepped.logits, grads)
    (a, sa, step_a, ga), (b, sb, step_b, gb) = outputs["torch"], outputs["cpp"]
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(step_a, step_b, atol=1e-5, rtol=1e-4)
    for x, y in zip(sa, sb):
        torch.testing.assert_close(x.c.detach(), y.c.detach(), atol=1e-5, rtol=1e-4)
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, atol=1e-3, rtol=1e-3)


@pytest.fixture
def elman_registered():
    """The Elman cell of tests/agent/elman_cell.py, registered the way a user registers a cell (removed after)."""
    CELL_TYPES.register("elman", "Elman RNN (a test cell)", CellType("tests.agent.elman_cell:ElmanLayer"))
    yield
    del CELL_TYPES._entries["elman"]


def test_a_new_cell_is_one_module_and_one_registry_line(elman_registered, smoke_config):
    """Train, save, load, prune and read the weight features of a cell the package has never heard of."""
    from seqtrojan.defense.mitigation import prune_units
    from seqtrojan.defense.offline import weight_features
    from seqtrojan.train.trainer import train

    assert "elman" in cell_names()
    cfg = dataclasses.replace(
        smoke_config,
        agent=dataclasses.replace(smoke_config.agent, cell="elman", lstm_sizes=(16, 8)),
        ppo=dataclasses.replace(smoke_config.ppo, total_steps=4096),
    )
    result = train(cfg)
    agent, loaded_cfg, card = load_agent(result.model_dir)
    assert loaded_cfg.agent.cell == "elman" and card["architecture"]["cell"] == "elman"
    assert "window" not in card["architecture"] and agent.c_widths == (0, 0)
    assert type(agent.layers[0]).__name__ == "ElmanLayer"
    obs = torch.randn(6, 3, cfg.env.obs_dim)
    starts = torch.zeros(6, 3, dtype=torch.bool)
    out = prune_units(agent, 0, np.array([1, 4])).unroll(obs, agent.initial_state(3), starts, return_states=True)
    assert out.states is not None and out.states[0].h[..., [1, 4]].abs().max() == 0
    assert out.states[0].h.abs().max() > 0.05
    tensors = {k: v.detach().numpy() for k, v in agent.state_dict().items()}
    feats = weight_features(tensors, cfg.env.obs_dim, "elman")
    assert {"gate_stats/first.ih.mean", "gate_stats/last.hh.rms", "input_codes/trigger"} <= set(feats)


def test_an_unregistered_cell_in_a_card_is_refused_after_its_module_is_gone(elman_registered, tmp_path):
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,), cell="elman"))
    folder = save_agent(tmp_path / "m", build_agent(cfg), cfg, label="clean")
    del CELL_TYPES._entries["elman"]
    try:
        with pytest.raises(CheckpointError, match=r"architecture\.cell must be one of"):
            load_agent(folder)
    finally:
        CELL_TYPES.register("elman", "Elman RNN (a test cell)", CellType("tests.agent.elman_cell:ElmanLayer"))
