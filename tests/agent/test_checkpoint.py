"""Model files: safetensors + JSON card round trip; pickles, corrupt files and mismatched cards are refused."""

from __future__ import annotations

import hashlib
import json
import math
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


# ---------------------------------------------------------------------- hostile model files
# A model file from a marketplace is untrusted: every refusal below must be one CheckpointError line, raised before
# the network is built or any tensor is read (the `no_allocation` guard fails the test otherwise). Before the card
# and header were validated, `lstm_sizes: [12000]` cost 7.4 GiB and minutes before failing, and other edits gave
# KeyError/TypeError/RecursionError/OverflowError tracebacks or were accepted.

OBS, ACTIONS = CFG.env.obs_dim, CFG.env.num_actions


def _shapes(obs_dim, num_actions, sizes):
    """state_dict shapes of RecurrentActorCritic(obs_dim, num_actions, sizes), written out independently."""
    shapes, inputs = {}, [obs_dim, *sizes[:-1]]
    for i, (n, w) in enumerate(zip(inputs, sizes)):
        shapes |= {f"cells.{i}.weight_ih": [4 * w, n], f"cells.{i}.weight_hh": [4 * w, w]}
        shapes |= {f"cells.{i}.bias_ih": [4 * w], f"cells.{i}.bias_hh": [4 * w]}
    shapes |= {"policy_head.weight": [num_actions, sizes[-1]], "policy_head.bias": [num_actions]}
    return shapes | {"value_head.weight": [1, sizes[-1]], "value_head.bias": [1]}


@pytest.fixture
def no_allocation(monkeypatch):
    """Fail the test if the network is built or tensors are read: refusals must come before either."""
    from seqtrojan.agent import checkpoint

    def forbidden(*args, **kwargs):
        raise AssertionError("a hostile model file got as far as building the network or reading tensors")

    monkeypatch.setattr(checkpoint, "RecurrentActorCritic", forbidden)
    for name in ("load", "load_file"):
        monkeypatch.setattr(checkpoint, name, forbidden, raising=False)


def _card(folder):
    return json.loads((folder / "card.json").read_text())


def _write_card(folder, card):
    (folder / "card.json").write_text(json.dumps(card))


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _rewrite_weights(folder, header_edit):
    """Rewrite model.safetensors with an edited header (same data) and record its new SHA-256 in the card, so that
    only the header checks can catch the lie."""
    path = folder / "model.safetensors"
    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    header_edit(header)
    raw = json.dumps(header).encode()
    path.write_bytes(len(raw).to_bytes(8, "little") + raw + data[8 + n :])
    card = _card(folder)
    card["weights_sha256"] = _sha(path)
    _write_card(folder, card)


def _assert_one_line(err):
    text = str(err.value)
    assert "\n" not in text and 0 < len(text) < 1000, text


def _with_sizes(card, sizes, tensors=False):
    card["architecture"]["lstm_sizes"] = sizes
    card["config"]["agent"]["lstm_sizes"] = sizes
    if tensors:
        card["tensors"] = _shapes(OBS, ACTIONS, sizes)
    return card


@pytest.mark.parametrize(
    ("sizes", "match"),
    [
        ([12000], r"lstm_sizes\[0\] must be an integer in \[1, 4096\], got 12000"),
        ([1000000, 1000000], r"lstm_sizes\[0\] must be an integer in \[1, 4096\]"),
        ([1e6, 1e6], r"lstm_sizes\[0\] must be an integer in \[1, 4096\], got 1000000\.0"),
        ([8] * 9, "1 to 8 layer widths"),
        ([4096] * 8, r"parameters, more than the limit"),
        (
            [2048],
            r"does not fit the architecture.*\[2048\]\): tensor 'cells\.0\.bias_hh' .* architecture says \[8192\]",
        ),
    ],
)
def test_oversized_architecture_is_refused_before_allocation(saved, no_allocation, sizes, match):
    _, folder = saved
    _write_card(folder, _with_sizes(_card(folder), sizes))
    with pytest.raises(CheckpointError, match=match) as err:
        load_agent(folder)
    _assert_one_line(err)


def test_card_listing_big_tensors_over_small_weights_is_refused(saved, no_allocation):
    _, folder = saved
    _write_card(folder, _with_sizes(_card(folder), [2048], tensors=True))  # matching-looking tensor list
    with pytest.raises(
        CheckpointError,
        match=r"card\.json does not match model\.safetensors.*has shape \[64\] but the card says \[8192\]",
    ):
        load_agent(folder)


@pytest.mark.parametrize(
    ("sizes", "offsets", "match"),
    [
        ([12000], "real_sizes", r"lstm_sizes\[0\] must be an integer in \[1, 4096\], got 12000"),
        ([2048], "real_sizes", "past the end of the data"),
        ([2048], "small", r"which need \d+ bytes.*hold 4"),
    ],
)
def test_forged_header_claiming_big_tensors_is_refused(saved, no_allocation, sizes, offsets, match):
    """Card (architecture, config, tensor list) and header all claim a wide network; the file holds the small one."""
    _, folder = saved

    def claim(header):
        header.clear()
        cursor = 0
        for name, shape in _shapes(OBS, ACTIONS, sizes).items():
            size = 4 * math.prod(shape) if offsets == "real_sizes" else 4
            header[name] = {"dtype": "F32", "shape": shape, "data_offsets": [cursor, cursor + size]}
            cursor += size

    _rewrite_weights(folder, claim)
    _write_card(folder, _with_sizes(_card(folder), sizes, tensors=True))
    with pytest.raises(CheckpointError, match=match) as err:
        load_agent(folder)
    _assert_one_line(err)


def test_huge_header_length_is_refused_before_reading_it(saved, no_allocation):
    _, folder = saved
    path = folder / "model.safetensors"
    path.write_bytes((1 << 62).to_bytes(8, "little") + b"{" + b" " * 100)
    with pytest.raises(CheckpointError, match=r"header of 4611686018427387904 bytes, more than the limit"):
        load_agent(folder)
    # a header length that fits in the file but is over the limit: not read either
    path.write_bytes(((1 << 20) + 1).to_bytes(8, "little") + b"{" + b" " * (1 << 20) + b"}")
    with pytest.raises(CheckpointError, match=r"header of 1048577 bytes, more than the limit of 1048576"):
        load_agent(folder)


@pytest.mark.parametrize(
    ("lie", "match"),
    [
        (lambda h: h["cells.0.weight_hh"].update(dtype="I32"), r"weight_hh' has dtype I32; weights must be one of"),
        (lambda h: h["cells.0.weight_hh"].update(dtype="F64"), r"dtype F64 and shape \[64, 16\].*need 8192 bytes"),
        (lambda h: h["cells.0.weight_hh"].update(dtype="Q99"), "unknown dtype 'Q99'"),
        (lambda h: h["value_head.bias"].update(data_offsets=[0, 4]), "overlaps another tensor"),
        (lambda h: h["value_head.bias"].update(data_offsets=[10**12, 10**12 + 4]), "past the end of the data"),
        (lambda h: h["value_head.bias"].update(data_offsets=[-4, 0]), "invalid data_offsets"),
        (lambda h: h["value_head.bias"].update(shape=[1.5]), "non-negative integers"),
        (lambda h: h.update(extra={"dtype": "F32", "shape": [0], "data_offsets": [0, 0], "x": 1}), "exactly dtype"),
        (lambda h: h.update(__metadata__=[1]), "__metadata__ must map strings to strings"),
    ],
)
def test_header_lies_are_refused_before_reading_tensors(saved, no_allocation, lie, match):
    _, folder = saved
    _rewrite_weights(folder, lie)
    with pytest.raises(CheckpointError, match=match) as err:
        load_agent(folder)
    _assert_one_line(err)


def test_trailing_bytes_after_the_last_tensor_are_refused(saved, no_allocation):
    _, folder = saved
    path = folder / "model.safetensors"
    path.write_bytes(path.read_bytes() + b"\0" * 16)
    card = _card(folder)
    card["weights_sha256"] = _sha(path)
    _write_card(folder, card)
    with pytest.raises(CheckpointError, match=r"tensors cover \d+ bytes but the file holds \d+"):
        load_agent(folder)


def _deep(card):
    card["metrics"] = "@@DEEP@@"
    return json.dumps(card).replace('"@@DEEP@@"', "[" * 100_000 + "]" * 100_000)


def _set(path, value):
    def edit(card):
        *parents, last = path
        node = card
        for key in parents:
            node = node[key]
        if value is KeyError:
            del node[last]
        else:
            node[last] = value
        return card

    return edit


HOSTILE_CARDS = {
    "tensors_as_list": (_set(["tensors"], [["cells.0.weight_ih", [64, 54]]]), "tensors must be a mapping"),
    "tensor_shape_not_list": (_set(["tensors", "value_head.bias"], 1), r"tensors\['value_head.bias'\] must be a list"),
    "architecture_missing_key": (_set(["architecture", "obs_dim"], KeyError), r"missing \['obs_dim'\]"),
    "architecture_as_list": (_set(["architecture"], [54, 4, [16, 8]]), "architecture must be a mapping"),
    "architecture_wrong_type": (_set(["architecture", "type"], "os.system"), "architecture.type must be"),
    "obs_dim_huge": (_set(["architecture", "obs_dim"], 10**12), r"obs_dim must be an integer in \[1, 32768\]"),
    "obs_dim_bool": (_set(["architecture", "obs_dim"], True), r"obs_dim must be an integer"),
    "num_actions_huge": (_set(["architecture", "num_actions"], 10**9), r"num_actions must be an integer in \[1, 64\]"),
    "widths_float": (_set(["architecture", "lstm_sizes"], [16.0, 8.0]), r"lstm_sizes\[0\] must be an integer"),
    "widths_not_list": (_set(["architecture", "lstm_sizes"], {"a": 1}), "lstm_sizes must be a list"),
    "widths_empty": (_set(["architecture", "lstm_sizes"], []), "lstm_sizes must be a list of 1 to 8"),
    "arch_disagrees_with_config": (_set(["architecture", "lstm_sizes"], [16, 4]), "disagrees with its config"),
    "label_other": (_set(["label"], "trusted"), r"label must be one of \[.*unknown'\], got 'trusted'"),
    "label_missing": (_set(["label"], KeyError), "lacks the field 'label'"),
    "label_list": (_set(["label"], ["clean"]), r"label must be one of \[.*\], got \['clean'\]"),
    "sha_missing": (_set(["weights_sha256"], KeyError), "lacks the field 'weights_sha256'"),
    "sha_null": (_set(["weights_sha256"], None), "weights_sha256 must be the weights' SHA-256.*got None"),
    "sha_not_hex": (_set(["weights_sha256"], "z" * 64), "weights_sha256 must be"),
    "config_missing": (_set(["config"], KeyError), "lacks the field 'config'"),
    "config_as_list": (_set(["config"], [1, 2]), "invalid config.*must be a mapping"),
    "config_overflow": (_set(["config", "ppo", "learning_rate"], 10**400), "invalid config.*OverflowError"),
    "config_bad_type": (_set(["config", "env", "size"], "9"), r"invalid config.*config\.env\.size must be an integer"),
    "format_version_bool": (_set(["format_version"], True), "format_version True, expected 1"),
    "metrics_not_mapping": (_set(["metrics"], [1, 2]), "metrics must be a mapping"),
    "env_steps_negative": (_set(["env_steps"], -1), "env_steps must be an integer >= 0"),
    "unknown_field": (_set(["exec"], "import os"), r"unknown field\(s\) \['exec'\]"),
    "too_many_items": (_set(["metrics", "x"], list(range(5000))), "a list with 5000 entries, more than the limit"),
    "deep_nesting": (_deep, "nests lists/objects more than 32 deep"),
    "huge_card": (_set(["metrics", "pad"], "x" * (1 << 20)), "larger than the 1048576 bytes"),
    "duplicate_key": (lambda c: json.dumps(c)[:-1] + ', "label": "clean"}', "duplicate key 'label'"),
    "huge_integer": (lambda c: json.dumps(c).replace('"seed": 0', '"seed": ' + "9" * 5000), "not valid JSON"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_CARDS))
def test_hostile_cards_give_one_checkpoint_error_before_allocation(saved, no_allocation, case):
    _, folder = saved
    edit, match = HOSTILE_CARDS[case]
    card = edit(_card(folder))
    (folder / "card.json").write_text(card if isinstance(card, str) else json.dumps(card))
    with pytest.raises(CheckpointError, match=match) as err:
        load_agent(folder)
    _assert_one_line(err)


def test_save_refuses_a_card_that_load_would_refuse(tmp_path):
    wider = ExperimentConfig(env=CFG.env, agent=AgentConfig(lstm_sizes=(32, 8)))  # not the agent's sizes
    with pytest.raises(CheckpointError, match="disagrees with its config"):
        save_agent(tmp_path / "m", build_agent(CFG), wider, label="clean")
    assert not (tmp_path / "m").exists()


def test_valid_model_loads_with_identical_weights_and_outputs(saved):
    agent, folder = saved
    loaded, _, card = load_agent(folder)
    assert card["weights_sha256"] == _sha(folder / "model.safetensors") and card["label"] == "backdoored"
    assert agent.state_dict().keys() == loaded.state_dict().keys()
    for name, tensor in agent.state_dict().items():
        assert torch.equal(tensor, loaded.state_dict()[name]), name
    obs = torch.randn(5, 2, CFG.env.obs_dim)
    starts = torch.zeros(5, 2, dtype=torch.bool)
    with torch.no_grad():
        a = agent.unroll(obs, agent.initial_state(2), starts)
        b = loaded.unroll(obs, loaded.initial_state(2), starts)
    assert torch.equal(a.logits, b.logits) and torch.equal(a.values, b.values)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_on_save_and_on_load(saved, tmp_path, value):
    from safetensors.torch import load_file, save_file

    _, folder = saved
    agent, cfg, _ = load_agent(folder)
    with torch.no_grad():
        agent.policy_head.bias[0] = value
    with pytest.raises(CheckpointError, match=r"holds NaN or infinite values \(in policy_head.bias\)"):
        save_agent(tmp_path / "diverged", agent, cfg, label="clean")
    assert not (tmp_path / "diverged").exists()
    tensors = load_file(str(folder / "model.safetensors"))  # a tampered file whose card records its hash
    tensors["value_head.bias"] = torch.full_like(tensors["value_head.bias"], value)
    save_file(tensors, str(folder / "model.safetensors"))
    card = json.loads((folder / "card.json").read_text())
    card["weights_sha256"] = hashlib.sha256((folder / "model.safetensors").read_bytes()).hexdigest()
    (folder / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=r"holds NaN or infinite values \(in value_head.bias\)"):
        load_agent(folder)
