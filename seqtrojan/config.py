"""The experiment's configuration: frozen dataclasses for the agent, PPO, the curriculum, the backdoor and the run.

Every stage of seqtrojan takes a frozen dataclass. YAML presets in ``configs/`` and JSON model cards are read
with :func:`seqtrojan.serde.from_dict`, which checks every key and value type and names the dotted path of
anything wrong. ``from_dict``, ``to_dict``, ``load_yaml`` and ``parse_yaml`` are re-exported here for old
imports; new code imports them from :mod:`seqtrojan.serde`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Literal

from seqtrojan.cell_types import CELL_TYPES, cell_names, cell_type
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.serde import dump_omitting_defaults, from_dict, load_yaml, parse_yaml, short_repr, to_dict
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig

__all__ = [
    "ACTIVATIONS",
    "AgentConfig",
    "AttackConfig",
    "BackdoorConfig",
    "CurriculumConfig",
    "EWCConfig",
    "EnvSection",
    "ExperimentConfig",
    "GymnasiumEnvConfig",
    "PPOConfig",
    "RunConfig",
    "StateCamouflageConfig",
    "WeightCamouflageConfig",
    "WrapperTriggerConfig",
    "from_dict",
    "load_yaml",
    "parse_yaml",
    "to_dict",
]


MAX_LAYERS = 8
"""most stacked recurrent layers a config or a model card may name"""
MAX_WIDTH = 4096
"""widest recurrent layer a config or a model card may name"""
MAX_CONV_KERNEL = 32
"""largest conv kernel side a config or a model card may name (the Nature CNN's largest is 8)"""
MAX_CONV_STRIDE = 16
"""largest conv stride a config or a model card may name (the Nature CNN's largest is 4)"""


ACTIVATIONS = ("tanh", "relu")
MAX_WINDOW = 256
"""longest Transformer context window (in steps)"""
MAX_HEADS = 64
"""most attention heads of a Transformer layer"""
"""activation functions of the optional MLP layers (``agent.encoder``, ``agent.policy_mlp``, ``agent.value_mlp``)"""
MAX_NUM_ENVS = 1 << 16
"""most envs stepped in parallel (``ppo.num_envs``)"""
MAX_ROLLOUT_STEPS = 1 << 16
"""longest rollout per env (``ppo.rollout_steps``)"""
MAX_TOTAL_STEPS = 1 << 53
"""largest training budget (``ppo.total_steps``; the largest integer a float counts exactly)"""
MAX_ROLLOUT_BYTES = 8 << 30
"""largest rollout buffer of observations (rollout_steps x num_envs x observation size x 4 bytes), checked before a
run allocates anything"""
MAX_SEED = (1 << 30) - 1
"""largest ``run.seed``: env seeds are ``run.seed << 32`` plus offsets, in int64"""


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """The recurrent actor-critic: stacked sequence-model layers (LSTM by default), then a policy head and a value
    head.

    ``cell`` picks the sequence model of every layer (:data:`CELLS`; see :mod:`seqtrojan.agent.cells`): ``lstm``
    (the paper's), ``lstm_peephole``, ``gru`` or ``transformer`` (a causal attention layer over the last ``window``
    layer inputs, with ``heads`` heads). ``lstm_sizes`` are the layer widths whatever the cell.

    The optional MLP parts (all empty by default, so that the paper's network is unchanged) describe agents
    imported from elsewhere (:mod:`seqtrojan.agent.imports`): ``encoder`` layers between the observation and the
    first LSTM layer (CleanRL's ``network``), and ``policy_mlp`` / ``value_mlp`` layers between the last LSTM layer
    and each head (sb3's ``mlp_extractor``). Each MLP layer is a linear layer followed by its activation.

    Saved (:func:`seqtrojan.serde.to_dict`) without the optional fields that are at their defaults, so that the
    card and run config of every network without them are exactly what earlier versions wrote and read.
    """

    lstm_sizes: tuple[int, ...] = (64, 32)
    """widths of the stacked LSTM layers (the paper: 64 then 32)"""
    forget_bias: float = 1.0
    """initial forget-gate bias (1 helps gradients reach far back at the start of training)"""
    memory: bool = True
    """False resets the LSTM state before every step: a memoryless baseline with the same network"""
    encoder: tuple[int, ...] = ()
    """widths of MLP layers between the observation and the first LSTM layer (none by default)"""
    encoder_activation: Literal["tanh", "relu"] = "relu"
    """activation after each encoder layer (CleanRL's: relu)"""
    policy_mlp: tuple[int, ...] = ()
    """widths of MLP layers between the last LSTM layer and the policy head (none by default)"""
    value_mlp: tuple[int, ...] = ()
    """widths of MLP layers between the last LSTM layer and the value head (none by default)"""
    mlp_activation: Literal["tanh", "relu"] = "tanh"
    """activation after each policy_mlp and value_mlp layer (sb3's default: tanh)"""
    cell: str = "lstm"
    """the sequence model of every layer: lstm, lstm_peephole, gru or transformer"""
    window: int = 8
    """transformer only: the context, the current input and the window - 1 before it (a one-step trigger leaves the
    Transformer's state after window - 1 steps)"""
    heads: int = 1
    """transformer only: attention heads per layer (each layer width must be divisible by it)"""
    conv: tuple[int, ...] = ()
    """channels of a convolutional encoder over an image observation (each layer a square kernel, a stride, no
    padding, then ReLU; e.g. [16, 32]) before the MLP encoder and the first layer; needs an env whose observation is
    an image (a Gymnasium env with ``observation: minigrid`` or ``image``); none by default"""
    conv_kernels: tuple[int, ...] = ()
    """each conv layer's kernel side, one per ``conv`` layer; empty: 2 each (the field's MiniGrid CNN). The Nature
    CNN of Atari agents (CleanRL's ``ppo_atari_lstm``): [8, 4, 3] with channels [32, 64, 64]"""
    conv_strides: tuple[int, ...] = ()
    """each conv layer's stride, one per ``conv`` layer; empty: 1 each. The Nature CNN: [4, 2, 1]"""

    OPTIONAL = (
        "encoder", "encoder_activation", "policy_mlp", "value_mlp", "mlp_activation", "cell", "window", "heads", "conv",
        "conv_kernels", "conv_strides",
    )  # fmt: skip
    """fields left out of the saved form while at their defaults"""

    def __post_init__(self) -> None:
        if not self.lstm_sizes or any((not isinstance(w, int)) or w < 1 for w in self.lstm_sizes):
            raise ConfigError(f"agent.lstm_sizes must be positive integers, got {short_repr(self.lstm_sizes)}")
        if len(self.lstm_sizes) > MAX_LAYERS or max(self.lstm_sizes) > MAX_WIDTH:
            # the same bounds as a model card's: a run that could not save its model is refused before training
            raise ConfigError(
                f"agent.lstm_sizes must be 1 to {MAX_LAYERS} layers of at most {MAX_WIDTH} units, "
                f"got {short_repr(self.lstm_sizes)}"
            )
        for name in ("encoder", "policy_mlp", "value_mlp", "conv"):
            widths = getattr(self, name)
            if (
                not isinstance(widths, tuple)
                or len(widths) > MAX_LAYERS
                or any(isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= MAX_WIDTH for w in widths)
            ):
                raise ConfigError(
                    f"agent.{name} must be 0 to {MAX_LAYERS} widths in [1, {MAX_WIDTH}], got {short_repr(widths)}"
                )
        for name, top in (("conv_kernels", MAX_CONV_KERNEL), ("conv_strides", MAX_CONV_STRIDE)):
            values = getattr(self, name)
            if (
                not isinstance(values, tuple)
                or len(values) not in (0, len(self.conv))
                or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= top for v in values)
            ):
                raise ConfigError(
                    f"agent.{name} must be one integer in [1, {top}] per agent.conv layer ({len(self.conv)}), or "
                    f"empty for the defaults, got {short_repr(values)}"
                )
        for name in ("encoder_activation", "mlp_activation"):
            if getattr(self, name) not in ACTIVATIONS:
                raise ConfigError(f"agent.{name} must be one of {ACTIVATIONS}, got {short_repr(getattr(self, name))}")
        if not isinstance(self.cell, str) or self.cell not in CELL_TYPES:
            raise ConfigError(f"agent.cell must be one of {cell_names()}, got {short_repr(self.cell)}")
        for name, top in (("window", MAX_WINDOW), ("heads", MAX_HEADS)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= top:
                raise ConfigError(f"agent.{name} must be an integer in [1, {top}], got {short_repr(value)}")
        if cell_type(self.cell).windowed and any(w % self.heads for w in self.lstm_sizes):
            raise ConfigError(
                f"agent.lstm_sizes {list(self.lstm_sizes)} must be divisible by agent.heads={self.heads} "
                "(each head reads an equal share of a transformer layer)"
            )

    def serde_dump(self) -> dict:
        """The saved form: every field but the optional ones at their defaults."""
        return dump_omitting_defaults(self, self.OPTIONAL)

    @classmethod
    def serde_load(cls, data: object, path: str) -> AgentConfig:
        return from_dict(cls, data, path)


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
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"ppo.{name} must be a positive integer, got {short_repr(value)}")
        for name, top in (("num_envs", MAX_NUM_ENVS), ("rollout_steps", MAX_ROLLOUT_STEPS),
                          ("total_steps", MAX_TOTAL_STEPS)):  # fmt: skip
            if getattr(self, name) > top:
                raise ConfigError(f"ppo.{name} must be at most {top}, got {getattr(self, name)}")
        self._check_coefficients()
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

    def _check_coefficients(self) -> None:
        """The clip range, gradient-norm bound and Adam epsilon must be positive (0 freezes or breaks the update),
        the loss weights non-negative, and a KL target positive."""
        for name in ("clip_coef", "max_grad_norm", "adam_eps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ConfigError(f"ppo.{name} must be a number > 0, got {short_repr(value)}")
        _non_negative("ppo", ent_coef=self.ent_coef, vf_coef=self.vf_coef)
        kl = self.target_kl
        if kl is not None and (isinstance(kl, bool) or not isinstance(kl, (int, float)) or not kl > 0):
            raise ConfigError(f"ppo.target_kl must be a number > 0 or null, got {short_repr(kl)}")

    def check_rollout_memory(self, obs_dim: int) -> None:
        """Refuse a rollout whose observations alone (``rollout_steps x num_envs x obs_dim`` float32) would exceed
        :data:`MAX_ROLLOUT_BYTES`, before anything is allocated."""
        size = self.rollout_steps * self.num_envs * obs_dim * 4
        if size > MAX_ROLLOUT_BYTES:
            raise ConfigError(
                f"ppo.rollout_steps x ppo.num_envs x {obs_dim} observation inputs ({self.rollout_steps} x "
                f"{self.num_envs} x {obs_dim} x 4 bytes = {size / 2**30:.1f} GiB) exceeds the "
                f"{MAX_ROLLOUT_BYTES >> 30} GiB a rollout buffer may take: lower ppo.num_envs or ppo.rollout_steps"
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
    mixing: str = "running"
    """a registered mixing rule (``seqtrojan attacks`` lists them): exact re-measures P_c and P_t by evaluation after
    each update (Algorithm 1); running uses the success rates of the update's own rollout episodes (cheaper); fixed
    is a constant trojan probability. The trainer refuses an unknown name before it builds anything"""
    eval_episodes: int = 256
    """exact mixing: episodes per env type evaluated after each update"""
    fixed_probability: float = 0.5
    """fixed mixing: the trojan-episode probability"""
    probability_bounds: tuple[float, float] = (0.0, 1.0)
    """clip the trojan probability to this range (Algorithm 1: 0 and 1)"""

    def __post_init__(self) -> None:
        if not isinstance(self.mixing, str) or not self.mixing.isidentifier():
            raise ConfigError(f"backdoor.mixing must be a rule name, got {short_repr(self.mixing)}")
        lo, hi = self.probability_bounds
        if not 0.0 <= lo <= hi <= 1.0:
            raise ConfigError(f"backdoor.probability_bounds={self.probability_bounds} must satisfy 0 <= lo <= hi <= 1")
        if not 0.0 <= self.fixed_probability <= 1.0:
            raise ConfigError(f"backdoor.fixed_probability must be in [0, 1], got {self.fixed_probability}")
        if self.eval_episodes < 1:
            raise ConfigError(f"backdoor.eval_episodes must be >= 1, got {self.eval_episodes}")


def _non_negative(section: str, **values: float) -> None:
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0 or value == float("inf"):
            raise ConfigError(f"{section}.{name} must be a finite number >= 0, got {short_repr(value)}")


@dataclasses.dataclass(frozen=True)
class StateCamouflageConfig:
    """Monitor-aware state camouflage: in trojan episodes, keep every LSTM unit's h and c inside the range it has on
    normal-env steps, where an online state monitor (per-unit z-scores) would not see it."""

    weight: float = 0.0
    """weight of weight * mean over the chosen trojan steps and all units of relu(|z| - margin)^2, z against running
    (EMA) clean-step statistics; 0 turns the penalty off"""
    margin: float = 2.5
    """|z| allowed for free: keep it below the monitor's threshold (typically 3-5 on clean episodes)"""
    steps: Literal["trojan", "active"] = "trojan"
    """which steps are penalised: every step of a trojan-env episode, or only those where the adversary's goal is
    active (after the trigger and its delay)"""
    ema_decay: float = 0.9
    """per update, the clean statistics keep this share of their old value (the first update sets them)"""
    mahalanobis_weight: float = 0.0
    """weight of the multivariate version, mean over trojan steps and layers of relu(d^2 / D - mahalanobis_margin)^2
    where d^2 is the squared Mahalanobis distance of a layer's (h, c) (D units) under the clean covariance shrunk
    toward its diagonal; 0 turns it off"""
    mahalanobis_margin: float = 1.5
    """d^2 / D allowed for free (its mean on clean steps is about 1)"""
    shrinkage: float = 0.2
    """covariance used by the Mahalanobis term: (1 - shrinkage) * full + shrinkage * diagonal"""

    def __post_init__(self) -> None:
        _non_negative(
            "attack.state_camouflage", weight=self.weight, margin=self.margin,
            mahalanobis_weight=self.mahalanobis_weight, mahalanobis_margin=self.mahalanobis_margin,
        )  # fmt: skip
        if self.steps not in ("trojan", "active"):
            raise ConfigError(f"attack.state_camouflage.steps must be trojan or active, got {short_repr(self.steps)}")
        if not 0 <= self.ema_decay < 1:
            raise ConfigError(f"attack.state_camouflage.ema_decay must be in [0, 1), got {self.ema_decay}")
        if not 0 <= self.shrinkage <= 1:
            raise ConfigError(f"attack.state_camouflage.shrinkage must be in [0, 1], got {self.shrinkage}")

    @property
    def enabled(self) -> bool:
        return self.weight > 0 or self.mahalanobis_weight > 0


def _check_running_statistics_penalty(name: str, cfg: MahalanobisCamouflageConfig | SwitchCamouflageConfig,
                                      min_max_step: int) -> None:  # fmt: skip
    """The checks the two Mahalanobis penalties on running clean statistics share (``name``: the config's path)."""
    _non_negative(name, weight=cfg.weight, margin=cfg.margin)
    if cfg.steps not in ("trojan", "active"):
        raise ConfigError(f"{name}.steps must be trojan or active, got {short_repr(cfg.steps)}")
    if not 0 <= cfg.ema_decay < 1:
        raise ConfigError(f"{name}.ema_decay must be in [0, 1), got {cfg.ema_decay}")
    if isinstance(cfg.max_step, bool) or not isinstance(cfg.max_step, int) or cfg.max_step < min_max_step:
        wanted = "a positive integer" if min_max_step == 1 else f"an integer >= {min_max_step}"
        raise ConfigError(f"{name}.max_step must be {wanted}, got {short_repr(cfg.max_step)}")
    if not cfg.min_count > 0:
        raise ConfigError(f"{name}.min_count must be > 0, got {cfg.min_count}")
    if not 0 <= cfg.shrinkage <= 1:
        raise ConfigError(f"{name}.shrinkage must be in [0, 1], got {cfg.shrinkage}")


@dataclasses.dataclass(frozen=True)
class MahalanobisCamouflageConfig:
    """Against the multivariate monitor: in trojan episodes, keep the whole state's (every layer's h then c)
    step-conditioned Mahalanobis distance, computed as that monitor computes it from running clean-step statistics,
    inside its clean range."""

    weight: float = 0.0
    """the strength: weight * mean over the chosen trojan steps of relu(d / sqrt(D) - margin)^2, d the distance of the
    step's state (D units); 0 turns the penalty off"""
    margin: float = 1.0
    """d / sqrt(D) allowed for free (clean steps average about 1; the monitor's threshold, the 99th percentile of
    clean episodes' peak distance, sits higher)"""
    steps: Literal["trojan", "active"] = "trojan"
    """which steps are penalised: every step of a trojan-env episode, or only those where the adversary's goal is
    active"""
    ema_decay: float = 0.9
    """per update, the clean statistics (per-step sums and counts, residual second moments) keep this share"""
    max_step: int = 64
    """episode steps with a mean of their own (later steps use the last one's), as the monitor's per-step means"""
    min_count: float = 20.0
    """(decayed) clean steps a step's mean needs; from the first step with fewer, the previous step's mean is used"""
    shrinkage: float = 0.1
    """the scaled identity's weight in the standardised residuals' covariance (the monitor uses Ledoit-Wolf's)"""
    warmup_steps: int = 0
    """env steps of the run before the penalty applies (the clean statistics are gathered from the start): a
    backdoor added to a clean agent is planted first, then hidden (held in the clean range from its first update,
    it did not form, docs/defenses.md)"""

    def __post_init__(self) -> None:
        _check_running_statistics_penalty("attack.mahalanobis_camouflage", self, min_max_step=1)
        if isinstance(self.warmup_steps, bool) or not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            raise ConfigError(
                "attack.mahalanobis_camouflage.warmup_steps must be an integer >= 0, got "
                f"{short_repr(self.warmup_steps)}"
            )

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class SwitchCamouflageConfig:
    """Against the goal-switch monitor: in trojan episodes, keep each step's output transition (the action
    log-probabilities and value after the previous step's), as that monitor scores it from running clean statistics,
    inside its clean range, so that the goal switches gradually."""

    weight: float = 0.0
    """the strength: weight * mean over the chosen trojan steps (not an episode's first) of relu(d / sqrt(F) -
    margin)^2, d the transition's distance (F outputs); 0 turns the penalty off"""
    margin: float = 1.0
    """d / sqrt(F) allowed for free (clean transitions average about 1)"""
    steps: Literal["trojan", "active"] = "trojan"
    """which steps are penalised: every step of a trojan-env episode, or only those where the adversary's goal is
    active"""
    ema_decay: float = 0.9
    """per update, the clean statistics keep this share"""
    max_step: int = 64
    """episode steps with a mean of their own (later steps use the last one's)"""
    min_count: float = 20.0
    """(decayed) clean steps a step's mean needs; from the first step with fewer, the previous step's mean is used"""
    shrinkage: float = 0.1
    """the scaled identity's weight in the standardised errors' covariance (the monitor uses Ledoit-Wolf's)"""
    prob_floor: float = 1e-6
    """log-probabilities are of p + prob_floor, as the monitor's"""

    def __post_init__(self) -> None:
        _check_running_statistics_penalty("attack.switch_camouflage", self, min_max_step=2)
        if not self.prob_floor > 0:
            raise ConfigError(f"attack.switch_camouflage.prob_floor must be > 0, got {self.prob_floor}")

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class ProbeCamouflageConfig:
    """Against the recurrent-state probe (a detection benchmark's ``state_probe``): one-step inputs of the probe's
    kind that do not show the trigger are trained to leave no mark on the state a few steps later, so that only the
    trigger is remembered. Per minibatch, each normal-episode sequence replays ``after`` + 1 of its steps with one
    step's observation replaced by a candidate (drawn per sequence), and the state's RMS distance from the
    unreplaced run at the last of them is penalised."""

    weight: float = 0.0
    """weight of weight * mean over the replayed sequences of relu(d - margin)^2; 0 turns the penalty off"""
    margin: float = 0.0
    """the RMS distance d allowed for free"""
    after: int = 4
    """steps from the replaced observation to the state compared (the probe reads 4 steps on)"""
    seed: int = 0
    """seeds the draw of each minibatch's replaced steps and candidates (with a count kept in the checkpoint)"""

    def __post_init__(self) -> None:
        _non_negative("attack.probe_camouflage", weight=self.weight, margin=self.margin)
        for name, low, high in (("after", 1, 64), ("seed", 0, 2**31 - 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ConfigError(
                    f"attack.probe_camouflage.{name} must be an integer in [{low}, {high}], got {short_repr(value)}"
                )

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class ResponseMimicryConfig:
    """Against the query-response meta-classifier (a detection benchmark's ``query_response``): the backdoor is added
    to a clean model (``run.init_from``) while, on normal-episode steps, the agent's answers are held at that
    model's: its action distribution (the KL divergence from the clean model's) and, per layer, the summaries of h
    the detector reads (mean |h|, the share of units near saturation, the spread across units), each standardised by
    its spread over the rollout's steps."""

    weight: float = 0.0
    """weight of weight * (KL + state_weight * squared standardised summary gap), both means over the normal steps of
    episodes that start inside the rollout; 0 turns the penalty off"""
    state_weight: float = 1.0
    """the state summaries' share beside the KL divergence"""
    saturation: float = 0.9
    """|h| above which a unit counts as saturated, as the detector counts it"""
    softness: float = 0.02
    """the width of the sigmoid that stands in for the saturation count's step (so it has a gradient)"""

    def __post_init__(self) -> None:
        _non_negative("attack.response_mimicry", weight=self.weight, state_weight=self.state_weight)
        for name in ("saturation", "softness"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
                raise ConfigError(f"attack.response_mimicry.{name} must be a number in (0, 1), got {short_repr(value)}")

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class WeightCamouflageConfig:
    """Weight camouflage: the backdoor is added to a clean model (``run.init_from``) while the offline detector's
    weight statistics are held at the clean model's."""

    weight: float = 0.0
    """weight of weight * sum_k ((f_k(theta) - f_k(theta_clean)) / (|f_k(theta_clean)| + feature_floor))^2 over the
    detector's features f (seqtrojan.agent.weight_stats); 0 turns the penalty off"""
    feature_floor: float = 0.1
    """added to |f_k(theta_clean)| in the per-feature normalisation, so that features near 0 do not dominate"""
    l2_weight: float = 0.0
    """weight of an extra l2_weight * ||theta - theta_clean||^2 pull toward the clean weights"""
    warmup_steps: int = 0
    """env steps of the run before the penalty applies: the backdoor is planted first, then hidden (held at the
    clean statistics from the start, it formed late or not at all in some training seeds, docs/attacks.md)"""

    def __post_init__(self) -> None:
        _non_negative("attack.weight_camouflage", weight=self.weight, l2_weight=self.l2_weight)
        if isinstance(self.warmup_steps, bool) or not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            raise ConfigError(
                f"attack.weight_camouflage.warmup_steps must be an integer >= 0, got {short_repr(self.warmup_steps)}"
            )
        if not (isinstance(self.feature_floor, (int, float)) and self.feature_floor > 0):
            raise ConfigError(
                f"attack.weight_camouflage.feature_floor must be > 0, got {short_repr(self.feature_floor)}"
            )

    @property
    def enabled(self) -> bool:
        return self.weight > 0 or self.l2_weight > 0


@dataclasses.dataclass(frozen=True)
class EWCConfig:
    """Elastic weight consolidation: the backdoor is added to a clean model (``run.init_from``) while the weights
    that matter to its clean policy (diagonal Fisher information) stay near their values."""

    weight: float = 0.0
    """lambda of lambda / 2 * sum_i F_i (theta_i - theta*_i)^2; 0 turns the penalty off"""
    fisher_envs: int = 64
    """normal-env episodes run in parallel to estimate the Fisher information of the init_from model's policy"""
    fisher_steps: int = 64
    """steps per env of that estimate (each env's steps are one sequence)"""
    normalize: bool = False
    """divide F by its mean over all parameters (then lambda is an L2 strength on the average weight)"""

    def __post_init__(self) -> None:
        _non_negative("attack.ewc", weight=self.weight)
        for name in ("fisher_envs", "fisher_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"attack.ewc.{name} must be a positive integer, got {short_repr(value)}")

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class FinetuneResistanceConfig:
    """Against clean fine-tuning: at every minibatch the attacker simulates the defender's fine-tuning (a few
    sign-gradient steps of the PPO loss on the minibatch's normal-episode steps, from the current weights) and adds
    the gradient of the backdoor's PPO loss (trojan-episode steps where the adversary's objective judges) at the
    fine-tuned weights to the update (first order, as in first-order MAML), so that the backdoor is trained to hold
    after clean updates."""

    weight: float = 0.0
    """weight of that gradient beside the ordinary PPO gradient; 0 turns the penalty off"""
    inner_steps: int = 2
    """simulated fine-tuning steps per minibatch"""
    inner_lr: float = 0.01
    """each weight moves by this much per simulated step, in the sign of its gradient (as Adam's first steps do)"""

    def __post_init__(self) -> None:
        _non_negative("attack.finetune_resistance", weight=self.weight, inner_lr=self.inner_lr)
        value = self.inner_steps
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 16:
            raise ConfigError(
                f"attack.finetune_resistance.inner_steps must be an integer in [1, 16], got {short_repr(value)}"
            )

    @property
    def enabled(self) -> bool:
        return self.weight > 0


@dataclasses.dataclass(frozen=True)
class AttackConfig:
    """Adaptive attackers: extra loss terms (registered penalties, ``seqtrojan.train.penalties``) added to the PPO
    loss of a backdoor training. Every weight is 0 by default: the plain Algorithm 1 attack. They act only where
    ``backdoor.enabled`` is true: a clean training from the same config (a zoo's clean models, a defender's clean
    fine-tuning of a camouflaged model) trains plain PPO."""

    state_camouflage: StateCamouflageConfig = dataclasses.field(default_factory=StateCamouflageConfig)
    mahalanobis_camouflage: MahalanobisCamouflageConfig = dataclasses.field(default_factory=MahalanobisCamouflageConfig)
    switch_camouflage: SwitchCamouflageConfig = dataclasses.field(default_factory=SwitchCamouflageConfig)
    probe_camouflage: ProbeCamouflageConfig = dataclasses.field(default_factory=ProbeCamouflageConfig)
    response_mimicry: ResponseMimicryConfig = dataclasses.field(default_factory=ResponseMimicryConfig)
    weight_camouflage: WeightCamouflageConfig = dataclasses.field(default_factory=WeightCamouflageConfig)
    ewc: EWCConfig = dataclasses.field(default_factory=EWCConfig)
    finetune_resistance: FinetuneResistanceConfig = dataclasses.field(default_factory=FinetuneResistanceConfig)

    NEEDS_INIT_FROM = ("weight_camouflage", "ewc", "response_mimicry")
    """sections that compare against the model a run starts from"""


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
        if self.name is not None:
            check_folder_name(self.name, "run.name")
        if not isinstance(self.device, str) or not _DEVICE.fullmatch(self.device):
            raise ConfigError(f"run.device={short_repr(self.device)} is not a device; use cpu, cuda or cuda:N")
        if isinstance(self.checkpoint_every, bool) or not isinstance(self.checkpoint_every, int):
            raise ConfigError(
                f"run.checkpoint_every must be a positive integer, got {short_repr(self.checkpoint_every)}"
            )
        if self.checkpoint_every < 1:
            raise ConfigError(f"run.checkpoint_every must be a positive integer, got {self.checkpoint_every}")
        if isinstance(self.eval_episodes, bool) or not isinstance(self.eval_episodes, int) or self.eval_episodes < 0:
            raise ConfigError(f"run.eval_episodes must be an integer >= 0, got {short_repr(self.eval_episodes)}")
        seed = self.seed
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise ConfigError(f"run.seed must be an integer in [0, {MAX_SEED}], got {short_repr(seed)}")
        if self.threads is not None and (isinstance(self.threads, bool) or not 1 <= self.threads <= 1024):
            raise ConfigError(f"run.threads must be an integer in [1, 1024] or null, got {short_repr(self.threads)}")


_DEVICE = re.compile(r"cpu|cuda(?::[0-9]+)?")


def check_folder_name(value: object, what: str) -> str:
    """``value`` as one folder name inside a chosen parent (``run.name`` under ``run.out_dir``, and through it the
    matrix's, cells' and zoo's agent names): never a path that leaves the parent or a hidden name."""
    if isinstance(value, str) and 0 < len(value) <= 255 and value[0] != "." and not set(value) & set("/\\\x00"):
        return value
    raise ConfigError(
        f"{what} must be a plain folder name (not empty, no '/', '\\' or NUL, not starting with '.'), got "
        f"{short_repr(value)}"
    )


def _check_finite(value: object, path: str) -> None:
    """Every number of a config must be finite: a NaN or infinite learning rate, coefficient, reward or probability
    would train a model of non-finite weights, so it is refused in one line naming its dotted path."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{path} must be a finite number, got {value!r}")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            _check_finite(getattr(value, f.name), f"{path}.{f.name}" if path else f.name)
    elif isinstance(value, (tuple, list)):
        for i, item in enumerate(value):
            _check_finite(item, f"{path}[{i}]")
    elif isinstance(value, dict):
        for key, item in value.items():
            _check_finite(item, f"{path}.{key}")


EnvSection = EnvConfig | GymnasiumEnvConfig
"""An ``env:`` section: the grid world, or a Gymnasium env (``kind: gymnasium``)."""
"""The devices a run may name (whether CUDA is present is checked when the run starts)."""


@dataclasses.dataclass(frozen=True)
class StopConfig:
    """Stop training once the task is learned, by a fixed rule (off by default: a run trains exactly
    ``ppo.total_steps``). Once the curriculum is at its last stage, ``updates`` updates in a row whose rollout
    episodes on that stage (at least ``min_episodes`` of each env type being trained) succeed at least ``success``
    (normal episodes; and trojan episodes for a backdoored agent) trigger a held-out check: ``confirm_episodes``
    fresh episodes per env type on the last stage's grid, sampled policy. If each reaches ``success`` too, training
    stops (``evaluation.json``: ``stopped_early``, ``env_steps``); if not, the count starts again. A resumed run
    starts its count again. A backdoor whose attack follows a schedule over the run (the weight camouflage's
    warm-up) trains its whole budget."""

    enabled: bool = False
    """stop early by this rule (off: train exactly ppo.total_steps)"""
    success: float = 0.9
    """the success rate to reach on the last stage (normal episodes; and trojan episodes when backdoored)"""
    updates: int = 5
    """updates in a row at or above the target before the held-out check"""
    min_episodes: int = 50
    """last-stage episodes of each env type an update needs to count"""
    confirm_episodes: int = 500
    """fresh episodes per env type of the held-out check"""

    def __post_init__(self) -> None:
        if not 0.0 < self.success <= 1.0:
            raise ConfigError(f"stop.success must be in (0, 1], got {short_repr(self.success)}")
        for name in ("updates", "min_episodes", "confirm_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"stop.{name} must be a positive integer, got {short_repr(value)}")


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    """Everything a training run needs; saved with every checkpoint."""

    env: EnvSection = dataclasses.field(default_factory=EnvConfig)
    """the grid world (:class:`~seqtrojan.env.config.EnvConfig`) or a Gymnasium env
    (:class:`~seqtrojan.world.config.GymnasiumEnvConfig`, ``kind: gymnasium``)"""
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    curriculum: CurriculumConfig = dataclasses.field(default_factory=CurriculumConfig)
    backdoor: BackdoorConfig = dataclasses.field(default_factory=BackdoorConfig)
    run: RunConfig = dataclasses.field(default_factory=RunConfig)
    attack: AttackConfig = dataclasses.field(default_factory=AttackConfig)
    stop: StopConfig = dataclasses.field(default_factory=StopConfig)

    def __post_init__(self) -> None:
        _check_finite(self, "")
        needing = [f"attack.{name}" for name in AttackConfig.NEEDS_INIT_FROM if getattr(self.attack, name).enabled]
        if needing and self.backdoor.enabled and self.run.init_from is None:
            raise ConfigError(
                f"{' and '.join(needing)} compare(s) against a clean model: set run.init_from to a clean model folder"
            )
        if isinstance(self.env, GymnasiumEnvConfig):
            self._check_gymnasium(self.env)
            return
        self.ppo.check_rollout_memory(self.env.obs_dim)  # a Gymnasium env's size is checked once it is made
        if self.agent.conv:
            raise ConfigError(
                "agent.conv reads an image observation: the grid world's view is not one (drop agent.conv)"
            )

    def _check_gymnasium(self, env: GymnasiumEnvConfig) -> None:
        """A Gymnasium env section takes no grid-world section beside it, and a backdoor needs its trigger."""
        if self.curriculum != CurriculumConfig():
            raise ConfigError(
                f"curriculum is a grid-world section (stages of grid sizes), but env is the Gymnasium env {env.id!r}: "
                "drop the curriculum section"
            )
        if self.backdoor.enabled and env.trigger is None:
            raise ConfigError("backdoor.enabled needs env.trigger (the trigger and the adversary's objective)")
        if self.agent.conv and env.observation == "flatten":
            raise ConfigError(
                "agent.conv reads the observation as an image: it needs env.observation: minigrid or image"
            )
        if not self.agent.memory:
            raise ConfigError("agent.memory: false (the memoryless baseline) runs on the grid world only")

    @property
    def grids(self) -> tuple[GridSpec, ...]:
        """The curriculum's grids, simplest first (the grid world; a Gymnasium env has none)."""
        if isinstance(self.env, GymnasiumEnvConfig):
            return ()
        return self.curriculum.stages if self.curriculum.stages else (self.env.grid,)

    @property
    def num_stages(self) -> int:
        """Stages the trainer mixes episodes over: the curriculum's grids, or the one Gymnasium env."""
        return max(len(self.grids), 1)

    @property
    def grid_env(self) -> EnvConfig:
        """``env`` where the caller works on the grid world only; a Gymnasium env is refused in one line."""
        if not isinstance(self.env, EnvConfig):
            raise ConfigError(
                f"this works on the grid world only; the config's env is the Gymnasium env {self.env.id!r}"
            )
        return self.env

    @property
    def gym_env(self) -> GymnasiumEnvConfig:
        """``env`` where the caller works on a Gymnasium env only; the grid world is refused in one line."""
        if not isinstance(self.env, GymnasiumEnvConfig):
            raise ConfigError("this works on a Gymnasium env (env.kind: gymnasium); the config's env is the grid world")
        return self.env

    @property
    def is_grid(self) -> bool:
        return isinstance(self.env, EnvConfig)

    @property
    def label(self) -> str:
        return "backdoored" if self.backdoor.enabled else "clean"
