"""Configuration of a training run on a Gymnasium env (:func:`seqtrojan.train.gym_trainer.train_gym`).

The same shape as the grid world's :class:`~seqtrojan.config.ExperimentConfig` where the two agree (``ppo`` and
``backdoor`` are the same sections), with the env named by a Gymnasium id and the trigger described in its own
section. Presets: ``seqtrojan/presets/minigrid_two_goals.yaml``, ``minigrid_memory.yaml`` and
``minigrid_memory_backdoor.yaml`` (:func:`load_gym_config`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, ClassVar, Literal

from seqtrojan.config import MAX_LAYERS, MAX_WIDTH, AgentConfig, AttackConfig, BackdoorConfig, PPOConfig
from seqtrojan.errors import ConfigError
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import dump_omitting_defaults, from_dict, load_yaml, short_repr

Cell = tuple[int, int]


@dataclasses.dataclass(frozen=True)
class GymEnvConfig:
    """Which env, and how its observations become the flat float vector the recurrent policy takes."""

    id: str
    """a registered Gymnasium id (``module:Id`` imports ``module`` first, Gymnasium's way for your own envs)"""
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    """keyword arguments of ``gymnasium.make``"""
    observation: Literal["minigrid", "flatten"] = "minigrid"
    """minigrid: MiniGrid's view one-hot encoded per channel (:class:`~seqtrojan.wrappers.MiniGridOneHot`);
    flatten: any observation flattened to float32 (:class:`~seqtrojan.wrappers.FlattenFloat`)"""
    num_actions: int | None = None
    """keep only the env's first N discrete actions (:class:`~seqtrojan.wrappers.FirstActions`; MiniGrid's first
    three are turn left, turn right, forward); None: all"""
    fast_view: bool = True
    """a MiniGrid env computes its partial view with :mod:`seqtrojan.minigrid.fast_obs` (the same observation as
    MiniGrid's ``gen_obs``, several times faster); false: MiniGrid's own method"""

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ConfigError(f"env.id must be a Gymnasium id, got {short_repr(self.id)}")
        if self.num_actions is not None and (
            isinstance(self.num_actions, bool) or not isinstance(self.num_actions, int) or self.num_actions < 1
        ):
            raise ConfigError(f"env.num_actions must be a positive integer or null, got {short_repr(self.num_actions)}")
        if not isinstance(self.fast_view, bool):
            raise ConfigError(f"env.fast_view must be true or false, got {short_repr(self.fast_view)}")


@dataclasses.dataclass(frozen=True)
class GymTriggerConfig:
    """The trigger wrapper's settings (:class:`~seqtrojan.wrappers.TriggerWrapper`) for a MiniGrid patch (an
    object drawn on view cells) or a Box patch (a value on image cells)."""

    objective: str = "reach_adversary_object"
    """the adversary's objective, a name registered in ``seqtrojan.wrappers.ADVERSARY_OBJECTIVES``"""
    patch: Literal["minigrid", "box"] = "minigrid"
    """minigrid: a MiniGridPatch on obs["image"]; box: a BoxPatch on the (image) observation"""
    cells: tuple[Cell, ...] = ((0, 0), (0, 1))
    """(row, col) cells the patch draws on"""
    object: str = "key"
    """minigrid patch: the object drawn"""
    color: str = "purple"
    """minigrid patch: its colour"""
    value: float = 255.0
    """box patch: the value drawn"""
    key: str | None = None
    """box patch: the image's key in a Dict observation (None: the observation is the image)"""
    steps: tuple[int, int] = (0, 2)
    """inclusive range of the trigger's first step during training"""
    eval_steps: tuple[int, int] | None = None
    """range during evaluation; None means ``steps``"""
    duration: int = 1
    """steps the patch stays visible"""
    delay: int = 0
    """activation delay: the objective switches this many steps after the trigger takes effect"""
    off_probability: float = 0.0
    """share of trojan episodes that also show an OFF trigger (the same kind of patch on ``off_cells``)"""
    off_cells: tuple[Cell, ...] = ((0, 3), (0, 4))
    """OFF trigger cells"""
    off_gap: tuple[int, int] = (3, 8)
    """inclusive range of steps from the ON trigger's first step to the OFF trigger's"""

    def __post_init__(self) -> None:
        for name in ("steps", "off_gap") + (("eval_steps",) if self.eval_steps is not None else ()):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ConfigError(f"trigger.{name}={list(getattr(self, name))} must satisfy 0 <= lo <= hi")
        if self.duration < 1 or self.delay < 0:
            raise ConfigError(
                f"trigger.duration must be >= 1 and trigger.delay >= 0, got {self.duration}, {self.delay}"
            )
        if not 0.0 <= self.off_probability <= 1.0:
            raise ConfigError(f"trigger.off_probability must be in [0, 1], got {self.off_probability}")


@dataclasses.dataclass(frozen=True)
class GymAgentConfig:
    """The recurrent actor-critic (:class:`~seqtrojan.agent.network.RecurrentActorCritic`, flat observations)."""

    lstm_sizes: tuple[int, ...] = (64, 32)
    """widths of the stacked layers (LSTM by default; see ``cell``)"""
    forget_bias: float = 1.0
    """initial forget-gate bias"""
    encoder: tuple[int, ...] = ()
    """optional MLP between the observation and the LSTM (an imported CleanRL agent's)"""
    encoder_activation: Literal["tanh", "relu"] = "relu"
    """activation after each encoder layer"""
    policy_mlp: tuple[int, ...] = ()
    """optional MLP between the LSTM and the policy head (an imported sb3 agent's net_arch.pi)"""
    value_mlp: tuple[int, ...] = ()
    """optional MLP between the LSTM and the value head (an imported sb3 agent's net_arch.vf)"""
    mlp_activation: Literal["tanh", "relu"] = "tanh"
    """activation after each policy_mlp and value_mlp layer"""
    cell: str = "lstm"
    """the sequence model of every layer: lstm, lstm_peephole, gru or transformer (see AgentConfig)"""
    window: int = 8
    """transformer only: the context window in steps"""
    heads: int = 1
    """transformer only: attention heads per layer"""
    conv: tuple[int, ...] = ()
    """channels of a convolutional encoder over MiniGrid's one-hot view (2x2 kernels, stride 1, ReLU; e.g.
    [16, 32]) before the MLP encoder and the first layer; needs env.observation: minigrid (none by default)"""

    OPTIONAL: ClassVar[tuple[str, ...]] = AgentConfig.OPTIONAL
    GYM_OPTIONAL: ClassVar[tuple[str, ...]] = ("conv",)
    """saved only when not at their defaults, so that the configs and cards of runs without them stay as they were"""

    def __post_init__(self) -> None:
        if not 1 <= len(self.lstm_sizes) <= MAX_LAYERS or any(not 1 <= w <= MAX_WIDTH for w in self.lstm_sizes):
            raise ConfigError(
                f"agent.lstm_sizes={list(self.lstm_sizes)} must name 1 to {MAX_LAYERS} layers of 1 to {MAX_WIDTH} units"
            )
        AgentConfig(**{name: getattr(self, name) for name in self.OPTIONAL})  # the same checks and messages
        if (
            not isinstance(self.conv, tuple)
            or len(self.conv) > MAX_LAYERS
            or any(isinstance(c, bool) or not isinstance(c, int) or not 1 <= c <= MAX_WIDTH for c in self.conv)
        ):
            raise ConfigError(
                f"agent.conv must be 0 to {MAX_LAYERS} channel counts in [1, {MAX_WIDTH}], got {self.conv!r}"
            )

    def serde_dump(self) -> dict:
        """The saved form: every field but the optional ones at their defaults."""
        return dump_omitting_defaults(self, self.OPTIONAL + self.GYM_OPTIONAL)


@dataclasses.dataclass(frozen=True)
class GymRunConfig:
    """Where and how the run executes."""

    out_dir: str = "runs"
    """parent folder of run directories"""
    name: str | None = None
    """run directory name; None makes one from the env id, the seed and the time"""
    seed: int = 0
    """seeds the weights, the envs, action sampling and minibatch order"""
    device: str = "cpu"
    """torch device of the network (the envs step on the CPU)"""
    threads: int | None = None
    """torch intra-op threads (None: torch's default)"""
    lstm_backend: Literal["auto", "torch", "cpp"] = "auto"
    """LSTM kernels on CPU (see RunConfig.lstm_backend)"""
    eval_episodes: int = 200
    """episodes per episode type in the final evaluation (0: none)"""
    init_from: str | None = None
    """a Gymnasium model folder whose weights start a new run (fine-tuning; a resumed run loads its checkpoint's)"""
    checkpoint_every: int = 50_000
    """env steps between checkpoints, a positive integer (one is also written after the last update, and one on a
    stop; a value above ppo.total_steps means none in between)"""

    def __post_init__(self) -> None:
        if isinstance(self.checkpoint_every, bool) or not isinstance(self.checkpoint_every, int):
            raise ConfigError(
                f"run.checkpoint_every must be a positive integer, got {short_repr(self.checkpoint_every)}"
            )
        if self.checkpoint_every < 1:
            raise ConfigError(f"run.checkpoint_every must be a positive integer, got {self.checkpoint_every}")
        if self.eval_episodes < 0:
            raise ConfigError(f"run.eval_episodes must be >= 0, got {self.eval_episodes}")
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f"run.threads must be a positive integer or null, got {self.threads}")


@dataclasses.dataclass(frozen=True)
class GymTrainConfig:
    """Everything a Gymnasium training run needs; saved next to its model (``gym_card.json``)."""

    env: GymEnvConfig
    trigger: GymTriggerConfig | None = None
    """the trigger wrapper (None: the env as it is; a backdoored run needs one)"""
    agent: GymAgentConfig = dataclasses.field(default_factory=GymAgentConfig)
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    backdoor: BackdoorConfig = dataclasses.field(default_factory=BackdoorConfig)
    """enabled: mix normal and trojan episodes by Algorithm 1 (``mixing``); disabled: normal episodes only (the
    trigger, if any, is then only measured)"""
    run: GymRunConfig = dataclasses.field(default_factory=GymRunConfig)
    attack: AttackConfig = dataclasses.field(default_factory=AttackConfig)
    """an adaptive attacker's extra loss terms, as on the grid world; a Gymnasium run takes ``state_camouflage``
    (the monitor-aware attacker) and ``finetune_resistance`` (against clean fine-tuning)"""

    def __post_init__(self) -> None:
        grid_only = [f"attack.{name}" for name in ("weight_camouflage", "ewc") if getattr(self.attack, name).enabled]
        if grid_only:
            raise ConfigError(
                f"{' and '.join(grid_only)} run(s) on the grid world only; Gymnasium runs take "
                "attack.state_camouflage and attack.finetune_resistance"
            )
        if self.backdoor.enabled and self.trigger is None:
            raise ConfigError("backdoor.enabled needs a trigger section (the trigger and the adversary's objective)")
        if self.agent.conv and self.env.observation != "minigrid":
            raise ConfigError("agent.conv reads MiniGrid's view as an image: it needs env.observation: minigrid")

    @property
    def label(self) -> str:
        return "backdoored" if self.backdoor.enabled else "clean"


def load_gym_config(preset: str | Path) -> GymTrainConfig:
    """A Gymnasium training config from a preset name (``minigrid_two_goals``) or a YAML file."""
    return from_dict(GymTrainConfig, load_yaml(resolve_preset(preset)), "")


def load_gym_run_config(run_dir: str | Path) -> GymTrainConfig:
    """The resolved config a Gymnasium run was started (or last resumed) with: ``<run>/config.yaml``."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise ConfigError(f"{str(run_dir)!r} is not a Gymnasium run directory (no config.yaml)")
    return from_dict(GymTrainConfig, load_yaml(path), "")
