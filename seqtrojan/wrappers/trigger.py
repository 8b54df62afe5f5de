"""A Gymnasium wrapper that turns any env into normal and trojan episodes (the paper's Env_C and Env_T).

Each episode is a trojan episode with probability ``trojan_probability`` (settable between episodes, which is how
Algorithm 1 drives it; ``reset(options={"trojan": True})`` forces one). In a trojan episode the trigger is drawn
into observations ``t = s .. s + duration - 1`` (or one frame of a sequence per step), for a first step ``s`` drawn
from ``trigger_steps`` (observation ``t`` is the one returned after ``t`` actions; 0 is reset's). The adversary's
objective judges action ``t`` (taken on observation ``t``) iff the latest trigger whose effect time is ``<= t`` is
the ON trigger, where the effect time is the trigger's first step (a sequence's last frame's) plus ``delay``; an
OFF trigger, shown ``off_gap`` steps after the ON trigger in a share ``off_probability`` of trojan episodes, takes
effect ``delay`` steps after its first step and switches back to the env's own objective. The same semantics as the
built-in grid world (:mod:`seqtrojan.env.core`).

Info (reset and step): ``t``, ``trojan``, ``trigger_step`` (-1 in a normal episode), ``off_step`` (-1 when none),
``trigger_visible`` (the observation shows the ON or OFF trigger) and ``adversary_active`` (the adversary's
objective judges the next action); step adds ``adversary_judged`` (it judged this action) and, at the episode's end,
``success``: the episode ended by termination (not truncation) with a positive last reward under the objective in
force, i.e. it achieved its correct objective.

An objective with a ``verdict`` (:class:`~seqtrojan.wrappers.objectives.JudgedOverEpisode`) is judged over the
episode instead of by its last reward: the steps from the trigger's effect on (in a normal episode, from the step
the trigger would have been drawn at) are counted (:class:`~seqtrojan.wrappers.objectives.EpisodeWindow`: actions
and the env's own return), and when the verdict says achieved the episode's end says ``reached: "adversary"`` (the
grid world's "ended at the adversary's goal": the evaluation's outcome, its persistence, the monitors and
mitigations read it) and, in a trojan episode, ``success``. A target action is achieved when more than half of the
window's actions were the target (``target_share`` at the episode's end), the collapsed return when nothing was
scored in the window (``return_after_trigger``). A normal episode's ``success`` is an inner wrapper's verdict where
one gives it (:class:`~seqtrojan.wrappers.goals.ReturnGoal`: the return beyond a threshold).
"""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.serde import short_repr
from seqtrojan.wrappers.objectives import EpisodeWindow, Objective
from seqtrojan.wrappers.patches import BoxPatch, MiniGridPatch, Patch, VectorPatch, as_frames

_OPTIONS = ("trojan", "trigger_step", "off_step")
"""reset options the wrapper reads (the rest go to the wrapped env)"""


def _step_range(value: Any, what: str, minimum: int = 0) -> tuple[int, int]:
    """``[lo, hi]``: a list or tuple of two integers (a string such as "12" or a float is refused, never read as
    digits or truncated)."""
    integers = isinstance(value, (list, tuple)) and len(value) == 2
    if not integers or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in value):
        raise ConfigError(f"{what} must be an inclusive range [lo, hi] of integer steps, got {short_repr(value)}")
    lo, hi = (int(v) for v in value)
    if not minimum <= lo <= hi:
        raise ConfigError(f"{what}={short_repr(value)} must satisfy {minimum} <= lo <= hi")
    return lo, hi


def _probability(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not 0.0 <= value <= 1.0:
        raise ConfigError(f"{what} must be a number in [0, 1], got {short_repr(value)}")
    return float(value)


def _count(value: Any, what: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{what} must be an integer >= {minimum}, got {short_repr(value)}")
    return int(value)


class TriggerWrapper(gym.Wrapper):
    """Normal and trojan episodes over any Gymnasium env (see the module docstring).

    Args:
        env: the env to wrap (any observation and action space).
        patch: what the trigger draws: a :class:`~seqtrojan.wrappers.BoxPatch`, a
            :class:`~seqtrojan.wrappers.MiniGridPatch`, a function ``(obs, frame) -> obs``, or a sequence of these
            (one frame per step; then ``duration`` must be 1).
        objective: the adversary's rule ``(obs, action, env_reward, terminated, info) -> (reward, terminated)``;
            None keeps the env's own (a trigger without effect).
        trojan_probability: chance that an episode is a trojan one (``set_trojan_probability`` changes it).
        trigger_steps: inclusive range of the trigger's first step.
        duration: steps a single patch stays visible (its frame index counts up).
        delay: activation delay: the objective switches ``delay`` steps after the trigger takes effect.
        off_patch: the OFF trigger's patch (or frames), or None for none.
        off_probability: chance that a trojan episode also shows the OFF trigger.
        off_gap: inclusive range of steps from the ON trigger's first step to the OFF trigger's.
        off_duration: steps the OFF patch stays visible.
    """

    def __init__(
        self,
        env: gym.Env,
        patch: Any,
        objective: Objective | None = None,
        *,
        trojan_probability: float = 0.5,
        trigger_steps: tuple[int, int] = (1, 1),
        duration: int = 1,
        delay: int = 0,
        off_patch: Any = None,
        off_probability: float = 0.0,
        off_gap: tuple[int, int] = (3, 8),
        off_duration: int = 1,
    ) -> None:
        super().__init__(env)
        self.frames: tuple[Patch, ...] = as_frames(patch, "patch")
        self.duration = _count(duration, "duration", 1)
        if len(self.frames) > 1 and self.duration != 1:
            raise ConfigError(
                f"duration={duration} with a sequence of {len(self.frames)} frames: each frame shows one step, so "
                "duration must be 1 (repeat a frame to show it longer)"
            )
        if objective is not None and not callable(objective):
            raise ConfigError(f"objective must be a function (obs, action, reward, terminated, info) -> "
                              f"(reward, terminated), got {short_repr(objective)}")  # fmt: skip
        self.objective = objective
        self.trigger_steps = _step_range(trigger_steps, "trigger_steps")
        self.delay = _count(delay, "delay", 0)
        self.off_frames: tuple[Patch, ...] = () if off_patch is None else as_frames(off_patch, "off_patch")
        self.off_probability = _probability(off_probability, "off_probability")
        if self.off_probability > 0 and not self.off_frames:
            raise ConfigError(f"off_probability={off_probability} but no off_patch is given")
        self.off_duration = _count(off_duration, "off_duration", 1)
        self.off_gap = _step_range(off_gap, "off_gap", minimum=len(self.frames))  # OFF takes effect after ON
        for frame in (*self.frames, *self.off_frames):
            frame.check(env.observation_space)
        self._p = _probability(trojan_probability, "trojan_probability")
        self._rng: np.random.Generator | None = None
        self._t = 0
        self._trojan = False
        self._on = -1
        self._off = -1
        self._env_return = 0.0
        self._window = -1  # first step of the episode's judged window (the trigger's effect, or where it would be)
        self._counted = EpisodeWindow()

    # ------------------------------------------------------------------ the mixture
    @property
    def trojan_probability(self) -> float:
        """Chance that a new episode is a trojan one (``vector_env.set_attr("trojan_probability", p)`` sets it)."""
        return self._p

    @trojan_probability.setter
    def trojan_probability(self, value: float) -> None:
        self._p = _probability(value, "trojan_probability")

    def set_trojan_probability(self, value: float) -> None:
        """Set the chance that a new episode is a trojan one (from the next reset on)."""
        self.trojan_probability = value

    @property
    def shown_steps(self) -> int:
        """Steps the ON trigger is visible: a sequence's length, else ``duration``."""
        return len(self.frames) if len(self.frames) > 1 else self.duration

    @property
    def effect_offset(self) -> int:
        """Steps from the ON trigger's first step to its effect: ``delay`` plus a sequence's length - 1."""
        return len(self.frames) - 1 + self.delay

    @property
    def trigger_step(self) -> int:
        """The ON trigger's first step in the episode in progress (-1 in a normal episode)."""
        return self._on

    @property
    def trojan(self) -> bool:
        """Whether the episode in progress is a trojan one."""
        return self._trojan

    @property
    def env_return(self) -> float:
        """The env's own rewards summed over the episode in progress (before the adversary's objective replaces
        them): what a user of the env got, trojan episode or not."""
        return self._env_return

    def adversary_active(self, t: int | None = None) -> bool:
        """Whether the adversary's objective judges action ``t`` (default: the next one)."""
        t = self._t if t is None else t
        on = self._on >= 0 and t >= self._on + self.effect_offset
        off = self._off >= 0 and t >= self._off + self.delay
        return on and not off

    @property
    def trigger_rng(self) -> np.random.Generator | None:
        """The generator of the trigger's own draws (trojan or not, trigger step, OFF trigger); None before the first
        reset. Settable, like Gymnasium's ``np_random``, so that a checkpointed episode can be replayed exactly."""
        return self._rng

    @trigger_rng.setter
    def trigger_rng(self, rng: np.random.Generator) -> None:
        self._rng = rng

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        options = dict(options or {})
        ours = {k: options.pop(k) for k in _OPTIONS if k in options}
        obs, info = self.env.reset(seed=seed, options=options or None)
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(None if seed is None else [int(seed), 0x7419_6E])
        self._draw_episode(ours)
        self._t = 0
        self._env_return = 0.0
        return self._draw(obs), self._info(info)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        judged = self._on >= 0 and self.adversary_active(self._t)  # a normal episode: never judged
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._env_return += float(reward)
        judge = getattr(self.objective, "verdict", None)  # an objective judged over the episode's window
        if judge is not None and self._t >= self._window:
            self._counted.add(int(action), float(reward))
        if judged and self.objective is not None:
            result = self.objective(obs, action, float(reward), bool(terminated), info)
            if not (isinstance(result, tuple) and len(result) == 2):
                raise ConfigError(
                    f"the adversary's objective must return (reward, terminated), got {short_repr(result)}"
                )
            reward, terminated = float(result[0]), bool(result[1])
        self._t += 1
        out = self._info(info)
        out["adversary_judged"] = judged
        if terminated or truncated:
            own = info.get("success") if not judged else None  # an inner goal's verdict (ReturnGoal), if any
            out["success"] = bool(own) if own is not None else bool(terminated) and float(reward) > 0.0
            if judge is not None:
                achieved, figures = judge(self._counted)
                out.update(figures)
                if achieved:
                    out["reached"] = "adversary"  # the adversary's behaviour, whatever else the episode achieved
                if self._trojan:
                    out["success"] = achieved
        return self._draw(obs), reward, terminated, truncated, out

    # ------------------------------------------------------------------ internals
    def _draw_episode(self, forced: dict[str, Any]) -> None:
        """Draw this episode's type and trigger steps (every draw is made, forced or not, so that a forced episode
        leaves the random stream where an unforced one would)."""
        rng = self._rng
        assert rng is not None  # reset() makes it
        trojan = bool(rng.random() < self._p)
        on = int(rng.integers(self.trigger_steps[0], self.trigger_steps[1] + 1))
        has_off = bool(rng.random() < self.off_probability)
        gap = int(rng.integers(self.off_gap[0], self.off_gap[1] + 1))
        if "trojan" in forced:
            if not isinstance(forced["trojan"], (bool, np.bool_)):
                raise ConfigError(f"reset option 'trojan' must be true or false, got {short_repr(forced['trojan'])}")
            trojan = bool(forced["trojan"])
        if "trigger_step" in forced:
            if not trojan:
                raise ConfigError("reset option 'trigger_step' is given for a normal episode (trojan=False)")
            on = _count(forced["trigger_step"], "reset option 'trigger_step'", 0)
        if "off_step" in forced:
            value = forced["off_step"]
            if value is None:
                has_off = False
            else:
                value = _count(value, "reset option 'off_step'", 0)
                if not trojan or value < on + len(self.frames) or not self.off_frames:
                    raise ConfigError(
                        f"reset option 'off_step'={value} needs a trojan episode, an off_patch and a step after the "
                        f"ON trigger's last frame (trigger_step={on})"
                    )
                has_off, gap = True, value - on
        self._trojan = trojan
        self._window = on + self.effect_offset  # a normal episode counts from where the trigger would have acted
        self._counted = EpisodeWindow()
        self._on = on if trojan else -1
        self._off = on + gap if trojan and has_off and self.off_frames else -1

    def _visible(self, start: int, frames: tuple[Patch, ...], duration: int) -> tuple[Patch, int] | None:
        """The frame (and its index) drawn on observation ``self._t`` by a trigger first shown at ``start``."""
        if start < 0:
            return None
        k = self._t - start
        shown = len(frames) if len(frames) > 1 else duration
        if not 0 <= k < shown:
            return None
        return (frames[k], k) if len(frames) > 1 else (frames[0], k)

    def _draw(self, obs: Any) -> Any:
        if self._on < 0 and self._off < 0:  # a normal episode: nothing to draw
            return obs
        for visible in (self._visible(self._on, self.frames, self.duration),
                        self._visible(self._off, self.off_frames, self.off_duration)):  # fmt: skip
            if visible is None:
                continue
            patch, frame = visible
            drawn = patch(obs, frame)
            checked = isinstance(patch, (BoxPatch, MiniGridPatch, VectorPatch))  # checked once, when built
            if not checked and not self.observation_space.contains(drawn):
                raise ShapeError(
                    f"the trigger's patch {type(patch).__name__} returned an observation outside the observation "
                    f"space ({_describe(drawn)}; expected {self.observation_space})"
                )
            obs = drawn
        return obs

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        on, off = self._on, self._off
        out = dict(info)
        out["t"] = self._t
        out["trojan"] = self._trojan
        out["trigger_step"] = on
        out["off_step"] = off
        out["trigger_visible"] = (on >= 0 or off >= 0) and (
            self._visible(on, self.frames, self.duration) is not None
            or self._visible(off, self.off_frames, self.off_duration) is not None
        )
        out["adversary_active"] = on >= 0 and self.adversary_active()
        return out


def _describe(obs: Any) -> str:
    if isinstance(obs, dict):
        return "{" + ", ".join(f"{k!r}: {_describe(v)}" for k, v in obs.items()) + "}"
    if isinstance(obs, np.ndarray):
        return f"shape {obs.shape}, dtype {obs.dtype}"
    return type(obs).__name__
