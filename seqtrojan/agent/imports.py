"""Agents trained elsewhere, imported as a :class:`~seqtrojan.agent.network.RecurrentActorCritic` model folder.

Two sources (docs/import.md has the full mapping and every refusal):

- **sb3**: a stable-baselines3 zip of sb3-contrib's ``RecurrentPPO`` with ``MlpLstmPolicy``. Read without unpickling
  anything: ``policy.pth`` with ``torch.load(weights_only=True)``, and the architecture from the JSON text of the
  ``data`` entry (``policy_kwargs``, and the non-pickled parts sb3 writes beside each pickled ``:serialized:``
  value: the observation space's ``_shape`` and ``dtype``, the action space's ``n``), checked against the weights.
- **cleanrl**: a state dict saved with ``torch.save(agent.state_dict())`` from CleanRL's ``ppo_atari_lstm.py``
  ``Agent``: its Atari CNN (``network.{0,2,4}`` Conv2d layers, a Flatten, ``network.7`` Linear, each layer followed
  by ReLU; the strides, which a state dict does not record, are CleanRL's 4, 2, 1 or given) or an MLP in its place
  (``network.{0,2,...}`` linear layers, each followed by the activation), ``lstm.*`` (``nn.LSTM``), ``actor`` and
  ``critic``.

The policy path (observation -> LSTM -> policy MLP -> logits) is imported exactly. sb3-contrib's default critic has a
separate LSTM (``enable_critic_lstm=True``) or, with ``enable_critic_lstm=False``, a linear layer on the
observation; this network has one LSTM stack, which the monitors, interventions and analyses read as *the* agent's
memory, so such a critic is not imported: the value MLP keeps sb3's shapes and weights (a starting point for
fine-tuning) and the value head is zero, so the value is 0 (``provenance.value = "zeroed"``). Evaluation, analysis
and the defenses read only the policy; PPO fine-tuning learns a new value. A ``shared_lstm=True`` critic and
CleanRL's critic are imported exactly (``provenance.value = "imported"``).

Every file is untrusted: sizes are checked before anything is read or decompressed (:data:`MAX_DATA_BYTES`,
:data:`MAX_WEIGHTS_BYTES`, also the entries of the torch archive inside), and a zip entry is read in chunks, never
past its declared size or the limit (a zip bomb whose header lies stops there). The weights are loaded memory-mapped
(``torch.load(mmap=True)``), so that each tensor's shape and the parameter counts (:data:`MAX_FILE_PARAMETERS`, and
the model card's ``MAX_PARAMETERS`` for the imported network) are checked before any tensor is read into memory or
the network is built; every tensor's name and shape is checked against the architecture, NaN or infinite weights
are refused, and any refusal is one :class:`~seqtrojan.errors.CheckpointError` line, raised before anything is
written.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import re
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any, Literal, cast

import torch

from seqtrojan.agent.card import MAX_DETAIL_CHARS, MAX_PARAMETERS, MAX_RANK, Architecture, load_json
from seqtrojan.agent.checkpoint import build_agent, save_agent
from seqtrojan.agent.network import conv_output_side
from seqtrojan.config import MAX_CONV_KERNEL, MAX_CONV_STRIDE, MAX_LAYERS, AgentConfig, ExperimentConfig
from seqtrojan.env.codes import ACTION_SETS, CELL_NAMES
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.folders import LOCK_FILE, folder_lock, make_output_folder
from seqtrojan.world import EnvSpec, env_spec

__all__ = [
    "MAX_DATA_BYTES", "MAX_WEIGHTS_BYTES", "SOURCES", "Imported", "import_agent", "provenance_of", "read_cleanrl",
    "read_foreign", "read_sb3",
]  # fmt: skip

SOURCES = ("sb3", "cleanrl")
MAX_DATA_BYTES = 64 << 20
"""largest ``data`` entry of an sb3 zip read (a real one is tens of KiB; it holds the last observations, pickled)"""
MAX_WEIGHTS_BYTES = 1 << 30
"""largest weights file (sb3's ``policy.pth`` entry or a CleanRL state dict), and the most its torch archive's
entries may hold together once decompressed (a model card allows 2^26 parameters, 256 MiB as float32; an sb3 policy
holds a second LSTM for its critic)"""
MAX_VERSION_BYTES = 256
"""largest ``_stable_baselines3_version`` entry read"""
MAX_TENSORS = 256
"""most tensors in an imported state dict"""
MAX_FILE_PARAMETERS = 2 * MAX_PARAMETERS
"""most numbers in all the tensors of a weights file together (an sb3 policy holds the network, at most a model
card's ``MAX_PARAMETERS``, and a second LSTM for its critic); one tensor holds at most ``MAX_PARAMETERS``"""
_CHUNK = 1 << 20
"""bytes read from a zip entry at a time"""

SB3_POLICY_MODULE = "sb3_contrib.common.recurrent.policies"
SB3_POLICY_CLASS = "RecurrentActorCriticPolicy"
"""sb3-contrib's class behind ``"MlpLstmPolicy"``"""
SB3_ACTIVATIONS = {"Tanh": "tanh", "ReLU": "relu"}
"""sb3 ``activation_fn`` classes (torch.nn) that have a counterpart here"""
_LSTM_KEY = re.compile(r"(weight_ih|weight_hh|bias_ih|bias_hh)_l([0-9]+)")
_CLASS_NAME = re.compile(r"<class '([A-Za-z0-9_.]+)'>")
_INIT_OF = re.compile(r"<function ([A-Za-z0-9_]+)\.__init__ at ")


@dataclasses.dataclass(frozen=True)
class Imported:
    """An agent read from a foreign file, ready to be built here: the network's parts and its tensors (our names)."""

    source: str
    """'sb3' or 'cleanrl'"""
    obs_dim: int
    num_actions: int
    agent: AgentConfig
    tensors: Mapping[str, torch.Tensor] = dataclasses.field(repr=False)
    """the state dict of :class:`~seqtrojan.agent.network.RecurrentActorCritic` (float32)"""
    value: str
    """'imported' (the value head computes the original's value) or 'zeroed'"""
    details: Mapping[str, Any]
    """what the card's ``provenance.details`` records (versions, the original's layout)"""
    env_steps: int | None = None


# ---------------------------------------------------------------------- sb3


def read_sb3(path: str | Path) -> Imported:
    """Read an sb3-contrib ``RecurrentPPO`` zip (``MlpLstmPolicy``) without unpickling anything."""
    path = Path(path)
    where = repr(str(path))
    if not path.is_file():
        raise CheckpointError(f"{where} does not exist or is not a file")
    try:
        with zipfile.ZipFile(path) as archive:
            entries = {info.filename: info for info in archive.infolist()}
            for name in ("data", "policy.pth"):
                if name not in entries:
                    raise CheckpointError(
                        f"{where} has no {name!r} entry: not a stable-baselines3 model zip (it holds "
                        f"{_clip(sorted(entries)[:8])})"
                    )
            data_raw = _read_entry(archive, entries["data"], MAX_DATA_BYTES, where)
            version = None
            if "_stable_baselines3_version" in entries:
                text = _read_entry(archive, entries["_stable_baselines3_version"], MAX_VERSION_BYTES, where)
                version = text.decode("utf-8", "replace").strip()
            data = load_json(data_raw, f"the 'data' entry of {where}")
            if not isinstance(data, dict):
                raise CheckpointError(f"the 'data' entry of {where} is not a JSON object")
            _check_sb3_policy_class(data.get("policy_class"), where)
            kwargs = _plain_items(data.get("policy_kwargs") or {})
            obs_shape = _sb3_observation_shape(data.get("observation_space"), where)
            declared_actions = _sb3_action_count(data.get("action_space"), where)
            with tempfile.TemporaryDirectory(prefix="seqtrojan-import-") as scratch:
                weights = Path(scratch) / "policy.pth"  # extracted to disk, so that it loads memory-mapped
                with weights.open("wb") as fh:
                    _copy_entry(archive, entries["policy.pth"], MAX_WEIGHTS_BYTES, where, fh)
                sd = _load_state_dict(weights, f"'policy.pth' in {where}")
                return _map_sb3(sd, kwargs, obs_shape, declared_actions, data, version, where)
    except zipfile.BadZipFile as err:
        raise CheckpointError(f"{where} is not a valid zip file: {err}") from None


def _map_sb3(
    sd: dict[str, torch.Tensor],
    kwargs: dict[str, Any],
    obs_shape: tuple[int, ...] | None,
    declared_actions: int | None,
    data: dict[str, Any],
    version: str | None,
    where: str,
) -> Imported:
    if "log_std" in sd:
        raise CheckpointError(f"{where} has a continuous action distribution (log_std): only Discrete actions import")
    if not any(k.startswith("lstm_actor.") for k in sd):
        raise CheckpointError(
            f"{where} has no lstm_actor weights: not a recurrent policy (only sb3-contrib RecurrentPPO's MlpLstmPolicy "
            f"imports)"
        )
    for key in sd:
        if key.startswith(("features_extractor.", "pi_features_extractor.", "vf_features_extractor.")):
            raise CheckpointError(
                f"{where} has features-extractor weights ({key!r}): only the FlattenExtractor of MlpLstmPolicy imports"
            )
    lstm = _lstm_layers(sd, "lstm_actor", where)
    hidden, obs_dim = lstm[0][1], lstm[0][0]
    _agree(kwargs, "lstm_hidden_size", hidden, where)
    _agree(kwargs, "n_lstm_layers", len(lstm), where)
    if obs_shape is not None and math.prod(obs_shape) != obs_dim:
        raise CheckpointError(
            f"{where}: the observation space has shape {list(obs_shape)} ({math.prod(obs_shape)} inputs) but "
            f"lstm_actor.weight_ih_l0 reads {obs_dim}"
        )
    activation_name = kwargs.get("activation_fn")
    activation = "tanh"
    if activation_name is not None:
        match = _CLASS_NAME.fullmatch(str(activation_name))
        short = match.group(1).rpartition(".")[2] if match else str(activation_name)
        if short not in SB3_ACTIVATIONS or (match and not match.group(1).startswith("torch.nn.")):
            raise CheckpointError(
                f"{where}: activation_fn {_clip(activation_name)} has no counterpart here (torch.nn.Tanh or ReLU)"
            )
        activation = SB3_ACTIVATIONS[short]
    extractor = kwargs.get("features_extractor_class")
    if extractor is not None and "FlattenExtractor" not in str(extractor):
        raise CheckpointError(f"{where}: features_extractor_class {_clip(extractor)} is not FlattenExtractor")
    pi = _mlp_layers(sd, "mlp_extractor.policy_net", hidden, where)
    vf = _mlp_layers(sd, "mlp_extractor.value_net", hidden, where)
    net_arch = kwargs.get("net_arch")
    if net_arch is not None:
        want = net_arch if isinstance(net_arch, dict) else {"pi": net_arch, "vf": net_arch}
        for part, got in (("pi", pi), ("vf", vf)):
            if isinstance(want, dict) and part in want and list(want[part]) != list(got):
                raise CheckpointError(
                    f"{where}: policy_kwargs.net_arch.{part} is {_clip(want[part])} but the weights have layers "
                    f"{list(got)}"
                )
    action_in = pi[-1] if pi else hidden
    num_actions = _dim(sd, "action_net.weight", 0, where)
    value_in = vf[-1] if vf else hidden
    expected: dict[str, tuple[int, ...]] = {
        "action_net.weight": (num_actions, action_in), "action_net.bias": (num_actions,),
        "value_net.weight": (1, value_in), "value_net.bias": (1,),
    }  # fmt: skip
    if declared_actions is not None and declared_actions != num_actions:
        raise CheckpointError(
            f"{where}: the action space has {declared_actions} actions but action_net.weight has {num_actions} rows"
        )
    # the critic: a separate LSTM (sb3-contrib's default), a linear layer on the observation, or the actor's LSTM
    if any(k.startswith("lstm_critic.") for k in sd):
        critic = "lstm"
        critic_lstm = _lstm_layers(sd, "lstm_critic", where)
        if critic_lstm != lstm:
            raise CheckpointError(f"{where}: lstm_critic's shapes {critic_lstm} differ from lstm_actor's {lstm}")
    elif "critic.weight" in sd or "critic.bias" in sd:
        critic = "linear"
        expected["critic.weight"], expected["critic.bias"] = (hidden, obs_dim), (hidden,)
    else:
        critic = "shared"
    flags = (kwargs.get("shared_lstm", False), kwargs.get("enable_critic_lstm", True))  # sb3-contrib's defaults
    said = "shared" if flags[0] is True else "lstm" if flags[1] is True else "linear"
    if said != critic:
        raise CheckpointError(
            f"{where}: policy_kwargs (shared_lstm={flags[0]}, enable_critic_lstm={flags[1]}) describe a {said} "
            f"critic but the weights hold a {critic} one"
        )
    known = {k for k in sd if k.startswith(("lstm_actor.", "lstm_critic.", "mlp_extractor."))}
    _check_shapes(sd, expected, known, where)
    ours: dict[str, torch.Tensor] = {}
    for k in range(len(lstm)):
        for part in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            ours[f"cells.{k}.{part}"] = sd[f"lstm_actor.{part}_l{k}"]
    for j in range(len(pi)):
        ours[f"policy_mlp.{j}.weight"] = sd[f"mlp_extractor.policy_net.{2 * j}.weight"]
        ours[f"policy_mlp.{j}.bias"] = sd[f"mlp_extractor.policy_net.{2 * j}.bias"]
    for j in range(len(vf)):
        ours[f"value_mlp.{j}.weight"] = sd[f"mlp_extractor.value_net.{2 * j}.weight"]
        ours[f"value_mlp.{j}.bias"] = sd[f"mlp_extractor.value_net.{2 * j}.bias"]
    ours["policy_head.weight"], ours["policy_head.bias"] = sd["action_net.weight"], sd["action_net.bias"]
    exact = critic == "shared"
    ours["value_head.weight"] = sd["value_net.weight"] if exact else torch.zeros(1, value_in)
    ours["value_head.bias"] = sd["value_net.bias"] if exact else torch.zeros(1)
    env_steps = data.get("num_timesteps")
    details = {
        "format": "stable-baselines3 zip", "sb3_version": _text(version), "policy": SB3_POLICY_CLASS,
        "critic": critic, "observation_shape": list(obs_shape) if obs_shape is not None else None,
    }  # fmt: skip
    agent = AgentConfig(
        lstm_sizes=(hidden,) * len(lstm), policy_mlp=pi, value_mlp=vf, mlp_activation=_activation(activation)
    )
    return Imported(
        "sb3", obs_dim, num_actions, agent,
        _network_tensors(ours, where), "imported" if exact else "zeroed", details,
        env_steps if type(env_steps) is int and env_steps >= 0 else None,
    )  # fmt: skip


def _check_sb3_policy_class(value: Any, where: str) -> None:
    """Refuse a policy class other than sb3-contrib's recurrent MLP policy, read from the non-pickled JSON items
    (``__module__`` and the ``__init__`` function's repr) where sb3 wrote them."""
    if not isinstance(value, dict):
        return  # the weights are checked anyway
    module = value.get("__module__")
    if isinstance(module, str) and module != SB3_POLICY_MODULE:
        raise CheckpointError(
            f"{where}: the policy class comes from {_clip(module)}, not {SB3_POLICY_MODULE}: only sb3-contrib "
            f"RecurrentPPO's MlpLstmPolicy (an LSTM policy) imports"
        )
    init = value.get("__init__")
    match = _INIT_OF.match(init) if isinstance(init, str) else None
    if match and match.group(1) != SB3_POLICY_CLASS:
        raise CheckpointError(
            f"{where}: the policy class is {match.group(1)}, not {SB3_POLICY_CLASS} (MlpLstmPolicy): CNN and "
            f"multi-input policies do not import"
        )


def _plain_items(value: Any) -> dict[str, Any]:
    """A JSON object sb3 wrote, without its pickled ``:type:`` / ``:serialized:`` items (never decoded)."""
    if not isinstance(value, dict):
        return {}
    return {k: v for k, v in value.items() if not (isinstance(k, str) and k.startswith(":"))}


def _sb3_observation_shape(value: Any, where: str) -> tuple[int, ...] | None:
    if not isinstance(value, dict):
        return None
    kind = value.get(":type:")
    if isinstance(kind, str) and not kind.endswith(".Box'>"):
        raise CheckpointError(
            f"{where}: the observation space is {_clip(kind)}; only a Box of numbers imports (flattened, as sb3's "
            f"FlattenExtractor reads it)"
        )
    shape = value.get("_shape")
    if shape is None:
        return None
    if not isinstance(shape, list) or len(shape) > MAX_RANK or any(type(d) is not int or d < 1 for d in shape):
        raise CheckpointError(f"{where}: the observation space has an invalid shape {_clip(shape)}")
    dtype = value.get("dtype")
    if dtype == "uint8" and len(shape) == 3:
        raise CheckpointError(
            f"{where}: the observation space is a uint8 image {shape}, which sb3 scales by 1/255 before the policy: "
            f"image policies do not import"
        )
    return tuple(shape)


def _sb3_action_count(value: Any, where: str) -> int | None:
    if not isinstance(value, dict):
        return None
    kind = value.get(":type:")
    if isinstance(kind, str) and not kind.endswith(".Discrete'>"):
        raise CheckpointError(
            f"{where}: the action space is {_clip(kind)}, not Discrete: continuous and multi-discrete policies do not "
            f"import (seqtrojan agents choose one of a few discrete actions)"
        )
    start = value.get("start")
    if start is not None and str(start) not in ("0", "0.0"):
        raise CheckpointError(f"{where}: the Discrete action space starts at {_clip(start)}; only start 0 imports")
    n = value.get("n")
    if n is None:
        return None
    try:
        return int(str(n))
    except ValueError:
        raise CheckpointError(f"{where}: the action space's n is {_clip(n)}, not an integer") from None


# ---------------------------------------------------------------------- CleanRL


CLEANRL_NATURE_KERNELS = (8, 4, 3)
"""the kernels of CleanRL's Atari CNN (the Nature CNN of ``ppo_atari_lstm.py``: Conv 32 8x8, 64 4x4, 64 3x3)"""
CLEANRL_NATURE_STRIDES = (4, 2, 1)
"""its strides (a state dict does not record strides: these are assumed for those kernels, else given)"""


def read_cleanrl(
    path: str | Path,
    obs_dim: int,
    num_actions: int,
    activation: str = "relu",
    *,
    image: tuple[int, int, int] | None = None,
    conv_strides: tuple[int, ...] | None = None,
) -> Imported:
    """Read a CleanRL LSTM agent's state dict (``ppo_atari_lstm.py``'s ``Agent``: its Atari CNN, or an MLP in its
    place). A CNN reads the observation as the image ``image`` (rows, cols, channels: the env's, see
    :func:`import_agent`); ``conv_strides`` gives each conv layer's stride (default: CleanRL's 4, 2, 1 for the
    Nature CNN's kernels 8, 4, 3; required for any other kernels)."""
    path = Path(path)
    where = repr(str(path))
    if not path.is_file():
        raise CheckpointError(f"{where} does not exist or is not a file")
    if activation not in SB3_ACTIVATIONS.values():
        raise ConfigError(f"activation must be one of {tuple(SB3_ACTIVATIONS.values())}, got {activation!r}")
    size = path.stat().st_size
    if size > MAX_WEIGHTS_BYTES:
        raise CheckpointError(f"{where} has {size} bytes, more than the limit of {MAX_WEIGHTS_BYTES}")
    sd = _load_state_dict(path, where)
    if "lstm.weight_ih_l0" not in sd:
        raise CheckpointError(f"{where} has no lstm.weight_ih_l0: not a CleanRL LSTM agent's state dict")
    lstm = _lstm_layers(sd, "lstm", where)
    hidden = lstm[0][1]
    network = _cleanrl_network(sd, where)
    convs, linear_at = network.convs, network.linear_at
    encoder: tuple[int, ...] = ()
    kernels: tuple[int, ...] = ()
    strides: tuple[int, ...] = ()
    if convs:
        kernels = tuple(k for _, _, k in convs)
        strides = _cleanrl_strides(kernels, conv_strides, where)
        features = _cleanrl_conv_features(convs, kernels, strides, obs_dim, image, where)
    elif conv_strides:
        raise ConfigError(f"--conv-strides {list(conv_strides)}: {where} has no conv layers (network.* are linear)")
    else:
        features = obs_dim
    if linear_at:
        encoder = _mlp_chain(sd, "network", linear_at, features if convs else None, where)
    first_in = lstm[0][0]  # what the agent's first layer reads (a CNN's image was checked against obs_dim)
    if convs:
        first_in = obs_dim
    elif linear_at:
        first_in = _dim(sd, f"network.{linear_at[0]}.weight", 1, where)
    if first_in != obs_dim:
        raise CheckpointError(f"{where}: the agent reads {first_in} observation inputs, not --obs-dim {obs_dim}")
    lstm_in = encoder[-1] if encoder else features
    if lstm[0][0] != lstm_in:
        raise CheckpointError(
            f"{where}: lstm.weight_ih_l0 reads {lstm[0][0]} inputs but the last network layer gives {lstm_in}"
        )
    expected = {
        "actor.weight": (num_actions, hidden), "actor.bias": (num_actions,),
        "critic.weight": (1, hidden), "critic.bias": (1,),
    }  # fmt: skip
    known = {k for k in sd if k.startswith(("lstm.", "network."))}
    _check_shapes(sd, expected, known, where, hint=f"--actions {num_actions}")
    ours: dict[str, torch.Tensor] = {}
    for j, index in enumerate(range(0, 2 * len(convs), 2)):
        ours[f"conv.{j}.weight"], ours[f"conv.{j}.bias"] = sd[f"network.{index}.weight"], sd[f"network.{index}.bias"]
    for j, index in enumerate(linear_at):
        ours[f"encoder.{j}.weight"] = sd[f"network.{index}.weight"]
        ours[f"encoder.{j}.bias"] = sd[f"network.{index}.bias"]
    for k in range(len(lstm)):
        for part in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            ours[f"cells.{k}.{part}"] = sd[f"lstm.{part}_l{k}"]
    ours["policy_head.weight"], ours["policy_head.bias"] = sd["actor.weight"], sd["actor.bias"]
    ours["value_head.weight"], ours["value_head.bias"] = sd["critic.weight"], sd["critic.bias"]
    agent = AgentConfig(
        lstm_sizes=(hidden,) * len(lstm), encoder=encoder, encoder_activation=_activation(activation),
        conv=tuple(c for c, _, _ in convs), conv_kernels=kernels, conv_strides=strides,
    )  # fmt: skip
    layout = "Atari CNN" if convs else "MLP encoder"
    details: dict[str, Any] = {"format": f"CleanRL LSTM state dict (ppo_atari_lstm.py layout, {layout})"}
    if convs:
        details["conv_strides"] = list(strides)
    return Imported("cleanrl", obs_dim, num_actions, agent, _network_tensors(ours, where), "imported", details)


@dataclasses.dataclass(frozen=True)
class _CleanRLNetwork:
    convs: tuple[tuple[int, int, int], ...]
    """each Conv2d's (out channels, in channels, kernel side), at network.0, 2, 4, ..."""
    linear_at: tuple[int, ...]
    """the indices of the Linear layers (after the Flatten that follows the convs)"""


def _cleanrl_network(sd: dict[str, torch.Tensor], where: str) -> _CleanRLNetwork:
    """The layers of CleanRL's ``network`` ``Sequential``: Conv2d layers at 0, 2, ... (each followed by its ReLU),
    then, after a ``Flatten``, Linear layers (each followed by the activation): CleanRL's Atari CNN is
    ``network.{0,2,4}`` (convs), 6 (Flatten), ``network.7`` (Linear 3136 -> 512). Without convs, Linear layers at
    0, 2, ... (an MLP in the CNN's place)."""
    indices: dict[int, set[str]] = {}
    for key in sd:
        if key.startswith("network."):
            position, _, part = key[len("network.") :].partition(".")
            if not position.isdigit() or len(position) > 4 or part not in ("weight", "bias"):
                raise CheckpointError(f"{where}: {key!r} is not a layer's weight or bias")
            indices.setdefault(int(position), set()).add(part)
    for index, parts in sorted(indices.items()):
        if parts != {"weight", "bias"}:
            raise CheckpointError(f"{where}: network.{index} lacks its {sorted({'weight', 'bias'} - parts)}")
    order = sorted(indices)
    conv_at = [i for i in order if sd[f"network.{i}.weight"].dim() == 4]
    linear_at = [i for i in order if i not in conv_at]
    first_linear = 2 * len(conv_at) + 1 if conv_at else 0
    expected_convs = list(range(0, 2 * len(conv_at), 2))
    expected_linears = list(range(first_linear, first_linear + 2 * len(linear_at), 2))
    if conv_at != expected_convs or linear_at != expected_linears or len(conv_at) > MAX_LAYERS:
        raise CheckpointError(
            f"{where}: the layers under network sit at {_clip(order)} (convs at {_clip(conv_at)}); expected at most "
            f"{MAX_LAYERS} Conv2d layers at 0, 2, ..., then after a Flatten Linear layers at 2k + 1, 2k + 3, ... "
            "(CleanRL's Sequential: each layer followed by its activation)"
        )
    convs: list[tuple[int, int, int]] = []
    for j, index in enumerate(conv_at):
        w, b = list(sd[f"network.{index}.weight"].shape), list(sd[f"network.{index}.bias"].shape)
        reads = convs[-1][0] if convs else w[1]
        if b != [w[0]] or w[1] != reads or w[2] != w[3] or not 1 <= w[2] <= MAX_CONV_KERNEL or min(w) < 1:
            raise CheckpointError(
                f"{where}: network.{index} has weight {w} and bias {b}: not a Conv2d with a square kernel of at "
                f"most {MAX_CONV_KERNEL}" + (f" reading the {reads} channels before it" if j else "")
            )
        convs.append((w[0], w[1], w[2]))
    return _CleanRLNetwork(tuple(convs), tuple(linear_at))


def _cleanrl_strides(kernels: tuple[int, ...], given: tuple[int, ...] | None, where: str) -> tuple[int, ...]:
    """The conv strides: ``given`` (one per layer), or CleanRL's Nature CNN's for its kernels."""
    if given is None or not len(given):
        if kernels == CLEANRL_NATURE_KERNELS:
            return CLEANRL_NATURE_STRIDES
        raise ConfigError(
            f"{where} has conv kernels {list(kernels)}, not CleanRL's Nature CNN ({list(CLEANRL_NATURE_KERNELS)}): "
            "a state dict does not record strides, pass --conv-strides (one per conv layer)"
        )
    strides = tuple(given)
    if len(strides) != len(kernels) or any(
        isinstance(s, bool) or not isinstance(s, int) or not 1 <= s <= MAX_CONV_STRIDE for s in strides
    ):
        raise ConfigError(
            f"--conv-strides {_clip(list(strides))}: one integer in [1, {MAX_CONV_STRIDE}] per conv layer "
            f"({len(kernels)})"
        )
    return strides


def _cleanrl_conv_features(
    convs: tuple[tuple[int, int, int], ...],
    kernels: tuple[int, ...],
    strides: tuple[int, ...],
    obs_dim: int,
    image: tuple[int, int, int] | None,
    where: str,
) -> int:
    """The features the convs give for the env's image (checked against the observation and the first conv)."""
    if image is None:
        raise CheckpointError(
            f"{where}: a CNN agent reads an image; pass --config with an env whose observation is one "
            "(env.observation: image, e.g. the atari_breakout preset)"
        )
    rows, cols, chans = image
    if rows * cols * chans != obs_dim or chans != convs[0][1]:
        raise CheckpointError(
            f"{where}: network.0 reads {convs[0][1]} channels, but the env's image is {rows}x{cols}x{chans} "
            f"({rows * cols * chans} inputs; --obs-dim {obs_dim})"
        )
    out_rows, out_cols = (conv_output_side(n, kernels, strides) for n in (rows, cols))
    if not out_rows or not out_cols:
        raise CheckpointError(
            f"{where}: conv kernels {list(kernels)} with strides {list(strides)} do not fit the {rows}x{cols} image"
        )
    return out_rows * out_cols * convs[-1][0]


# ---------------------------------------------------------------------- shared checks


def _read_entry(archive: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int, where: str) -> bytes:
    """An entry's bytes (at most ``limit``; see :func:`_copy_entry`)."""
    buffer = io.BytesIO()
    _copy_entry(archive, info, limit, where, buffer)
    return buffer.getvalue()


def _copy_entry(archive: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int, where: str, out: IO[bytes]) -> int:
    """Copy an entry's bytes to ``out`` in chunks: refused before decompression when its declared size exceeds
    ``limit``, and stopped one byte past the declared size, whatever the compressed data holds (a zip bomb whose
    header declares a small size). Returns the bytes copied."""
    if info.file_size > limit:
        raise CheckpointError(
            f"the {info.filename!r} entry of {where} unpacks to {info.file_size} bytes, more than the limit of "
            f"{limit}: refusing to read it"
        )
    copied = 0
    try:
        with archive.open(info) as fh:
            while chunk := fh.read(min(_CHUNK, info.file_size + 1 - copied)):
                copied += len(chunk)
                if copied > info.file_size:
                    raise CheckpointError(
                        f"the {info.filename!r} entry of {where} unpacks to more than the {info.file_size} bytes "
                        f"its header declares: refusing to read it"
                    )
                out.write(chunk)
    except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError, RuntimeError) as err:
        raise CheckpointError(
            f"the {info.filename!r} entry of {where} cannot be read: {_clip_text(str(err))}"
        ) from None
    return copied


def _load_state_dict(path: Path, where: str) -> dict[str, torch.Tensor]:
    """``torch.load(weights_only=True, mmap=True)`` of a torch zip archive on disk, after bounding what its entries
    hold: a flat mapping of names to float tensors whose sizes are checked before any is read into memory (they
    stay mapped from the file)."""
    with path.open("rb") as fh:
        magic = fh.read(2)
    if magic != b"PK":
        raise CheckpointError(
            f"{where} is not a torch zip archive (torch.save's format since torch 1.6): refusing to read it"
        )
    _check_torch_archive(path, where)
    try:
        loaded = torch.load(str(path), map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:  # weights_only refuses any pickled object that is not tensors and plain containers
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise CheckpointError(
            f"{where} holds more than weights (torch.load(weights_only=True) refused it: {type(err).__name__}: "
            f"{_clip_text(first)}); refusing to unpickle it"
        ) from None
    if not isinstance(loaded, Mapping):
        raise CheckpointError(f"{where} holds a {type(loaded).__name__}, not a state dict (names -> tensors)")
    if len(loaded) > MAX_TENSORS:
        raise CheckpointError(f"{where} holds {len(loaded)} entries, more than the limit of {MAX_TENSORS}")
    out: dict[str, torch.Tensor] = {}
    for key, value in loaded.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise CheckpointError(
                f"{where}: entry {_clip(key)} is a {type(value).__name__}, not a tensor: not a state dict"
            )
        if not value.is_floating_point() or value.dim() > MAX_RANK or value.numel() > MAX_PARAMETERS:
            raise CheckpointError(
                f"{where}: tensor {_clip(key)} has dtype {value.dtype} and shape {_clip(list(value.shape))} (a "
                f"weight is a float tensor of at most {MAX_RANK} dimensions and {MAX_PARAMETERS} numbers)"
            )
        out[key] = value.detach()
    total = sum(v.numel() for v in out.values())
    if total > MAX_FILE_PARAMETERS:
        raise CheckpointError(
            f"{where} holds {total} numbers in its tensors, more than the limit of {MAX_FILE_PARAMETERS}: refusing "
            f"to read them"
        )
    return out


def _check_torch_archive(path: Path, where: str) -> None:
    """The entries of a torch archive, from its directory: torch.save stores them uncompressed, and together they
    may hold at most :data:`MAX_WEIGHTS_BYTES`."""
    try:
        with zipfile.ZipFile(path) as inner:
            infos = inner.infolist()
    except zipfile.BadZipFile as err:
        raise CheckpointError(f"{where} is not a valid torch archive: {err}") from None
    unpacked = sum(info.file_size for info in infos)
    if unpacked > MAX_WEIGHTS_BYTES:
        raise CheckpointError(
            f"{where} unpacks to {unpacked} bytes, more than the limit of {MAX_WEIGHTS_BYTES}: refusing to read it"
        )
    packed = [info.filename for info in infos if info.compress_type != zipfile.ZIP_STORED]
    if packed:
        raise CheckpointError(
            f"{where} has compressed entries ({_clip(packed[:3])}), which torch.save never writes: refusing to read it"
        )


def _network_tensors(ours: dict[str, torch.Tensor], where: str) -> dict[str, torch.Tensor]:
    """The imported network's tensors as float32 copies, after checking its parameter count against a model card's
    limit (from the shapes: before anything is copied or the network is built); every value must be finite."""
    total = sum(v.numel() for v in ours.values())
    if total > MAX_PARAMETERS:
        raise CheckpointError(
            f"{where}: the imported network would have {total} parameters, more than the limit of {MAX_PARAMETERS} "
            f"a model may have"
        )
    copies = {k: v.to(dtype=torch.float32, memory_format=torch.contiguous_format, copy=True) for k, v in ours.items()}
    bad = sorted(k for k, v in copies.items() if not bool(torch.isfinite(v).all()))
    if bad:
        raise CheckpointError(f"{where}: the weights hold NaN or infinite values (imported as {_clip(bad)})")
    return copies


def _lstm_layers(sd: dict[str, torch.Tensor], prefix: str, where: str) -> list[tuple[int, int]]:
    """The (input size, hidden size) of each layer of the ``nn.LSTM`` stored under ``prefix``; every tensor's shape
    is checked, and any other tensor under ``prefix`` (projections, a reverse direction) is refused."""
    layers: dict[int, set[str]] = {}
    for key in sd:
        if key.startswith(prefix + "."):
            match = _LSTM_KEY.fullmatch(key[len(prefix) + 1 :])
            if match is None:
                raise CheckpointError(
                    f"{where}: {key!r} is not a weight of a one-directional LSTM without projections (expected "
                    f"{prefix}.weight_ih_l0, weight_hh_l0, bias_ih_l0, bias_hh_l0, ...)"
                )
            layers.setdefault(int(match.group(2)), set()).add(match.group(1))
    if sorted(layers) != list(range(len(layers))) or not layers:
        raise CheckpointError(f"{where}: the layers of {prefix} are {sorted(layers)}, not 0, 1, ...")
    out: list[tuple[int, int]] = []
    for k in range(len(layers)):
        missing = sorted({"weight_ih", "weight_hh", "bias_ih", "bias_hh"} - layers[k])
        if missing:
            raise CheckpointError(f"{where}: {prefix} layer {k} lacks {[f'{prefix}.{m}_l{k}' for m in missing]}")
        hidden = _dim(sd, f"{prefix}.weight_hh_l{k}", 1, where)
        n_in = _dim(sd, f"{prefix}.weight_ih_l{k}", 1, where) if k == 0 else hidden
        expected = {
            f"{prefix}.weight_ih_l{k}": (4 * hidden, n_in), f"{prefix}.weight_hh_l{k}": (4 * hidden, hidden),
            f"{prefix}.bias_ih_l{k}": (4 * hidden,), f"{prefix}.bias_hh_l{k}": (4 * hidden,),
        }  # fmt: skip
        if k > 0 and hidden != out[0][1]:
            raise CheckpointError(f"{where}: {prefix} layer {k} has {hidden} units, layer 0 {out[0][1]}")
        for name, shape in expected.items():
            if tuple(sd[name].shape) != shape or hidden < 1:
                actual = list(sd[name].shape)
                raise CheckpointError(f"{where}: tensor {name!r} has shape {actual}, expected {list(shape)}")
        out.append((n_in, hidden))
    return out


def _mlp_layers(sd: dict[str, torch.Tensor], prefix: str, n_in: int | None, where: str) -> tuple[int, ...]:
    """The widths of the linear layers of an ``nn.Sequential(Linear, activation, Linear, activation, ...)`` stored
    under ``prefix`` (indices 0, 2, 4, ...), each reading the previous one's output (the first ``n_in``, if given)."""
    indices: dict[int, set[str]] = {}
    for key in sd:
        if key.startswith(prefix + "."):
            position, _, part = key[len(prefix) + 1 :].partition(".")
            if not position.isdigit() or part not in ("weight", "bias"):
                raise CheckpointError(f"{where}: {key!r} is not a linear layer's weight or bias")
            indices.setdefault(int(position), set()).add(part)
    expected_indices = list(range(0, 2 * len(indices), 2))
    if sorted(indices) != expected_indices:
        raise CheckpointError(
            f"{where}: the layers under {prefix} sit at {sorted(indices)}; expected linear layers at "
            f"{expected_indices} (Linear, activation, Linear, activation, ...)"
        )
    for index in expected_indices:
        if indices[index] != {"weight", "bias"}:
            raise CheckpointError(f"{where}: {prefix}.{index} lacks its {sorted({'weight', 'bias'} - indices[index])}")
    return _mlp_chain(sd, prefix, tuple(expected_indices), n_in, where)


def _mlp_chain(
    sd: dict[str, torch.Tensor], prefix: str, at: tuple[int, ...], n_in: int | None, where: str
) -> tuple[int, ...]:
    """The widths of the linear layers ``prefix.{i}`` for ``i`` in ``at``, each reading the previous one's output
    (the first ``n_in``, if given)."""
    widths: list[int] = []
    for j, index in enumerate(at):
        w, b = sd[f"{prefix}.{index}.weight"].shape, sd[f"{prefix}.{index}.bias"].shape
        reads = n_in if j == 0 else widths[-1]
        if len(w) != 2 or tuple(b) != (w[0],) or (reads is not None and w[1] != reads) or w[0] < 1:
            raise CheckpointError(
                f"{where}: {prefix}.{index} has weight {list(w)} and bias {list(b)}, which do not chain"
                + (f" from {reads} inputs" if reads is not None else "")
            )
        widths.append(int(w[0]))
    return tuple(widths)


def _check_shapes(
    sd: dict[str, torch.Tensor], expected: dict[str, tuple[int, ...]], known: set[str], where: str, hint: str = ""
) -> None:
    for name, shape in expected.items():
        if name not in sd:
            raise CheckpointError(f"{where} lacks the tensor {name!r}")
        if tuple(sd[name].shape) != shape:
            because = f" (for {hint})" if hint else ""
            actual = list(sd[name].shape)
            raise CheckpointError(f"{where}: tensor {name!r} has shape {actual}, expected {list(shape)}{because}")
    unexpected = sorted(set(sd) - set(expected) - known)
    if unexpected:
        raise CheckpointError(f"{where} has tensor(s) this layout does not have: {_clip(unexpected)}")


def _dim(sd: dict[str, torch.Tensor], name: str, axis: int, where: str) -> int:
    """Size ``axis`` of the matrix ``name``."""
    if name not in sd:
        raise CheckpointError(f"{where} lacks the tensor {name!r}")
    shape = list(sd[name].shape)
    if len(shape) != 2 or shape[axis] < 1:
        raise CheckpointError(f"{where}: tensor {name!r} has shape {shape}, not a weight matrix")
    return shape[axis]


def _agree(kwargs: dict[str, Any], key: str, actual: int, where: str) -> None:
    if key in kwargs and kwargs[key] != actual:
        raise CheckpointError(f"{where}: policy_kwargs.{key} is {_clip(kwargs[key])} but the weights have {actual}")


# ---------------------------------------------------------------------- writing


def import_agent(
    source: str,
    path: str | Path,
    out: str | Path,
    *,
    config: ExperimentConfig | None = None,
    label: str | None = None,
    obs_dim: int | None = None,
    num_actions: int | None = None,
    activation: str = "relu",
    conv_strides: tuple[int, ...] | None = None,
) -> Path:
    """Import ``path`` (``source`` 'sb3' or 'cleanrl') into the model folder ``out``; returns ``out``.

    ``config`` describes the env the agent acts in (its ``env`` must give the agent's observation size and action
    count; default: the default config, the 3x3 view and four moves). ``label`` is what the caller states; None
    writes 'unknown' with ``provenance.label_stated = false`` (evaluated in both envs, never ground truth).
    ``obs_dim`` and ``num_actions`` are required for
    'cleanrl' and checked against the weights; ``activation`` is CleanRL's encoder activation and ``conv_strides``
    its CNN's strides (default: CleanRL's 4, 2, 1 for the Nature CNN's kernels; the CNN reads the config's env's
    image). Nothing is written unless everything is accepted, and ``out`` must not already hold files.
    """
    base = config if config is not None else ExperimentConfig()
    spec = env_spec(base.env)
    imported = read_foreign(source, path, out, label=label, obs_dim=obs_dim, num_actions=num_actions,
                            activation=activation, image=spec.image, conv_strides=conv_strides)  # fmt: skip
    _check_env(imported, base, spec, repr(str(path)))
    stated = label is not None
    label = label if label is not None else "unknown"
    try:
        cfg = dataclasses.replace(
            base, agent=imported.agent, backdoor=dataclasses.replace(base.backdoor, enabled=label == "backdoored")
        )
    except ConfigError as err:
        raise ConfigError(f"--label {label}: {err}") from None
    agent = build_agent(cfg, Architecture.of_config(cfg, spec.obs_dim, spec.num_actions, spec.image))
    agent.load_state_dict(dict(imported.tensors), strict=True)  # names and shapes were checked above
    provenance = provenance_of(imported, path, stated)
    folder = make_output_folder(Path(out), "--out")
    with folder_lock(folder, "import folder"):  # two imports into one new folder: the second finds it taken
        if any(p.name != LOCK_FILE for p in folder.iterdir()):
            raise ConfigError(f"{str(folder)!r} already exists and is not an empty folder: choose a new --out")
        saved = save_agent(folder, agent.eval(), cfg, label=label, env_steps=imported.env_steps, provenance=provenance)
        # a model folder holds its two files only; a racer that still opens the old lock then finds them and stops
        (folder / LOCK_FILE).unlink(missing_ok=True)
    return saved


def read_foreign(
    source: str,
    path: str | Path,
    out: str | Path,
    *,
    label: str | None = None,
    obs_dim: int | None = None,
    num_actions: int | None = None,
    activation: str = "relu",
    image: tuple[int, int, int] | None = None,
    conv_strides: tuple[int, ...] | None = None,
) -> Imported:
    """What :func:`import_agent` does before writing: check the options and that ``out`` is new or empty, read
    ``path`` and check ``obs_dim`` and ``num_actions`` (where given) against it. ``image`` is the env's image layout
    (a CleanRL CNN reads it) and ``conv_strides`` the CNN's strides (:func:`read_cleanrl`)."""
    if source not in SOURCES:
        raise ConfigError(f"--from must be one of {SOURCES}, got {source!r}")
    if label is not None and label not in ("clean", "backdoored"):
        raise ConfigError(f"label must be 'clean' or 'backdoored', got {label!r}")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{str(out)!r} already exists and is not an empty folder: choose a new --out")
    if source == "sb3":
        imported = read_sb3(path)
    else:
        if obs_dim is None or num_actions is None:
            raise ConfigError("--from cleanrl needs --obs-dim and --actions (a state dict does not record them)")
        imported = read_cleanrl(path, obs_dim, num_actions, activation, image=image, conv_strides=conv_strides)
    where = repr(str(path))
    checks = ((obs_dim, imported.obs_dim, "--obs-dim"), (num_actions, imported.num_actions, "--actions"))
    for given, actual, flag in checks:
        if given is not None and given != actual:
            raise CheckpointError(f"{where}: the agent has {flag[2:]} {actual}, not {flag} {given}")
    return imported


def provenance_of(imported: Imported, path: str | Path, label_stated: bool) -> dict[str, Any]:
    """The card's ``provenance`` of an agent imported from ``path``: source, file name and SHA-256, whether the label
    was stated, whether the value is imported or zeroed, and the source's details."""
    return {
        "imported_from": imported.source, "source_file": _text(Path(path).name) or "?",
        "source_sha256": _sha256(Path(path)), "label_stated": label_stated, "value": imported.value,
        "details": {k: _text(v) if isinstance(v, str) else v for k, v in imported.details.items()},
    }  # fmt: skip


def _check_env(imported: Imported, config: ExperimentConfig, spec: EnvSpec, where: str) -> None:
    """The env ``config`` describes (its spaces: ``spec``) must give the agent's observation size and action count."""
    if (imported.obs_dim, imported.num_actions) == (spec.obs_dim, spec.num_actions):
        return
    if not isinstance(config.env, EnvConfig):
        raise CheckpointError(
            f"{where}: the agent reads {imported.obs_dim} inputs and chooses among {imported.num_actions} actions, "
            f"but the config's env ({config.env.id}, observation {config.env.observation!r}) gives {spec.obs_dim} "
            f"inputs and {spec.num_actions} actions"
        )
    env = config.env
    hints = []
    view = math.isqrt(imported.obs_dim // len(CELL_NAMES))
    if view * view * len(CELL_NAMES) == imported.obs_dim and view != env.view_size:
        hints.append(f"env.view_size: {view}")
    sets = [name for name, moves in ACTION_SETS.items() if len(moves) == imported.num_actions]
    if imported.num_actions != env.num_actions and sets:
        hints.append(f"env.actions: {' or '.join(sets)}")
    hint = f"; pass --config with {', '.join(hints)}" if hints else (
        "; seqtrojan's env has no such observation (its tools run agents in that env)"
    )  # fmt: skip
    raise CheckpointError(
        f"{where}: the agent reads {imported.obs_dim} inputs and chooses among {imported.num_actions} actions, but "
        f"the env of the config gives {env.obs_dim} inputs (view {env.view_size}x{env.view_size}) and "
        f"{env.num_actions} actions ({env.actions}){hint}"
    )


def _activation(name: str) -> Literal["tanh", "relu"]:
    if name not in ("tanh", "relu"):
        raise ConfigError(f"activation must be tanh or relu, got {name!r}")
    return cast('Literal["tanh", "relu"]', name)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _text(value: Any) -> str | None:
    """A string for the card (bounded), or None."""
    if value is None:
        return None
    text = str(value)
    return text if len(text) <= MAX_DETAIL_CHARS else text[: MAX_DETAIL_CHARS - 3] + "..."


def _clip(value: Any) -> str:
    return _clip_text(repr(value))


def _clip_text(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= 200 else text[:197] + "..."
