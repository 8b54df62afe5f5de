"""Model cards and safetensors headers, validated as untrusted input before anything is allocated.

A model folder comes from a shared-model marketplace, so ``card.json`` and the header of ``model.safetensors`` are
hostile until proven otherwise. This module reads both with bounded sizes and checks them against a fixed schema:

- ``card.json`` is at most :data:`MAX_CARD_BYTES`, nested at most :data:`MAX_JSON_DEPTH` deep and holds at most
  :data:`MAX_VALUES` values (both checked before parsing, in linear time, so deep nesting never reaches Python's
  recursive JSON parser), with at most :data:`MAX_ITEMS` entries in any list or object and no duplicate keys;
- its fields have the types and values ``save_agent`` writes: label ``clean`` or ``backdoored``, a SHA-256 of the
  weights, an architecture within :data:`MAX_OBS_DIM`, :data:`MAX_ACTIONS`, :data:`MAX_LAYERS`, :data:`MAX_WIDTH`
  and :data:`MAX_PARAMETERS` (its optional MLP parts too: ``encoder``, ``policy_mlp``, ``value_mlp`` and their
  activations, present only where not empty), an embedded config that parses to the same architecture, and for an
  imported model a ``provenance`` of fixed keys (:data:`PROVENANCE_KEYS`);
- the safetensors header (an 8-byte little-endian length, then JSON) is read alone, its length bounded by
  :data:`MAX_HEADER_BYTES` before it is read; every tensor's dtype is known, its byte range matches its shape and
  dtype, and the ranges tile the data exactly to the end of the file;
- :func:`check_weights` then requires the card's tensor list, the header and the architecture to agree, and the
  weights to be floating point.

Only after all of this does :func:`seqtrojan.agent.checkpoint.load_agent` read the tensors and build the network,
so the memory a model file can make a loader allocate is bounded by the file's real size and these limits.
Every refusal is one :class:`~seqtrojan.errors.CheckpointError` line naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import re
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from seqtrojan.agent.cells import layer_shapes
from seqtrojan.agent.network import DEFAULT_CONV_KERNEL, DEFAULT_CONV_STRIDE, conv_output_side
from seqtrojan.cell_types import CELL_TYPES, cell_names, is_windowed
from seqtrojan.config import (
    ACTIVATIONS,
    MAX_CONV_KERNEL,
    MAX_CONV_STRIDE,
    MAX_HEADS,
    MAX_LAYERS,
    MAX_WIDTH,
    MAX_WINDOW,
    ExperimentConfig,
)
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import CheckpointError, ConfigError, SeqTrojanError
from seqtrojan.serde import from_dict
from seqtrojan.world.config import GymnasiumEnvConfig, upgrade_gym_train_layout

FORMAT = "seqtrojan-model"
FORMAT_VERSION = 1
WEIGHTS = "model.safetensors"
CARD = "card.json"
LABELS = ("clean", "backdoored", "unknown")
"""what a model is said to be; ``unknown``: nobody stated it (an imported agent without ``--label``), so every tool
treats it as a suspect (both envs evaluated) and nothing takes it as ground truth"""

ARCHITECTURE_TYPE = "RecurrentActorCritic"

MAX_CARD_BYTES = 1 << 20
"""largest card.json read (1 MiB; a real card is a few KiB)"""
MAX_HEADER_BYTES = 1 << 20
"""largest safetensors header read (1 MiB; a model's header is a few KiB)"""
MAX_JSON_DEPTH = 32
"""deepest nesting of lists/objects in a card or header (a real card nests 6 or 7 deep)"""
MAX_ITEMS = 4096
"""most entries in any one JSON list or object"""
MAX_VALUES = 1 << 16
"""most list items and object entries in one card or header, all together (a real card has about a hundred)"""
MAX_OBS_DIM = 1 << 15
"""the largest view the env allows (57x57, 6 cell codes) has 19494 inputs"""
MAX_ACTIONS = 64
MAX_PARAMETERS = 1 << 26
"""most parameters in a model (67M; 256 MiB as float32). The paper's network (64, 32) has about 40k"""
MAX_RANK = 8
"""most dimensions of one tensor"""
MAX_MESSAGE = 200
"""characters of a hostile value quoted in an error message"""

DTYPE_SIZES = {
    "BOOL": 1, "U8": 1, "I8": 1, "F8_E5M2": 1, "F8_E4M3": 1, "I16": 2, "U16": 2, "F16": 2, "BF16": 2,
    "I32": 4, "U32": 4, "F32": 4, "I64": 8, "U64": 8, "F64": 8,
}  # fmt: skip
"""bytes per element of each safetensors dtype"""
FLOAT_DTYPES = ("F16", "BF16", "F32", "F64")
"""dtypes a model's weights may have"""

_REQUIRED = ("format", "format_version", "label", "architecture", "config", "tensors", "weights_sha256")
_OPTIONAL = ("seqtrojan_version", "created", "seed", "env_steps", "metrics", "provenance")
IMPORT_SOURCES = ("sb3", "cleanrl")
"""where an imported model can come from (a card's ``provenance.imported_from``)"""
VALUE_IMPORTS = ("imported", "zeroed")
"""``provenance.value``: the value head computes the original's value, or it is zero (the original's critic had
parts this network does not have; see docs/import.md)"""
PROVENANCE_KEYS = ("imported_from", "source_file", "source_sha256", "label_stated", "value", "details")
"""the keys of a card's ``provenance`` (all required)"""
MAX_DETAIL_CHARS = 1000
"""longest string in ``provenance`` (and its ``details``)"""
_ARCH_REQUIRED = ("type", "obs_dim", "num_actions", "lstm_sizes")
_ARCH_MLPS = ("encoder", "policy_mlp", "value_mlp")
_ARCH_ACTIVATIONS = {"encoder_activation": "relu", "mlp_activation": "tanh"}
"""the optional activations and their defaults (those of :class:`seqtrojan.config.AgentConfig`)"""
_ARCH_CELL = ("cell", "window", "heads")
_ARCH_CONV = ("conv", "image", "conv_kernels", "conv_strides")
"""the sequence model (absent: an LSTM); window and heads are written for a transformer only"""
_SHA256 = re.compile(r"[0-9a-f]{64}")
_STRINGS = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\\?\Z)', re.DOTALL)
"""a JSON string; one left open runs to the end of the text (so a match never fails and never backtracks far)"""
_NOT_STRUCTURE = bytes(sorted(set(range(256)) - set(b"[]{},")))
_BRACKET_STEP = [0] * 256
for _c in b"[{":
    _BRACKET_STEP[_c] = 1
for _c in b"]}":
    _BRACKET_STEP[_c] = -1


@dataclasses.dataclass(frozen=True)
class Architecture:
    """The network a card describes: ``RecurrentActorCritic(obs_dim, num_actions, lstm_sizes, ...)`` with its
    optional MLP parts (empty by default) and its sequence model (``cell``; ``window`` and ``heads`` mean something
    for a transformer only and are at their defaults otherwise)."""

    obs_dim: int
    num_actions: int
    lstm_sizes: tuple[int, ...]
    encoder: tuple[int, ...] = ()
    encoder_activation: str = "relu"
    policy_mlp: tuple[int, ...] = ()
    value_mlp: tuple[int, ...] = ()
    mlp_activation: str = "tanh"
    cell: str = "lstm"
    window: int = 8
    heads: int = 1
    conv: tuple[int, ...] = ()
    """channels of the convolutional encoder's layers (none by default)"""
    image: tuple[int, ...] | None = None
    """(rows, cols, channels) the conv encoder reads the observation as (only with ``conv``)"""
    conv_kernels: tuple[int, ...] = ()
    """each conv layer's kernel side (empty: 2 each; filled in with the defaults when ``conv`` has layers)"""
    conv_strides: tuple[int, ...] = ()
    """each conv layer's stride (empty: 1 each; filled in likewise)"""

    def __post_init__(self) -> None:
        if self.conv:  # one description per network: the defaults written out
            n = len(self.conv)
            object.__setattr__(self, "conv_kernels", tuple(self.conv_kernels) or (DEFAULT_CONV_KERNEL,) * n)
            object.__setattr__(self, "conv_strides", tuple(self.conv_strides) or (DEFAULT_CONV_STRIDE,) * n)

    @classmethod
    def of_config(
        cls, config: ExperimentConfig, obs_dim: int | None = None, num_actions: int | None = None,
        image: tuple[int, ...] | None = None,
    ) -> Architecture:  # fmt: skip
        """The architecture ``config`` builds (:func:`seqtrojan.agent.checkpoint.build_agent`). The grid world's
        config fixes the inputs and actions; a Gymnasium env's spaces come from the env (or the card): give them."""
        a = config.agent
        attention = is_windowed(a.cell)
        if isinstance(config.env, EnvConfig):
            obs_dim, num_actions = config.env.obs_dim, config.env.num_actions
        if obs_dim is None or num_actions is None:
            raise ConfigError(f"the architecture of an agent for {config.gym_env.id!r} needs its inputs and actions")
        return cls(
            obs_dim, num_actions, tuple(a.lstm_sizes), tuple(a.encoder), a.encoder_activation,
            tuple(a.policy_mlp), tuple(a.value_mlp), a.mlp_activation, a.cell, a.window if attention else 8,
            a.heads if attention else 1, tuple(a.conv), tuple(image) if a.conv and image is not None else None,
            tuple(a.conv_kernels), tuple(a.conv_strides),
        )  # fmt: skip

    def optional_parts(self) -> dict[str, Any]:
        """The optional parts that are not at their defaults, as the card writes them."""
        out: dict[str, Any] = {}
        for name in _ARCH_MLPS:
            if getattr(self, name):
                out[name] = list(getattr(self, name))
        for name, default in _ARCH_ACTIVATIONS.items():
            if getattr(self, name) != default:
                out[name] = getattr(self, name)
        if self.cell != "lstm":
            out["cell"] = self.cell
        if is_windowed(self.cell):
            out["window"], out["heads"] = self.window, self.heads
        if self.conv:
            out["conv"], out["image"] = list(self.conv), list(self.image or ())
            if any(k != DEFAULT_CONV_KERNEL for k in self.conv_kernels):
                out["conv_kernels"] = list(self.conv_kernels)
            if any(s != DEFAULT_CONV_STRIDE for s in self.conv_strides):
                out["conv_strides"] = list(self.conv_strides)
        return out

    def to_card(self) -> dict[str, Any]:
        """The card's ``architecture`` field (the optional parts only where not at their defaults)."""
        return {
            "type": ARCHITECTURE_TYPE, "obs_dim": self.obs_dim, "num_actions": self.num_actions,
            "lstm_sizes": list(self.lstm_sizes), **self.optional_parts(),
        }  # fmt: skip

    def tensor_shapes(self) -> dict[str, tuple[int, ...]]:
        """The network's state_dict names and shapes, computed without building it."""
        shapes: dict[str, tuple[int, ...]] = {}
        features = self.obs_dim  # what the MLP encoder (or the first layer) reads
        if self.conv:
            rows, cols, chans = self.image or (0, 0, 0)
            for i, (a, b, k) in enumerate(zip((chans, *self.conv[:-1]), self.conv, self.conv_kernels)):
                shapes[f"conv.{i}.weight"], shapes[f"conv.{i}.bias"] = (b, a, k, k), (b,)
            out_rows, out_cols = (conv_output_side(n, self.conv_kernels, self.conv_strides) for n in (rows, cols))
            features = out_rows * out_cols * self.conv[-1]
        inputs = (self.encoder[-1] if self.encoder else features, *self.lstm_sizes[:-1])
        for i, (n_in, width) in enumerate(zip(inputs, self.lstm_sizes)):
            for name, shape in layer_shapes(self.cell, n_in, width, self.window, self.heads).items():
                shapes[f"cells.{i}.{name}"] = shape
        last = self.lstm_sizes[-1]
        shapes["policy_head.weight"] = (self.num_actions, self.policy_mlp[-1] if self.policy_mlp else last)
        shapes["policy_head.bias"] = (self.num_actions,)
        shapes["value_head.weight"] = (1, self.value_mlp[-1] if self.value_mlp else last)
        shapes["value_head.bias"] = (1,)
        for name, n_in in (("encoder", features), ("policy_mlp", last), ("value_mlp", last)):
            widths = getattr(self, name)
            for i, (a, b) in enumerate(zip((n_in, *widths[:-1]), widths)):
                shapes[f"{name}.{i}.weight"] = (b, a)
                shapes[f"{name}.{i}.bias"] = (b,)
        return shapes

    @property
    def num_parameters(self) -> int:
        return sum(math.prod(shape) for shape in self.tensor_shapes().values())

    def describe(self) -> str:
        text = f"obs_dim={self.obs_dim}, num_actions={self.num_actions}, lstm_sizes={list(self.lstm_sizes)}"
        return "".join([text, *(f", {k}={v}" for k, v in self.optional_parts().items())])


@dataclasses.dataclass(frozen=True)
class ModelCard:
    """A validated ``card.json``. ``data`` is the card as parsed JSON (what ``load_agent`` returns)."""

    label: str
    """'clean' or 'backdoored'"""
    architecture: Architecture
    config: ExperimentConfig
    """the embedded training config (agrees with ``architecture``)"""
    tensors: Mapping[str, tuple[int, ...]]
    """tensor names and shapes the card lists"""
    weights_sha256: str
    metrics: Mapping[str, Any]
    env_steps: int | None
    seed: int | None
    seqtrojan_version: str | None
    created: str | None
    provenance: Mapping[str, Any] | None
    """where an imported model came from (:data:`PROVENANCE_KEYS`); None for a model trained here"""
    data: dict[str, Any] = dataclasses.field(repr=False, compare=False)


@dataclasses.dataclass(frozen=True)
class TensorInfo:
    """One entry of a safetensors header: dtype, shape and byte range within the data (after the header)."""

    dtype: str
    shape: tuple[int, ...]
    begin: int
    end: int


@dataclasses.dataclass(frozen=True)
class SafetensorsHeader:
    """A validated safetensors header; the data starts at byte ``8 + header_len`` and runs to ``file_size``."""

    header_len: int
    file_size: int
    tensors: Mapping[str, TensorInfo]
    metadata: Mapping[str, str]
    raw: bytes = dataclasses.field(repr=False)
    """the header's bytes as read (the JSON after the 8-byte length)"""

    @property
    def shapes(self) -> dict[str, list[int]]:
        return {name: list(t.shape) for name, t in self.tensors.items()}


# ---------------------------------------------------------------------- card


def inherited_label(own: str, start: str | None) -> str:
    """A trained model's label: 'backdoored' when its run planted a backdoor (``own``, the run config's label) or
    started from a model labelled 'backdoored' (``start``): fine-tuning does not make a model clean (whether its
    backdoor survived is a measurement, not its label)."""
    return "backdoored" if "backdoored" in (own, start) else "clean"


def read_card(folder: str | Path) -> ModelCard:
    """Read and validate ``folder/card.json`` (no weights are read; a folder written by an earlier version for a
    Gymnasium run, with ``gym_card.json``, is read through :func:`upgrade_gym_card`, which reads the weights'
    header). Raises :class:`CheckpointError`."""
    folder = Path(folder)
    path = folder / CARD
    if not path.is_file() and (folder / LEGACY_GYM_CARD).is_file():
        return parse_card(json.dumps(upgrade_gym_card(folder)), repr(str(folder / LEGACY_GYM_CARD)))
    if not path.is_file():
        raise CheckpointError(f"no {CARD} in {str(folder)!r}: not a seqtrojan model folder")
    raw = read_regular_file(path, MAX_CARD_BYTES, repr(str(path)), "a model card may have")
    return parse_card(raw, repr(str(path)))


LEGACY_GYM_CARD = "gym_card.json"
"""the card seqtrojan 0.x wrote for a Gymnasium run's model (format ``seqtrojan-gym-model``, version 1)"""
_LEGACY_GYM_KEYS = (
    "format", "format_version", "seqtrojan_version", "created", "label", "architecture", "env_steps", "config",
    "metrics", "weights_sha256", "provenance",
)  # fmt: skip


def upgrade_gym_card(folder: Path) -> dict[str, Any]:
    """A ``gym_card.json`` (written by earlier versions for Gymnasium runs) as today's card: the config in today's
    layout (:func:`~seqtrojan.world.config.upgrade_gym_train_layout`), the architecture completed from it, and the
    tensor list read from the weights' header. Every check of :func:`parse_card` then applies."""
    path = folder / LEGACY_GYM_CARD
    where = repr(str(path))
    old = load_json(read_regular_file(path, MAX_CARD_BYTES, where, "a model card may have"), where)
    if not isinstance(old, dict) or old.get("format") != "seqtrojan-gym-model" or old.get("format_version") != 1:
        raise CheckpointError(f"{where} is not a seqtrojan-gym-model card, version 1")
    unknown = sorted(set(old) - set(_LEGACY_GYM_KEYS))
    arch = old.get("architecture")
    config = upgrade_gym_train_layout(old.get("config"))
    if unknown or not isinstance(arch, dict) or not isinstance(config, dict):
        raise CheckpointError(f"{where}: unknown field(s) {_clip(unknown)}, or no architecture and config mappings")
    agent: dict[str, Any] = config["agent"] if isinstance(config.get("agent"), dict) else {}
    architecture = {"type": ARCHITECTURE_TYPE, **arch}
    for name in (*_ARCH_MLPS, *_ARCH_ACTIVATIONS):
        if agent.get(name) not in (None, [], _ARCH_ACTIVATIONS.get(name)):
            architecture[name] = agent[name]
    if is_windowed(agent.get("cell")):
        architecture["window"], architecture["heads"] = agent.get("window", 8), agent.get("heads", 1)
    if agent.get("conv"):
        cells = arch.get("obs_dim", 0) // _MINIGRID_CELL_BITS if isinstance(arch.get("obs_dim"), int) else 0
        side = math.isqrt(cells)
        architecture["conv"], architecture["image"] = agent["conv"], [side, side, _MINIGRID_CELL_BITS]
    header = read_header(folder / WEIGHTS)
    card = {k: v for k, v in old.items() if k in _OPTIONAL or k in _REQUIRED}
    card.update(
        format=FORMAT, format_version=FORMAT_VERSION, architecture=architecture, config=config,
        tensors=header.shapes, seed=config["run"].get("seed") if isinstance(config.get("run"), dict) else None,
    )  # fmt: skip
    return card


_MINIGRID_CELL_BITS = 20
"""numbers per cell of MiniGrid's one-hot view (:data:`seqtrojan.wrappers.observations.CELL_BITS`)"""


def parse_card(raw: bytes | str, where: str = CARD) -> ModelCard:
    """Validate card text (``where`` names it in errors); see the module docstring for what is checked."""
    if len(raw) > MAX_CARD_BYTES:
        raise CheckpointError(f"{where} is larger than the {MAX_CARD_BYTES} bytes a model card may have")
    card = load_json(raw, where)
    if not isinstance(card, dict) or card.get("format") != FORMAT:
        raise CheckpointError(f"{where} is not a seqtrojan model card (format must be {FORMAT!r})")
    version = card.get("format_version")
    if type(version) is not int or version != FORMAT_VERSION:
        raise CheckpointError(f"{where} has format_version {_clip(version)}, expected {FORMAT_VERSION}")
    for key in _REQUIRED:
        if key not in card:
            raise CheckpointError(f"{where} lacks the field {key!r}")
    unknown = sorted(set(card) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise CheckpointError(f"{where} has unknown field(s) {_clip(unknown)}; known: {[*_REQUIRED, *_OPTIONAL]}")
    label = card["label"]
    if label not in LABELS:
        raise CheckpointError(f"{where}: label must be one of {list(LABELS)}, got {_clip(label)}")
    sha = card["weights_sha256"]
    if not isinstance(sha, str) or not _SHA256.fullmatch(sha):
        raise CheckpointError(
            f"{where}: weights_sha256 must be the weights' SHA-256 (64 lowercase hex digits), got {_clip(sha)}"
        )
    arch = _architecture(card["architecture"], where)
    tensors = _tensor_list(card["tensors"], where)
    metrics = card.get("metrics", {})
    if not isinstance(metrics, dict):
        raise CheckpointError(f"{where}: metrics must be a mapping, got {type(metrics).__name__}")
    env_steps = _optional_int(card, "env_steps", where, minimum=0)
    seed = _optional_int(card, "seed", where)
    version_text, created = (_optional_str(card, key, where) for key in ("seqtrojan_version", "created"))
    provenance = _provenance(card["provenance"], where) if card.get("provenance") is not None else None
    config = _config(card["config"], where)
    from_config = Architecture.of_config(config, arch.obs_dim, arch.num_actions, arch.image)
    if from_config != arch:
        raise CheckpointError(
            f"{where}: architecture ({arch.describe()}) disagrees with its config ({from_config.describe()})"
        )
    return ModelCard(
        label, arch, config, tensors, sha, metrics, env_steps, seed, version_text, created, provenance, card
    )


def _architecture(value: Any, where: str) -> Architecture:
    if not isinstance(value, dict):
        raise CheckpointError(f"{where}: architecture must be a mapping, got {type(value).__name__}")
    keys, optional = set(_ARCH_REQUIRED), {*_ARCH_MLPS, *_ARCH_ACTIVATIONS, *_ARCH_CELL, *_ARCH_CONV}
    if not keys <= set(value) <= keys | optional:
        missing, extra = sorted(keys - set(value)), sorted(set(value) - keys - optional)
        raise CheckpointError(
            f"{where}: architecture must have the keys {sorted(keys)} and may have {sorted(optional)} (missing "
            f"{missing}, unknown {_clip(extra)})"
        )
    if value["type"] != ARCHITECTURE_TYPE:
        raise CheckpointError(f"{where}: architecture.type must be {ARCHITECTURE_TYPE!r}, got {_clip(value['type'])}")
    obs_dim = _bounded_int(value["obs_dim"], 1, MAX_OBS_DIM, f"{where}: architecture.obs_dim")
    num_actions = _bounded_int(value["num_actions"], 1, MAX_ACTIONS, f"{where}: architecture.num_actions")
    sizes = value["lstm_sizes"]
    if not isinstance(sizes, list) or not 1 <= len(sizes) <= MAX_LAYERS:
        raise CheckpointError(
            f"{where}: architecture.lstm_sizes must be a list of 1 to {MAX_LAYERS} layer widths, got {_clip(sizes)}"
        )
    widths = tuple(_bounded_int(w, 1, MAX_WIDTH, f"{where}: architecture.lstm_sizes[{i}]") for i, w in enumerate(sizes))
    mlps: dict[str, Any] = {}
    for name in _ARCH_MLPS:
        layers = value.get(name, [])
        if not isinstance(layers, list) or len(layers) > MAX_LAYERS:
            raise CheckpointError(
                f"{where}: architecture.{name} must be a list of at most {MAX_LAYERS} layer widths, got {_clip(layers)}"
            )
        what = f"{where}: architecture.{name}"
        mlps[name] = tuple(_bounded_int(w, 1, MAX_WIDTH, f"{what}[{i}]") for i, w in enumerate(layers))
    for name, default in _ARCH_ACTIVATIONS.items():
        mlps[name] = value.get(name, default)
        if mlps[name] not in ACTIVATIONS:
            raise CheckpointError(f"{where}: architecture.{name} must be one of {ACTIVATIONS}, got {_clip(mlps[name])}")
    cell = value.get("cell", "lstm")
    if not isinstance(cell, str) or cell not in CELL_TYPES:
        raise CheckpointError(f"{where}: architecture.cell must be one of {cell_names()}, got {_clip(cell)}")
    if is_windowed(cell):
        if "window" not in value or "heads" not in value:
            raise CheckpointError(f"{where}: a {cell}'s architecture must give its window and heads")
        mlps["window"] = _bounded_int(value["window"], 1, MAX_WINDOW, f"{where}: architecture.window")
        mlps["heads"] = _bounded_int(value["heads"], 1, MAX_HEADS, f"{where}: architecture.heads")
        if any(w % mlps["heads"] for w in widths):
            raise CheckpointError(
                f"{where}: architecture.lstm_sizes {list(widths)} must be divisible by "
                f"architecture.heads={mlps['heads']}"
            )
    elif "window" in value or "heads" in value:
        raise CheckpointError(f"{where}: architecture.window and heads belong to a windowed cell, not to a {cell}")
    if any(name in value for name in _ARCH_CONV):
        mlps.update(_conv_parts(value, obs_dim, where))
    arch = Architecture(obs_dim, num_actions, widths, **mlps, cell=cell)
    if arch.num_parameters > MAX_PARAMETERS:
        raise CheckpointError(
            f"{where}: architecture ({arch.describe()}) has {arch.num_parameters} parameters, more than the "
            f"limit of {MAX_PARAMETERS}"
        )
    return arch


def _conv_parts(value: dict[str, Any], obs_dim: int, where: str) -> dict[str, tuple[int, ...]]:
    """A card's ``conv`` channels and ``image`` layout (and the optional ``conv_kernels`` and ``conv_strides``, one
    per layer), checked: both present, bounded, the image holding exactly the observation, and each kernel fitting
    what the layers before it leave."""
    conv, image = value.get("conv"), value.get("image")
    if not isinstance(conv, list) or not 1 <= len(conv) <= MAX_LAYERS or not isinstance(image, list) or len(image) != 3:
        raise CheckpointError(
            f"{where}: architecture.conv (1 to {MAX_LAYERS} channel counts) and architecture.image ([rows, cols, "
            f"channels]) go together, got {_clip(conv)} and {_clip(image)}"
        )
    channels = tuple(_bounded_int(c, 1, MAX_WIDTH, f"{where}: architecture.conv[{i}]") for i, c in enumerate(conv))
    layout = tuple(_bounded_int(d, 1, MAX_OBS_DIM, f"{where}: architecture.image[{i}]") for i, d in enumerate(image))
    geometry: dict[str, tuple[int, ...]] = {}
    for name, default, top in (("conv_kernels", DEFAULT_CONV_KERNEL, MAX_CONV_KERNEL),
                               ("conv_strides", DEFAULT_CONV_STRIDE, MAX_CONV_STRIDE)):  # fmt: skip
        given = value.get(name, [default] * len(channels))
        if not isinstance(given, list) or len(given) != len(channels):
            raise CheckpointError(
                f"{where}: architecture.{name} must list one integer per conv layer ({len(channels)}), got "
                f"{_clip(given)}"
            )
        what = f"{where}: architecture.{name}"
        geometry[name] = tuple(_bounded_int(v, 1, top, f"{what}[{i}]") for i, v in enumerate(given))
    kernels, strides = geometry["conv_kernels"], geometry["conv_strides"]
    sides = [conv_output_side(n, kernels, strides) for n in layout[:2]]
    if math.prod(layout) != obs_dim or not all(sides):
        default = set(kernels) == {DEFAULT_CONV_KERNEL} and set(strides) == {DEFAULT_CONV_STRIDE}
        layers = f"{len(channels)} 2x2 conv layers"
        if not default:
            layers = f"conv kernels {list(kernels)}, strides {list(strides)}"
        raise CheckpointError(
            f"{where}: architecture.image {list(layout)} must hold the {obs_dim} inputs and leave a row and a column "
            f"after {layers}"
        )
    return {"conv": channels, "image": layout, **geometry}


def _provenance(value: Any, where: str) -> dict[str, Any]:
    """A validated ``provenance`` (an imported model's origin): exactly :data:`PROVENANCE_KEYS`, typed."""
    what = f"{where}: provenance"
    if not isinstance(value, dict):
        raise CheckpointError(f"{what} must be a mapping or null, got {type(value).__name__}")
    if set(value) != set(PROVENANCE_KEYS):
        missing, extra = sorted(set(PROVENANCE_KEYS) - set(value)), sorted(set(value) - set(PROVENANCE_KEYS))
        raise CheckpointError(
            f"{what} must have exactly the keys {list(PROVENANCE_KEYS)} (missing {missing}, unknown {_clip(extra)})"
        )
    if value["imported_from"] not in IMPORT_SOURCES:
        source = _clip(value["imported_from"])
        raise CheckpointError(f"{what}.imported_from must be one of {IMPORT_SOURCES}, got {source}")
    if not isinstance(value["source_file"], str) or not 0 < len(value["source_file"]) <= MAX_DETAIL_CHARS:
        raise CheckpointError(f"{what}.source_file must be a file name, got {_clip(value['source_file'])}")
    sha = value["source_sha256"]
    if not isinstance(sha, str) or not _SHA256.fullmatch(sha):
        raise CheckpointError(f"{what}.source_sha256 must be 64 lowercase hex digits, got {_clip(sha)}")
    if type(value["label_stated"]) is not bool:
        raise CheckpointError(f"{what}.label_stated must be true or false, got {_clip(value['label_stated'])}")
    if value["value"] not in VALUE_IMPORTS:
        raise CheckpointError(f"{what}.value must be one of {VALUE_IMPORTS}, got {_clip(value['value'])}")
    details = value["details"]
    if not isinstance(details, dict):
        raise CheckpointError(f"{what}.details must be a mapping, got {type(details).__name__}")
    for key, item in details.items():
        scalar = item is None or type(item) in (bool, int, float) or isinstance(item, str)
        ints = isinstance(item, list) and len(item) <= MAX_RANK and all(type(i) is int for i in item)
        if not (scalar or ints) or (isinstance(item, str) and len(item) > MAX_DETAIL_CHARS):
            raise CheckpointError(
                f"{what}.details[{_clip(key)}] must be a number, a string of at most {MAX_DETAIL_CHARS} characters, "
                f"true/false, null or a short list of integers, got {_clip(item)}"
            )
    return value


def _tensor_list(value: Any, where: str) -> dict[str, tuple[int, ...]]:
    if not isinstance(value, dict):
        raise CheckpointError(f"{where}: tensors must be a mapping of name to shape, got {type(value).__name__}")
    out = {}
    for name, shape in value.items():
        out[name] = _shape(shape, f"{where}: tensors[{_clip(name)}]")
    return out


def _config(value: Any, where: str) -> ExperimentConfig:
    try:
        config = from_dict(ExperimentConfig, value, "config")
    except Exception as err:  # from_dict on untrusted data is pure: any failure means a bad config
        message = str(err) if isinstance(err, SeqTrojanError) else f"{type(err).__name__}: {err}"
        raise CheckpointError(f"{where} has an invalid config: {_clip_text(message)}") from None
    if isinstance(config.env, GymnasiumEnvConfig) and ":" in config.env.id:
        raise CheckpointError(
            f"{where}: config.env.id={_clip(config.env.id)} would import a module; a model's env must be a "
            "registered Gymnasium id"
        )
    return config


def _shape(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, list) or len(value) > MAX_RANK:
        raise CheckpointError(f"{what} must be a list of at most {MAX_RANK} dimensions, got {_clip(value)}")
    if any(type(d) is not int or d < 0 for d in value):
        raise CheckpointError(f"{what} must hold non-negative integers, got {_clip(value)}")
    return tuple(value)


def _bounded_int(value: Any, lo: int, hi: int, what: str) -> int:
    if type(value) is not int or not lo <= value <= hi:
        raise CheckpointError(f"{what} must be an integer in [{lo}, {hi}], got {_clip(value)}")
    return value


def _optional_int(card: dict[str, Any], key: str, where: str, minimum: int | None = None) -> int | None:
    value = card.get(key)
    if value is None:
        return None
    if type(value) is not int or (minimum is not None and value < minimum):
        bound = f" >= {minimum}" if minimum is not None else ""
        raise CheckpointError(f"{where}: {key} must be an integer{bound} or null, got {_clip(value)}")
    return value


def _optional_str(card: dict[str, Any], key: str, where: str) -> str | None:
    value = card.get(key)
    if value is not None and not isinstance(value, str):
        raise CheckpointError(f"{where}: {key} must be a string or null, got {_clip(value)}")
    return value


# ---------------------------------------------------------------------- safetensors header


def read_header(path: str | Path) -> SafetensorsHeader:
    """Read and validate the header of a safetensors file without reading its tensors."""
    path = Path(path)
    where = repr(str(path))
    if not path.is_file():
        raise CheckpointError(f"{where} does not exist")
    with path.open("rb") as fh:
        head = fh.read(9)
        size = os.fstat(fh.fileno()).st_size
        header_len = int.from_bytes(head[:8], "little") if len(head) >= 8 else -1
        plausible = len(head) == 9 and 0 < header_len <= MAX_HEADER_BYTES and header_len + 8 <= size
        # A header length can begin with the bytes of "PK" (19280 + 65536 k) or 0x80 (128 + 256 k): only a file that
        # cannot be safetensors is called a zip or a pickle.
        if not (plausible and head[8:9] == b"{") and (head[:2] == b"PK" or head[:1] == b"\x80"):
            raise CheckpointError(f"{where} is a pickle/zip file, not safetensors: refusing to load it")
        if header_len > MAX_HEADER_BYTES:
            raise CheckpointError(
                f"{where} declares a safetensors header of {header_len} bytes, more than the limit of "
                f"{MAX_HEADER_BYTES}: refusing to read it"
            )
        if len(head) < 9 or header_len <= 0 or header_len + 8 > size or head[8:9] != b"{":
            raise CheckpointError(f"{where} is not a valid safetensors file (corrupt or truncated)")
        fh.seek(8)
        raw = fh.read(header_len)
    if len(raw) != header_len:
        raise CheckpointError(f"{where} is not a valid safetensors file (corrupt or truncated)")
    return parse_header(raw, size, where)


def parse_header(raw: bytes, file_size: int, where: str = WEIGHTS) -> SafetensorsHeader:
    """Validate a safetensors header (the JSON after the 8-byte length) for a file of ``file_size`` bytes."""
    header = load_json(raw, f"the safetensors header of {where}")
    if not isinstance(header, dict):
        raise CheckpointError(f"the safetensors header of {where} is not a JSON object")
    data_len = file_size - 8 - len(raw)
    metadata = header.pop("__metadata__", {})
    if not isinstance(metadata, dict) or not all(isinstance(v, str) for v in metadata.values()):
        raise CheckpointError(f"the safetensors header of {where}: __metadata__ must map strings to strings")
    tensors = {}
    for name, entry in header.items():
        what = f"{where}: tensor {_clip(name)} in the safetensors header"
        if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
            raise CheckpointError(f"{what} must have exactly dtype, shape and data_offsets, got {_clip(entry)}")
        dtype = entry["dtype"]
        if dtype not in DTYPE_SIZES:
            raise CheckpointError(f"{what} has unknown dtype {_clip(dtype)}")
        shape = _shape(entry["shape"], f"{what}: shape")
        offsets = entry["data_offsets"]
        if (
            not isinstance(offsets, list)
            or len(offsets) != 2
            or any(type(o) is not int for o in offsets)
            or not 0 <= offsets[0] <= offsets[1]
        ):
            raise CheckpointError(f"{what} has invalid data_offsets {_clip(offsets)}")
        begin, end = offsets
        if end > data_len:
            raise CheckpointError(
                f"{what} has data_offsets [{begin}, {end}] past the end of the data ({data_len} bytes): corrupt or "
                f"truncated"
            )
        need = math.prod(shape) * DTYPE_SIZES[dtype]
        if end - begin != need:
            raise CheckpointError(
                f"{what} says dtype {dtype} and shape {list(shape)}, which need {need} bytes, but its data_offsets "
                f"[{begin}, {end}] hold {end - begin}"
            )
        tensors[name] = TensorInfo(dtype, shape, begin, end)
    cursor = 0
    for name, info in sorted(tensors.items(), key=lambda item: (item[1].begin, item[1].end)):
        if info.begin != cursor:
            problem = "overlaps another tensor" if info.begin < cursor else "leaves a gap before it"
            raise CheckpointError(f"{where} is corrupt: tensor {_clip(name)} in the safetensors header {problem}")
        cursor = info.end
    if cursor != data_len:
        raise CheckpointError(
            f"{where} is corrupt or truncated: its tensors cover {cursor} bytes but the file holds {data_len} after "
            f"the header"
        )
    return SafetensorsHeader(len(raw), file_size, tensors, metadata, bytes(raw))


def check_weights(card: ModelCard, header: SafetensorsHeader, where: str) -> None:
    """Refuse weights whose header disagrees with the card's tensor list or architecture, or are not float."""
    actual = header.shapes
    listed = {k: list(v) for k, v in card.tensors.items()}
    if listed != actual:
        raise CheckpointError(f"{CARD} does not match {WEIGHTS} in {where}: {first_difference(listed, actual)}")
    needed = {k: list(v) for k, v in card.architecture.tensor_shapes().items()}
    if needed != actual:
        diff = first_difference(needed, actual, "the architecture")
        raise CheckpointError(
            f"{WEIGHTS} in {where} does not fit the architecture in {CARD} ({card.architecture.describe()}): {diff}"
        )
    for name, info in header.tensors.items():
        if info.dtype not in FLOAT_DTYPES:
            raise CheckpointError(
                f"{WEIGHTS} in {where}: tensor {name!r} has dtype {info.dtype}; weights must be one of {FLOAT_DTYPES}"
            )


def first_difference(expected: dict[str, list[int]], actual: dict[str, list[int]], source: str = "the card") -> str:
    """The first tensor (by name) whose presence or shape differs between ``source`` (expected) and the weights."""
    for name in sorted(set(expected) | set(actual)):
        if name not in actual:
            return f"tensor {_clip(name)} is listed in {source} but missing from the weights"
        if name not in expected:
            return f"tensor {_clip(name)} is in the weights but not in {source}"
        if expected[name] != actual[name]:
            return f"tensor {_clip(name)} has shape {_clip(actual[name])} but {source} says {_clip(expected[name])}"
    return "unknown difference"


# ---------------------------------------------------------------------- bounded files and JSON


def read_regular_file(path: Path, limit: int, where: str, whose: str = "this file may have") -> bytes:
    """The bytes of the regular file ``path``, at most ``limit``. A FIFO, device or folder is refused without
    blocking (checked before opening, then opened non-blocking and checked again on the open file, in case it was
    swapped), and a larger file from its size before anything is read. ``FileNotFoundError`` passes through; any
    other refusal is one :class:`CheckpointError` line naming ``where``."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise CheckpointError(f"{where} is not a regular file (a FIFO, device or folder): refusing to read it")
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise
    except OSError as err:
        raise CheckpointError(f"cannot read {where}: {err.strerror or err}") from None
    with os.fdopen(fd, "rb") as fh:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise CheckpointError(f"{where} is not a regular file (a FIFO, device or folder): refusing to read it")
        if info.st_size > limit:
            raise CheckpointError(f"{where} is larger than the {limit} bytes {whose}: refusing to read it")
        raw = fh.read(limit + 1)
    if len(raw) > limit:  # it grew while being read
        raise CheckpointError(f"{where} is larger than the {limit} bytes {whose}: refusing to read it")
    return raw


class _DuplicateKeyError(ValueError):
    pass


def load_json(raw: bytes | str, where: str, *, max_values: int = MAX_VALUES, max_items: int = MAX_ITEMS) -> Any:
    """Parse untrusted JSON with bounded cost: nesting depth and the number of values (``max_values``) are checked
    before parsing, then no duplicate keys and no list or object with more than ``max_items`` entries."""
    data = raw if isinstance(raw, bytes) else raw.encode("utf-8", "surrogatepass")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise CheckpointError(f"{where} is not valid JSON: {err}") from None
    if data.count(b'"') > 4 * max_values:  # a key and a string value per entry, two quotes each
        raise CheckpointError(f"{where} has more strings than {max_values} values can hold: refusing to parse it")
    structure = _structure(data)
    if structure.count(b",") + 1 > max_values:
        raise CheckpointError(f"{where} has more than {max_values} values: refusing to parse it")
    if _depth(structure) > MAX_JSON_DEPTH:
        raise CheckpointError(f"{where} nests lists/objects more than {MAX_JSON_DEPTH} deep: refusing to parse it")
    try:
        value = json.loads(text, object_pairs_hook=_unique_keys)
    except (ValueError, RecursionError) as err:  # JSONDecodeError, duplicate keys, over-long integers
        raise CheckpointError(f"{where} is not valid JSON: {_clip_text(str(err))}") from None
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, (dict, list)):
            if len(item) > max_items:
                kind = "an object" if isinstance(item, dict) else "a list"
                raise CheckpointError(
                    f"{where} has {kind} with {len(item)} entries, more than the limit of {max_items}"
                )
            stack.extend(item.values() if isinstance(item, dict) else item)
    return value


def nesting_depth(text: bytes) -> int:
    """Deepest list/object nesting in JSON text, ignoring brackets inside strings: linear time, no recursion.

    (Invalid JSON, e.g. with unbalanced brackets or an unterminated string, is refused by the parser anyway.)"""
    return _depth(_structure(text))


def _structure(text: bytes) -> bytes:
    """The brackets and commas of JSON text that are outside strings."""
    return _STRINGS.sub(b"", text).translate(None, _NOT_STRUCTURE)


def _depth(structure: bytes) -> int:
    return max(itertools.accumulate(map(_BRACKET_STEP.__getitem__, structure)), default=0)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKeyError(f"duplicate key {_clip(key)}")
        out[key] = value
    return out


def _clip(value: Any) -> str:
    """``repr(value)``, shortened: hostile values can be a megabyte long."""
    return _clip_text(repr(value))


def _clip_text(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= MAX_MESSAGE else text[: MAX_MESSAGE - 3] + "..."
