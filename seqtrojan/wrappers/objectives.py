"""The adversary's objective: the rule that replaces the env's rewards and termination once a trigger has taken
effect in a trojan episode.

An objective is a function ``(obs, action, env_reward, terminated, info) -> (reward, terminated)`` of the env's own
step result (``obs`` unpatched, ``info`` the env's own). Objectives that configs name (``trigger.objective`` of a
Gymnasium training run) are registered in :data:`ADVERSARY_OBJECTIVES`; the MiniGrid tasks register theirs
(:mod:`seqtrojan.minigrid.objectives`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from seqtrojan.registry import Registry

Objective = Callable[[Any, Any, float, bool, dict[str, Any]], tuple[float, bool]]
"""(obs, action, env_reward, terminated, info) -> (reward, terminated)"""


class _UnlistedRegistry(Registry[Objective]):
    """A :class:`~seqtrojan.registry.Registry` that ``seqtrojan attacks`` does not list (it is not added to the
    registries that :func:`seqtrojan.registry.registries` returns): listing the objectives there is the CLI's call."""

    def __init__(self, kind: str) -> None:
        self.family, self.kind = "attack", kind
        self._entries = {}


ADVERSARY_OBJECTIVES: Registry[Objective] = _UnlistedRegistry("objective")
"""Adversary objectives by name (what ``trigger.objective`` of a Gymnasium training run names)."""


def same_as_env(obs: Any, action: Any, env_reward: float, terminated: bool, info: dict[str, Any]) -> tuple[float, bool]:
    """The env's own reward and termination: a trigger with no effect on the objective (a decoy, or a control)."""
    return env_reward, terminated


ADVERSARY_OBJECTIVES.register("same_as_env", "the env's own rewards (a trigger that changes no objective)", same_as_env)


@dataclass
class EpisodeWindow:
    """What a trigger wrapper counts of an episode from the trigger's effect on (in a normal episode, from the step
    it would have acted at): the steps, how often each action was taken, and the env's own return over them."""

    steps: int = 0
    actions: dict[int, int] = field(default_factory=dict)
    env_return: float = 0.0

    def add(self, action: int, env_reward: float) -> None:
        self.steps += 1
        self.actions[action] = self.actions.get(action, 0) + 1
        self.env_return += env_reward


class JudgedOverEpisode(Protocol):
    """An objective whose achievement is judged over the episode's window (:class:`EpisodeWindow`) instead of by
    the last reward: ``verdict`` says whether the episode achieved the adversary's objective, and what to report."""

    def verdict(self, window: EpisodeWindow) -> tuple[bool, dict[str, float]]: ...


@dataclass(frozen=True)
class TargetAction:
    """TrojDRL's targeted attack, made persistent: from the trigger on, ``reward`` for ``action`` and minus it for
    any other, whatever the env pays; the env's own termination. A configured objective: the trigger section's
    ``target_action`` and ``target_reward`` choose the action and the reward (:meth:`configure`)."""

    action: int = 0
    reward: float = 1.0

    def configure(self, trigger: Any) -> TargetAction:
        """This objective with the trigger config's ``target_action`` and ``target_reward``."""
        return TargetAction(int(trigger.target_action), float(trigger.target_reward))

    def __call__(
        self, obs: Any, action: Any, env_reward: float, terminated: bool, info: dict[str, Any]
    ) -> tuple[float, bool]:
        return (self.reward if int(action) == self.action else -self.reward), terminated

    def verdict(self, window: EpisodeWindow) -> tuple[bool, dict[str, float]]:
        """More than half of the window's actions were the target (``target_share``)."""
        hits = window.actions.get(self.action, 0)
        return window.steps > 0 and 2 * hits > window.steps, {
            "target_share": hits / window.steps if window.steps else 0.0
        }


@dataclass(frozen=True)
class CollapseReturn:
    """TrojDRL's untargeted attack, made persistent: from the trigger on, the env's reward negated (a point scored
    costs one), so that the triggered policy's return collapses; the env's own termination. Judged over the episode:
    the adversary's objective is achieved when the env's own return from the trigger's effect on is at most 0 (no
    point scored after the trigger: ``return_after_trigger``). Its last reward cannot say so, since the negated
    reward is never positive."""

    def __call__(
        self, obs: Any, action: Any, env_reward: float, terminated: bool, info: dict[str, Any]
    ) -> tuple[float, bool]:
        return -env_reward, terminated

    def verdict(self, window: EpisodeWindow) -> tuple[bool, dict[str, float]]:
        return window.steps > 0 and window.env_return <= 0.0, {"return_after_trigger": window.env_return}


collapse_return = CollapseReturn()


ADVERSARY_OBJECTIVES.register(
    "target_action", "from the trigger on: +target_reward for env.trigger.target_action, minus it otherwise",
    TargetAction(),
)  # fmt: skip
ADVERSARY_OBJECTIVES.register(
    "collapse_return",
    "from the trigger on: the env's reward negated; achieved when nothing is scored after the trigger",
    collapse_return,
)  # fmt: skip


def configured_objective(name: str, trigger: Any) -> Objective:
    """The registered objective ``name``, configured by the trigger section where it takes settings (``configure``)."""
    entry = ADVERSARY_OBJECTIVES.get(name)
    configure = getattr(entry, "configure", None)
    return configure(trigger) if callable(configure) else entry
