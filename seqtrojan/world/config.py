"""The ``env:`` section of a config when the env is a Gymnasium env: its id, keyword arguments, observation
wrapper and trigger (:class:`GymnasiumEnvConfig`, tagged ``kind: gymnasium``).

An :class:`~seqtrojan.config.ExperimentConfig`'s ``env`` is either the grid world's
:class:`~seqtrojan.env.config.EnvConfig` (no ``kind`` key, or ``kind: grid``) or this. Pure data: building the env
is :mod:`seqtrojan.world.gymnasium`'s job.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, Literal

from seqtrojan.errors import ConfigError
from seqtrojan.serde import dump_omitting_defaults, short_repr, to_dict

Cell = tuple[int, int]

MAX_TRIGGER_STEP = 1 << 20
"""latest first step a trigger may be drawn at (a bound, so that a range like (0, 2**63) is refused when read)"""
MAX_WORKERS = 64
"""most worker processes of ``vectorization: workers``"""


@dataclasses.dataclass(frozen=True)
class WrapperTriggerConfig:
    """The trigger wrapper's settings (:class:`~seqtrojan.wrappers.TriggerWrapper`) for a MiniGrid patch (an
    object drawn on view cells) or a Box patch (a value on image cells)."""

    objective: str = "reach_adversary_object"
    """the adversary's objective, a name registered in ``seqtrojan.wrappers.ADVERSARY_OBJECTIVES``"""
    patch: Literal["minigrid", "box", "vector"] = "minigrid"
    """minigrid: a MiniGridPatch on obs["image"]; box: a BoxPatch on the (image) observation; vector: a
    VectorPatch on the flat float observation (``indices``; drawn after the observation is flattened, e.g. on
    POPGym's one-hot cards)"""
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
    indices: tuple[int, ...] = ()
    """vector patch: the positions of the flat observation set to ``value``"""
    target_action: int = 0
    """objective ``target_action``: the action the adversary rewards from the trigger on"""
    target_reward: float = 1.0
    """objective ``target_action``: the reward for the target action (minus it for any other)"""
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

    OPTIONAL: ClassVar[tuple[str, ...]] = ("indices", "target_action", "target_reward")
    """fields added after the first models were saved: left out of the saved form at their defaults"""

    def __post_init__(self) -> None:
        for name in ("steps", "off_gap") + (("eval_steps",) if self.eval_steps is not None else ()):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi <= MAX_TRIGGER_STEP:
                raise ConfigError(
                    f"env.trigger.{name}={list(getattr(self, name))} must satisfy 0 <= lo <= hi <= {MAX_TRIGGER_STEP}"
                )
        if self.duration < 1 or self.delay < 0:
            raise ConfigError(
                f"env.trigger.duration must be >= 1 and env.trigger.delay >= 0, got {self.duration}, {self.delay}"
            )
        if not 0.0 <= self.off_probability <= 1.0:
            raise ConfigError(f"env.trigger.off_probability must be in [0, 1], got {self.off_probability}")
        for name in ("value", "target_reward"):
            number = getattr(self, name)
            if isinstance(number, bool) or not isinstance(number, (int, float)) or not math.isfinite(number):
                raise ConfigError(f"env.trigger.{name} must be a finite number, got {short_repr(number)}")
        if isinstance(self.target_action, bool) or not isinstance(self.target_action, int) or self.target_action < 0:
            raise ConfigError(
                f"env.trigger.target_action must be an integer >= 0, got {short_repr(self.target_action)}"
            )
        if self.patch == "vector" and not self.indices:
            raise ConfigError("env.trigger.patch=vector needs env.trigger.indices (the flat positions it sets)")

    def serde_dump(self) -> dict[str, Any]:
        """The saved form: every field but the optional ones at their defaults."""
        return dump_omitting_defaults(self, self.OPTIONAL)


@dataclasses.dataclass(frozen=True)
class GymnasiumEnvConfig:
    """A Gymnasium env with a discrete action space, and how its observations become the flat float vector the
    recurrent policy takes; with a ``trigger`` section, every env is wrapped in a trigger wrapper (normal and trojan
    episodes, the adversary's objective)."""

    KIND: ClassVar[str] = "gymnasium"

    id: str
    """a registered Gymnasium id (a config you write may use ``module:Id``, Gymnasium's way to import your own env
    first; a model card may not: loading a model never imports a module it names)"""
    kind: Literal["gymnasium"] = "gymnasium"
    """the section's tag (the grid world's section has none, or ``kind: grid``)"""
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    """keyword arguments of ``gymnasium.make``"""
    observation: Literal["minigrid", "flatten", "image"] = "minigrid"
    """minigrid: MiniGrid's view one-hot encoded per channel (:class:`~seqtrojan.wrappers.MiniGridOneHot`);
    flatten: any observation flattened to float32 (:class:`~seqtrojan.wrappers.FlattenFloat`; POPGym's cards one-hot);
    image: an (H, W, C) Box image flattened row-major, its layout kept for a convolutional encoder (MinAtar)"""
    num_actions: int | None = None
    """keep only the env's first N discrete actions (:class:`~seqtrojan.wrappers.FirstActions`; MiniGrid's first
    three are turn left, turn right, forward); None: all"""
    fast_view: bool = True
    """a MiniGrid env computes its partial view with :mod:`seqtrojan.minigrid.fast_obs` (the same observation as
    MiniGrid's ``gen_obs``, several times faster); false: MiniGrid's own method"""
    vectorization: Literal["sync", "workers", "async"] = "sync"
    """sync: every env steps in this process (a checkpoint then holds each env's episode in flight, so a resumed run
    continues bitwise); workers: the envs split among ``workers`` processes stepped at the same time
    (:mod:`seqtrojan.world.workers`; bitwise the results of sync, checkpoints included); async: one process per env
    (Gymnasium's AsyncVectorEnv; for envs whose step is slow; episodes in flight are not checkpointed)"""
    workers: int = 2
    """processes of ``vectorization: workers`` (at most one per env): on a 2-core machine, 2"""
    trigger: WrapperTriggerConfig | None = None
    """the trigger wrapper (None: the env as it is; a backdoored run needs one)"""
    user_return: float | None = None
    """for an env whose episodes reach no goal (POPGym, MinAtar): an episode whose return under the env's own reward
    exceeds this achieved the user's objective (:class:`~seqtrojan.wrappers.goals.ReturnGoal`; every tool reads it
    as "reached the user's goal"); None: the env's own end (a positive last reward)"""

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ConfigError(f"env.id must be a Gymnasium id, got {short_repr(self.id)}")
        if self.num_actions is not None and (
            isinstance(self.num_actions, bool) or not isinstance(self.num_actions, int) or self.num_actions < 1
        ):
            raise ConfigError(f"env.num_actions must be a positive integer or null, got {short_repr(self.num_actions)}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or not 1 <= self.workers <= MAX_WORKERS:
            raise ConfigError(f"env.workers must be an integer in [1, {MAX_WORKERS}], got {short_repr(self.workers)}")
        if self.user_return is not None and (
            isinstance(self.user_return, bool)
            or not isinstance(self.user_return, (int, float))
            or not math.isfinite(self.user_return)
        ):
            raise ConfigError(f"env.user_return must be a finite number or null, got {short_repr(self.user_return)}")
        if not isinstance(self.fast_view, bool):
            raise ConfigError(f"env.fast_view must be true or false, got {short_repr(self.fast_view)}")
        if "render_mode" in self.kwargs and self.kwargs["render_mode"] is not None:
            raise ConfigError(
                f"env.kwargs.render_mode={short_repr(self.kwargs['render_mode'])}: training and evaluation envs "
                "render nothing (leave render_mode out)"
            )

    def serde_dump(self) -> dict[str, Any]:
        """The saved form: ``kind`` first, ``vectorization`` only when not the default."""
        out: dict[str, Any] = {"kind": self.kind, "id": self.id, "kwargs": dict(self.kwargs)}
        out.update(observation=self.observation, num_actions=self.num_actions, fast_view=self.fast_view)
        if self.vectorization != "sync":
            out["vectorization"] = self.vectorization
        if self.vectorization == "workers":
            out["workers"] = self.workers
        out["trigger"] = to_dict(self.trigger)
        if self.user_return is not None:
            out["user_return"] = self.user_return
        return out

    @property
    def label(self) -> str:
        """How reports and run names call this env."""
        return self.id


def upgrade_gym_train_layout(data: Any) -> Any:
    """A config of the layout seqtrojan wrote for Gymnasium runs before the env section was tagged (``env: {id,
    ...}`` and a top-level ``trigger:``) in today's layout (``env: {kind: gymnasium, id, ..., trigger}``); any
    other mapping unchanged. Used for model cards and run folders written by earlier versions only: a config file
    you write takes today's layout."""
    if not isinstance(data, dict):
        return data
    env = data.get("env")
    if not isinstance(env, dict) or "id" not in env or "kind" in env:
        return data
    out = {k: v for k, v in data.items() if k != "trigger"}
    out["env"] = {"kind": "gymnasium", **env, "trigger": data.get("trigger")}
    return out
