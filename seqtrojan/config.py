"""Typed configuration: dataclasses <-> plain dicts / YAML, with clear errors for unknown or ill-typed keys.

Every stage of seqtrojan takes a frozen dataclass. YAML presets in ``configs/`` and JSON model cards are read
with :func:`from_dict`, which checks every key and value type and names the dotted path of anything wrong.
"""

from __future__ import annotations

import dataclasses
import re
import reprlib
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError

T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """The recurrent actor-critic: stacked LSTM layers, then a policy head and a value head."""

    lstm_sizes: tuple[int, ...] = (64, 32)
    """widths of the stacked LSTM layers (the paper: 64 then 32)"""
    forget_bias: float = 1.0
    """initial forget-gate bias (1 helps gradients reach far back at the start of training)"""
    memory: bool = True
    """False resets the LSTM state before every step: a memoryless baseline with the same network"""

    def __post_init__(self) -> None:
        if not self.lstm_sizes or any((not isinstance(w, int)) or w < 1 for w in self.lstm_sizes):
            raise ConfigError(f"agent.lstm_sizes must be positive integers, got {_short(self.lstm_sizes)}")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Recurrent PPO (clipped objective, GAE, value loss, entropy bonus, gradient clipping, LR schedule)."""

    total_steps: int = 2_000_000
    """environment steps to train for (all envs together)"""
    num_envs: int = 512
    """B: episodes stepped in parallel"""
    rollout_steps: int = 64
    """T: steps per env per rollout"""
    bptt_length: int | None = None
    """length of the sequences the update unrolls (a divisor of rollout_steps); None means rollout_steps"""
    num_minibatches: int = 4
    """minibatches per epoch; sequences are split between them (each whole, with its start state)"""
    update_epochs: int = 4
    """passes over each rollout"""
    learning_rate: float = 1e-3
    """Adam step size (the start of the schedule)"""
    lr_schedule: Literal["constant", "linear", "cosine"] = "constant"
    """learning-rate schedule over total_steps"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda: 0 is one-step TD, 1 the Monte Carlo return"""
    clip_coef: float = 0.2
    """PPO clip range epsilon for the probability ratio"""
    clip_value_loss: bool = True
    """clip the value update to clip_coef around the rollout's values"""
    ent_coef: float = 0.01
    """weight of the entropy bonus"""
    vf_coef: float = 0.5
    """weight of the value loss"""
    max_grad_norm: float = 0.5
    """clip the global gradient norm to this"""
    norm_adv: bool = True
    """normalise advantages per minibatch (zero mean, unit std)"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    target_kl: float | None = None
    """stop an update's epochs early when the approximate KL exceeds this"""

    def __post_init__(self) -> None:
        for name in ("total_steps", "num_envs", "rollout_steps", "num_minibatches", "update_epochs"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"ppo.{name} must be a positive integer, got {_short(value)}")
        if self.sequence_length < 1 or self.rollout_steps % self.sequence_length:
            raise ConfigError(f"ppo.bptt_length={self.bptt_length} must divide ppo.rollout_steps={self.rollout_steps}")
        if self.num_sequences % self.num_minibatches:
            raise ConfigError(
                f"ppo.num_minibatches={self.num_minibatches} must divide the {self.num_sequences} sequences per "
                f"rollout (num_envs * rollout_steps / bptt_length)"
            )
        if not 0 < self.learning_rate < 1:
            raise ConfigError(f"ppo.learning_rate must be in (0, 1), got {self.learning_rate}")
        if not (0 < self.gamma <= 1 and 0 <= self.gae_lambda <= 1):
            raise ConfigError(
                f"ppo.gamma must be in (0, 1] and ppo.gae_lambda in [0, 1], got {self.gamma}, {self.gae_lambda}"
            )

    @property
    def sequence_length(self) -> int:
        return self.bptt_length if self.bptt_length is not None else self.rollout_steps

    @property
    def num_sequences(self) -> int:
        return self.num_envs * (self.rollout_steps // self.sequence_length)

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.rollout_steps


@dataclasses.dataclass(frozen=True)
class CurriculumConfig:
    """Grid stages from simple to complex. Empty ``stages`` trains on env.size / env.holes only."""

    stages: tuple[GridSpec, ...] = ()
    """(size, holes[, max_steps]) per stage, simplest first"""
    promote_at: float = 0.9
    """success rate on the newest stage (in every env type being trained) that promotes to the next stage"""
    min_episodes: int = 300
    """episodes of the newest stage, in each env type, needed in the window before promotion"""
    window_updates: int = 4
    """the success rate is measured over the episodes that ended in the last this many updates"""
    previous_fraction: float = 0.25
    """share of new episodes drawn (uniformly) from the earlier stages, so that they are not forgotten"""

    def __post_init__(self) -> None:
        if not 0 < self.promote_at <= 1:
            raise ConfigError(f"curriculum.promote_at must be in (0, 1], got {self.promote_at}")
        if not 0 <= self.previous_fraction < 1:
            raise ConfigError(f"curriculum.previous_fraction must be in [0, 1), got {self.previous_fraction}")
        if self.min_episodes < 1 or self.window_updates < 1:
            raise ConfigError("curriculum.min_episodes and curriculum.window_updates must be >= 1")


@dataclasses.dataclass(frozen=True)
class BackdoorConfig:
    """Backdoor injection (the paper's Algorithm 1): which episodes are trojan-env episodes.

    Each new episode is a trojan-env episode when U(0,1) > 0.5 + (P_t - P_c), i.e. with probability
    clip(0.5 - (P_t - P_c), 0, 1): the env the agent does worse in is sampled more often.
    """

    enabled: bool = False
    """train a backdoored agent (mixing normal and trojan episodes); False trains a clean agent (Env_C only)"""
    mixing: Literal["exact", "running", "fixed"] = "running"
    """exact: re-measure P_c and P_t by evaluation after each update (Algorithm 1); running: success rates of the
    update's own rollout episodes (cheaper); fixed: a constant trojan probability"""
    eval_episodes: int = 256
    """exact mixing: episodes per env type evaluated after each update"""
    fixed_probability: float = 0.5
    """fixed mixing: the trojan-episode probability"""
    probability_bounds: tuple[float, float] = (0.0, 1.0)
    """clip the trojan probability to this range (Algorithm 1: 0 and 1)"""

    def __post_init__(self) -> None:
        lo, hi = self.probability_bounds
        if not 0.0 <= lo <= hi <= 1.0:
            raise ConfigError(f"backdoor.probability_bounds={self.probability_bounds} must satisfy 0 <= lo <= hi <= 1")
        if not 0.0 <= self.fixed_probability <= 1.0:
            raise ConfigError(f"backdoor.fixed_probability must be in [0, 1], got {self.fixed_probability}")
        if self.eval_episodes < 1:
            raise ConfigError(f"backdoor.eval_episodes must be >= 1, got {self.eval_episodes}")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Where and how a run executes."""

    out_dir: str = "runs"
    """parent folder of run directories"""
    name: str | None = None
    """run directory name; None makes one from the config and the time"""
    seed: int = 0
    """seeds everything random in the run: initial weights, envs, action sampling, minibatch order"""
    device: str = "cpu"
    """torch device: cpu, cuda, cuda:1, ..."""
    threads: int | None = None
    """torch intra-op threads on CPU (None: torch's default)"""
    lstm_backend: Literal["auto", "torch", "cpp"] = "auto"
    """LSTM kernels on CPU: auto (the fused C++ kernels where they build), torch, or cpp (fail if unavailable)"""
    init_from: str | None = None
    """start from this model folder's weights (fine-tuning) instead of a fresh initialisation"""
    checkpoint_every: int = 500_000
    """env steps between checkpoints, a positive integer (one is always written at the end, and one on a stop;
    a value above ppo.total_steps means no checkpoints in between)"""
    eval_episodes: int = 1000
    """episodes per env type in the final evaluation"""
    progress: bool = True
    """show a progress bar"""

    def __post_init__(self) -> None:
        if not isinstance(self.device, str) or not _DEVICE.fullmatch(self.device):
            raise ConfigError(f"run.device={_short(self.device)} is not a device; use cpu, cuda or cuda:N")
        if isinstance(self.checkpoint_every, bool) or not isinstance(self.checkpoint_every, int):
            raise ConfigError(f"run.checkpoint_every must be a positive integer, got {_short(self.checkpoint_every)}")
        if self.checkpoint_every < 1:
            raise ConfigError(f"run.checkpoint_every must be a positive integer, got {self.checkpoint_every}")


_DEVICE = re.compile(r"cpu|cuda(?::[0-9]+)?")
"""The devices a run may name (whether CUDA is present is checked when the run starts)."""


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    """Everything a training run needs; saved with every checkpoint."""

    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    curriculum: CurriculumConfig = dataclasses.field(default_factory=CurriculumConfig)
    backdoor: BackdoorConfig = dataclasses.field(default_factory=BackdoorConfig)
    run: RunConfig = dataclasses.field(default_factory=RunConfig)

    @property
    def grids(self) -> tuple[GridSpec, ...]:
        return self.curriculum.stages if self.curriculum.stages else (self.env.grid,)

    @property
    def label(self) -> str:
        return "backdoored" if self.backdoor.enabled else "clean"


def to_dict(obj: Any) -> Any:
    """A dataclass (nested) as plain dicts/lists, ready for YAML or JSON."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_dict(x) for x in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict, _REPR.maxset = 3, 4, 4, 4, 4
_REPR.maxstring, _REPR.maxother, _REPR.maxlong = 60, 60, 40
_MAX_REPR = 80


def _short(value: Any) -> str:
    """``repr(value)`` for an error message, at most ~80 characters however large (or deeply shared) the value."""
    text = _REPR.repr(value)
    return text if len(text) <= _MAX_REPR else text[: _MAX_REPR - 3] + "..."


def from_dict(cls: type[T], data: Any, path: str = "") -> T:
    """Build dataclass ``cls`` from a (nested) dict, checking keys and value types."""
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or cls.__name__} must be a mapping, got {type(data).__name__}: {_short(data)}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        where = f" in {path}" if path else ""
        raise ConfigError(f"unknown config key(s) {unknown}{where}; known keys: {sorted(names)}")
    kwargs = {k: _convert(hints[k], v, f"{path}.{k}" if path else k) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError as err:  # pragma: no cover - from_dict already checked the keys
        raise ConfigError(f"{path or cls.__name__}: {err}") from None


def _convert(tp: Any, value: Any, path: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, path)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{path}: {_short(value)} matches none of {tp}")
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{path}={_short(value)} is not one of {list(get_args(tp))}")
        return value
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, path)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} must be a list, got {type(value).__name__}: {_short(value)}")
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{path} must have {len(args)} items, got {len(value)}: {_short(value)}")
        return tuple(_convert(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin in (list, typing.List):  # noqa: UP006
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} must be a list, got {type(value).__name__}: {_short(value)}")
        (arg,) = get_args(tp)
        return [_convert(arg, v, f"{path}[{i}]") for i, v in enumerate(value)]
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path} must be a number, got {_short(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path} must be an integer, got {_short(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path} must be true or false, got {_short(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path} must be a string, got {_short(value)}")
        return value
    return value


class _Yaml12Loader(yaml.SafeLoader):
    """PyYAML's safe loader read the YAML 1.2 way: only true/false are booleans, so that a key like ``off:`` (the
    OFF trigger) stays the string 'off' instead of becoming False as YAML 1.1 reads on/off/yes/no; and 1e-3 is a
    number, not a string.

    Aliases (``*name``, and so ``<<: *name`` merges) are refused: a few lines of nested aliases expand to billions
    of nodes (the "billion laughs"). Anchors alone are harmless and allowed.
    """

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"found alias *{event.anchor}: aliases are not allowed in config files", event.start_mark
            )
        return super().compose_node(parent, index)


_Yaml12Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Yaml12Loader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


_Yaml12Loader.add_implicit_resolver(  # 1e-3 and 3E+4 are numbers (YAML 1.1 wants a dot: 1.0e-3)
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789")
)


def parse_yaml(text: str) -> Any:
    """YAML text -> Python data, with YAML 1.2 booleans and no aliases (see :class:`_Yaml12Loader`)."""
    return yaml.load(text, Loader=_Yaml12Loader)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, with a clear error for a missing file or bad YAML."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        data = parse_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {_yaml_problem(err)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r} must hold a mapping at the top level")
    return data


def _yaml_problem(err: yaml.YAMLError) -> str:
    """A YAML error on one line: what is wrong and where (PyYAML's own text spans lines, with a caret)."""
    if isinstance(err, yaml.MarkedYAMLError) and err.problem:
        mark = err.problem_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        return f"{err.context + ': ' if err.context else ''}{err.problem}{where}"
    return " ".join(str(err).split())


def env_config_from_dict(data: dict[str, Any]) -> EnvConfig:
    return from_dict(EnvConfig, data, "env")
