"""A Gymnasium env behind the batched-env seam (:class:`~seqtrojan.world.protocol.BatchedEnv`).

:func:`make_gym_env` builds one env of a :class:`~seqtrojan.world.config.GymnasiumEnvConfig`: ``gymnasium.make``
(a MiniGrid env with the fast view), the first N actions, MiniGrid's ``reached`` info, the trigger wrapper and the
flat float observation. :class:`GymnasiumBatchedEnv` steps ``num_envs`` of them and answers in the grid core's
terms (:class:`~seqtrojan.env.core.StepResult`: torch tensors of observations, rewards, ends, and per episode its
type, outcome, success and length), so that the trainer, the evaluation and every tool read one kind of result.

Two vectorisations (``env.vectorization``): ``sync`` steps every env in this process with a plain loop (no
``SyncVectorEnv`` info batching: several times less overhead per step; each env is wrapped in an
:class:`EpisodeRecorder`, so a checkpoint holds the episodes in flight and a resumed run continues bitwise);
``async`` runs Gymnasium's ``AsyncVectorEnv`` (a process per env, for envs whose own step is slow) and reads the
same facts from its infos. Both reset a finished env in the step that ends its episode, as the grid core does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

import seqtrojan.minigrid.objectives  # noqa: F401  (registers the MiniGrid objectives)
from seqtrojan.env.codes import FAILED, REACHED_ADV_GOAL, REACHED_USER_GOAL, RUNNING, TIMED_OUT
from seqtrojan.env.core import EnvState, StepResult
from seqtrojan.errors import CheckpointError, ConfigError, ShapeError
from seqtrojan.minigrid.fast_obs import use_fast_observation
from seqtrojan.serde import short_repr
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig
from seqtrojan.world.families import ensure_family, family_wrappers, make_family_env
from seqtrojan.wrappers import (
    BoxPatch,
    FirstActions,
    FlattenFloat,
    MiniGridOneHot,
    MiniGridPatch,
    TriggerWrapper,
    VectorPatch,
    finished_episodes,
    trigger_vector_env,
)
from seqtrojan.wrappers.goals import ReturnGoal
from seqtrojan.wrappers.objectives import TargetAction, configured_objective
from seqtrojan.wrappers.observations import CELL_BITS

MAX_OBS_DIM = 1 << 20
"""most inputs a Gymnasium env's flat observation may have (a bound checked before any buffer is allocated)"""
MAX_ACTIONS = 64
"""most discrete actions an agent may choose among (the model card's bound)"""
MAX_EPISODE_STEPS = 10_000
"""the episode loop's bound for an env with no time limit of its own"""
MAX_ENVS = 4096
"""most Gymnasium envs one batched env holds (each is a Python object, or a process with ``async``)"""

_OUTCOME_OF_REACHED = {"user": REACHED_USER_GOAL, "adversary": REACHED_ADV_GOAL}


def find_trigger(env: gym.Env) -> TriggerWrapper | None:
    """The TriggerWrapper in ``env``'s wrapper stack, if any."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, TriggerWrapper):
            return env
        env = env.env
    return None


def build_trigger(env: gym.Env, trigger: WrapperTriggerConfig, phase: str, trojan_probability: float) -> TriggerWrapper:
    """``env`` under the trigger ``trigger`` describes (``phase`` "eval" uses ``trigger.eval_steps``)."""
    objective = configured_objective(trigger.objective, trigger)
    if isinstance(objective, TargetAction):
        actions = getattr(env.action_space, "n", None)
        if actions is not None and objective.action >= int(actions):
            raise ConfigError(
                f"env.trigger.target_action={objective.action} is not one of the env's {int(actions)} actions"
            )
    on: MiniGridPatch | BoxPatch | VectorPatch
    off: MiniGridPatch | BoxPatch | VectorPatch
    if trigger.patch == "minigrid":
        on = MiniGridPatch(trigger.cells, trigger.object, trigger.color)
        off = MiniGridPatch(trigger.off_cells, trigger.object, trigger.color)
    elif trigger.patch == "vector":
        on = off = VectorPatch(trigger.indices, trigger.value)
    else:
        on = BoxPatch(trigger.cells, trigger.value, trigger.key)
        off = BoxPatch(trigger.off_cells, trigger.value, trigger.key)
    steps = trigger.eval_steps if phase == "eval" and trigger.eval_steps is not None else trigger.steps
    return TriggerWrapper(
        env, on, objective, trojan_probability=trojan_probability, trigger_steps=steps, duration=trigger.duration,
        delay=trigger.delay, off_patch=off if trigger.off_probability > 0 else None,
        off_probability=trigger.off_probability, off_gap=trigger.off_gap,
    )  # fmt: skip


def check_registered(env_id: str) -> None:
    """Refuse an id that is not registered with Gymnasium, or that would import a module (``module:Id``): what a
    model card names must never choose which installed module runs."""
    if ":" in env_id or env_id not in gym.registry:
        raise ConfigError(
            f"env.id={short_repr(env_id)} is not a registered Gymnasium id (a model's env must be one; "
            "module:Id imports are refused here)"
        )


def make_gym_env(
    config: GymnasiumEnvConfig, phase: str = "train", trojan_probability: float = 0.0, registered_only: bool = False
) -> gym.Env:
    """One env: ``gymnasium.make(env.id, **env.kwargs)`` (an Atari id under its family's preprocessing:
    :func:`~seqtrojan.world.families.make_atari`; a MiniGrid env with the fast view unless
    ``env.fast_view`` is false; only its first ``env.num_actions`` actions when set), MiniGrid's info
    (``reached``) for a MiniGrid env, the trigger wrapper (with a trigger section), then the flat float observation.
    ``registered_only`` (a config read from a model card) refuses an id that is not registered."""
    from minigrid.minigrid_env import MiniGridEnv

    from seqtrojan.minigrid.tasks import MiniGridInfo

    ensure_family(config.id)
    if registered_only:
        check_registered(config.id)
    try:
        env = make_family_env(config.id, config.kwargs, phase)
    except ConfigError:
        raise
    except (gym.error.Error, ModuleNotFoundError, ImportError) as err:
        raise ConfigError(f"env.id={config.id!r} cannot be made: {short_repr(str(err))}") from None
    except (TypeError, ValueError, AssertionError, MemoryError, RuntimeError) as err:  # ale-py: RuntimeError
        raise ConfigError(
            f"env {config.id!r} refused env.kwargs={short_repr(config.kwargs)}: {short_repr(str(err))}"
        ) from None
    env = family_wrappers(env, config.id)
    if config.fast_view:
        use_fast_observation(env)
    if config.num_actions is not None:
        env = FirstActions(env, config.num_actions)
    if isinstance(env.unwrapped, MiniGridEnv) and find_trigger(env) is None:
        env = MiniGridInfo(env)
    if config.user_return is not None:
        env = ReturnGoal(env, config.user_return)
    drawn_on_flat = config.trigger is not None and config.trigger.patch == "vector"
    if drawn_on_flat:  # a vector patch writes into the flat observation: flatten first
        env = _flat_observation(env, config)
    if config.trigger is not None:
        if find_trigger(env) is not None:
            raise ConfigError(
                f"env.id={config.id!r} already has a trigger wrapper; drop env.trigger or use the plain env's id"
            )
        env = build_trigger(env, config.trigger, phase, trojan_probability)
    elif (found := find_trigger(env)) is not None:
        found.set_trojan_probability(trojan_probability)
    return env if drawn_on_flat else _flat_observation(env, config)


def _flat_observation(env: gym.Env, config: GymnasiumEnvConfig) -> gym.Env:
    """``env`` under the observation wrapper ``config.observation`` names."""
    if config.observation == "minigrid":
        return MiniGridOneHot(env)
    if config.observation == "image":
        image_layout(env.observation_space, config.id)
    return FlattenFloat(env)


def image_layout(space: spaces.Space, env_id: str) -> tuple[int, int, int]:
    """(rows, cols, channels) of an (H, W, C) Box image observation; any other space is refused in one line."""
    if not isinstance(space, spaces.Box) or len(space.shape) != 3:
        raise ConfigError(
            f"env.id={env_id!r}: env.observation=image needs an (H, W, C) Box image, but the observation space "
            f"is {short_repr(space)} (use observation: flatten)"
        )
    rows, cols, channels = (int(d) for d in space.shape)
    return rows, cols, channels


def make_vector_env(
    config: GymnasiumEnvConfig, num_envs: int, phase: str = "train", trojan_probability: float = 0.0
) -> SyncVectorEnv:
    """``num_envs`` envs of ``config`` (:func:`make_gym_env`) in a SAME_STEP ``SyncVectorEnv``: Gymnasium's own
    vector form, for code that reads each episode's infos (the recorded evaluations of the analysis and monitors)."""
    return trigger_vector_env(lambda: make_gym_env(config, phase, trojan_probability), num_envs)


def check_spaces(env: gym.Env, env_id: str) -> tuple[int, int]:
    """(obs_dim, num_actions): the agents need a discrete action space and a flat, bounded observation."""
    if not isinstance(env.action_space, spaces.Discrete):
        raise ConfigError(
            f"env.id={env_id!r} has action space {short_repr(env.action_space)}; the recurrent agents need a "
            "discrete one (gymnasium.spaces.Discrete)"
        )
    space = env.observation_space
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        raise ConfigError(f"env.id={env_id!r}: the observation wrapper gave {short_repr(space)}, not a flat Box")
    obs_dim, actions = int(space.shape[0]), int(env.action_space.n)
    if not 1 <= obs_dim <= MAX_OBS_DIM or not 2 <= actions <= MAX_ACTIONS:
        raise ConfigError(
            f"env.id={env_id!r} gives {obs_dim} inputs and {actions} actions; seqtrojan takes 1 to {MAX_OBS_DIM} "
            f"inputs and 2 to {MAX_ACTIONS} actions"
        )
    return obs_dim, actions


def observation_image(config: GymnasiumEnvConfig, env: gym.Env, obs_dim: int) -> tuple[int, int, int] | None:
    """How ``env``'s flat observation is laid out as an image (for a conv encoder), or None."""
    if config.observation == "minigrid":
        return minigrid_image(obs_dim)
    if config.observation == "image":
        inner = env
        while isinstance(inner, gym.Wrapper) and not isinstance(inner, FlattenFloat):
            inner = inner.env
        assert isinstance(inner, FlattenFloat)  # _flat_observation put it there
        return image_layout(inner.env.observation_space, config.id)
    return None


def minigrid_image(obs_dim: int) -> tuple[int, int, int]:
    """The (rows, cols, channels) of a flat MiniGrid one-hot view (:class:`~seqtrojan.wrappers.MiniGridOneHot`)."""
    cells, rest = divmod(obs_dim, CELL_BITS)
    side = math.isqrt(cells)
    if rest or side * side != cells:
        raise ConfigError(f"{obs_dim} inputs are not a square MiniGrid view of {CELL_BITS} numbers per cell")
    return side, side, CELL_BITS


# ---------------------------------------------------------------------- episode records (exact resume)

_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "SFC64", "Philox")
"""numpy bit generators whose state is plain JSON (Gymnasium seeds envs with PCG64)"""


def _rng_state(rng: np.random.Generator | None) -> dict[str, Any] | None:
    """A generator's state as plain JSON (None when there is none, or its bit generator keeps arrays)."""
    if rng is None or type(rng.bit_generator).__name__ not in _BIT_GENERATORS:
        return None
    return dict(rng.bit_generator.state)


def _rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    name = state.get("bit_generator") if isinstance(state, dict) else None
    if name not in _BIT_GENERATORS:
        raise CheckpointError(f"episode record: bit_generator={short_repr(name)} is not one of {list(_BIT_GENERATORS)}")
    rng = np.random.Generator(getattr(np.random, name)())
    try:
        rng.bit_generator.state = state
    except (TypeError, ValueError, KeyError) as err:
        raise CheckpointError(f"episode record: a {name} state that numpy refuses ({err})") from None
    return rng


class EpisodeRecorder(gym.Wrapper):
    """Records, for the episode in flight, what replays it: the random state just before its reset (the env's
    ``np_random`` and the TriggerWrapper's generator, or the reset's seed) and every action since.

    :meth:`replay` restores that state, resets and takes the actions again: for an env whose randomness all comes
    from its ``np_random`` (Gymnasium's convention, MiniGrid's way) the env ends exactly where it was, which the
    trainer checks against the saved observation. Outermost in the stack, so the replayed observation is the
    policy's."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.trigger = find_trigger(env)
        self.start: dict[str, Any] | None = None
        """how the episode in flight began (None: it cannot be replayed, e.g. a reset with options)"""
        self.actions: list[int] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        p = None if self.trigger is None else self.trigger.trojan_probability
        start: dict[str, Any] | None = None  # a reset with options cannot be replayed
        if not options and seed is not None:
            start = {"seed": int(seed), "np_random": None, "trigger_rng": None, "trojan_probability": p}
        elif not options:
            np_random = _rng_state(getattr(self.env.unwrapped, "_np_random", None))
            trigger_rng = None if self.trigger is None else _rng_state(self.trigger.trigger_rng)
            replayable = np_random is not None and (self.trigger is None or trigger_rng is not None)
            start = {"seed": None, "np_random": np_random, "trigger_rng": trigger_rng, "trojan_probability": p}
            start = start if replayable else None
        obs, info = self.env.reset(seed=seed, options=options)
        self.start, self.actions = start, []
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        self.actions.append(int(action))
        return self.env.step(action)

    def record(self) -> dict[str, Any] | None:
        """The episode in flight as plain JSON (None when it cannot be replayed)."""
        return None if self.start is None else {"start": dict(self.start), "actions": list(self.actions)}

    def replay(self, record: dict[str, Any]) -> Any:
        """Restore the random state ``record`` holds, reset and take its actions; returns the last observation.
        Raises CheckpointError when the record is malformed or the replayed episode ends early."""
        try:
            start, actions = record["start"], [int(a) for a in record["actions"]]
            seed = start["seed"]
            if seed is None:
                self.env.unwrapped.np_random = _rng_from_state(start["np_random"])
                if self.trigger is not None:
                    self.trigger.trigger_rng = _rng_from_state(start["trigger_rng"])
            if self.trigger is not None:
                self.trigger.set_trojan_probability(float(start["trojan_probability"]))
        except (KeyError, TypeError, ValueError) as err:
            raise CheckpointError(f"episode record is malformed: {short_repr(err)}") from None
        obs, _ = self.reset(seed=seed)
        for t, action in enumerate(actions):
            obs, _, terminated, truncated, _ = self.step(action)
            if terminated or truncated:
                raise CheckpointError(f"the replayed episode ended at step {t + 1} of {len(actions)}")
        return obs


# ---------------------------------------------------------------------- the batched env


class GymnasiumBatchedEnv:
    """``num_envs`` envs of ``config`` stepped together, answering as the grid core does (torch tensors on
    ``device``; see the module docstring). One stage (index 0): a Gymnasium env has no curriculum."""

    num_stages = 1

    def __init__(
        self,
        config: GymnasiumEnvConfig,
        num_envs: int,
        seed: int = 0,
        device: torch.device | str = "cpu",
        *,
        phase: str = "train",
        trojan_probability: float = 0.0,
        registered_only: bool = False,
    ) -> None:
        check_num_envs(num_envs)
        self.config, self.num_envs, self.device = config, num_envs, torch.device(device)
        self.phase, self.registered_only = phase, registered_only
        probe = make_gym_env(config, phase, trojan_probability, registered_only)
        try:
            self.obs_dim, self.num_actions = check_spaces(probe, config.id)
        finally:
            probe.close()
        self.image = observation_image(config, probe, self.obs_dim)
        """(rows, cols, channels) of the observation as an image (a convolutional encoder reads it), or None"""
        self._async: AsyncVectorEnv | None = None
        self.envs: list[gym.Env] = []
        if config.vectorization == "async":
            self._async = AsyncVectorEnv(
                [self._factory(trojan_probability) for _ in range(num_envs)], autoreset_mode=AutoresetMode.SAME_STEP
            )
        else:
            self.envs = [EpisodeRecorder(self._factory(trojan_probability)()) for _ in range(num_envs)]
        self.triggers = [find_trigger(env) for env in self.envs]
        self.has_trigger = config.trigger is not None or any(t is not None for t in self.triggers)
        self.lengths = np.zeros(num_envs, dtype=np.int64)
        self._ended = np.zeros(num_envs, dtype=bool)  # without autoreset: the env's episode has ended (not stepped)
        self._trojan = np.zeros(num_envs, dtype=bool)  # the episode in flight is a trojan one (async: from infos)
        self._active = np.zeros(num_envs, dtype=bool)  # the adversary's objective judges the next action (async)
        self._last_rows: list[Any] = []
        self._limit: int | None = None
        self._obs = self.reset(seed)

    def _factory(self, trojan_probability: float):
        config, phase, registered_only = self.config, self.phase, self.registered_only

        def make() -> gym.Env:
            return make_gym_env(config, phase, trojan_probability, registered_only)

        return make

    # ------------------------------------------------------------------ the seam
    def reset(self, seed: int | Sequence[int] | None = None) -> torch.Tensor:
        """Start a fresh episode in every env (env ``i`` seeded ``seed + i``); returns the observations (B, obs_dim)."""
        seeds = self._seeds(seed)
        if self._async is not None:
            obs, infos = self._async.reset(seed=seeds)
            self._read_infos(infos, np.ones(self.num_envs, dtype=bool))
        else:
            rows = [env.reset(seed=s)[0] for env, s in zip(self.envs, seeds)]
            obs = self._stack(rows)
        self.lengths[:] = 0
        self._ended[:] = False
        self._obs = self._tensor(obs)
        return self._obs

    def observe(self) -> torch.Tensor:
        """The current observations (B, obs_dim) float32."""
        return self._obs

    def step(self, actions: torch.Tensor, autoreset: bool = True, check: bool = True) -> StepResult:
        """One action per env (B,) int64; a finished env starts its next episode in the same step, or (``autoreset``
        false: the episode loop's one episode per env) stays finished, no longer stepped, its results ignored."""
        acts = actions.detach().cpu().numpy()
        if check:
            check_actions(acts, self.num_envs, self.num_actions)
        if self._async is not None:
            if not autoreset:
                raise ConfigError("a batched Gymnasium env with vectorization: async always resets finished envs")
            return self._step_async(acts)
        b = self.num_envs
        rows: list[Any] = [None] * b
        reward, terminated, truncated = [0.0] * b, [False] * b, [False] * b
        success, trojan, active, outcome = [False] * b, [False] * b, [False] * b, [0] * b
        chosen = acts.astype(np.int64, copy=False).tolist()  # Python ints, as int(acts[i])
        ended = self._ended
        frozen = None if autoreset else ended.copy()  # the episodes that had ended before this step
        for i, (env, trigger, action) in enumerate(zip(self.envs, self.triggers, chosen, strict=True)):
            if ended[i]:  # no autoreset: a finished episode stays as it ended
                rows[i], terminated[i] = self._last_rows[i], True
                continue
            if trigger is not None:
                trojan[i], active[i] = trigger.trojan, trigger.adversary_active()
            obs, r, term, trunc, info = env.step(action)
            reward[i], terminated[i], truncated[i] = float(r), term, trunc
            if term or trunc:
                success[i] = info["success"] if "success" in info else bool(term) and float(r) > 0.0
                outcome[i] = _outcome(info, bool(trunc))
                if autoreset:
                    obs, _ = env.reset()
                else:
                    ended[i] = True
            rows[i] = obs
        if not autoreset:
            self._last_rows = rows
        return self._result(
            self._stack(rows), np.array(reward, dtype=np.float32), np.array(terminated, dtype=bool),
            np.array(truncated, dtype=bool), np.array(outcome, dtype=np.int64), np.array(success, dtype=bool),
            np.array(trojan, dtype=bool), np.array(active, dtype=bool), frozen,
        )  # fmt: skip

    # ------------------------------------------------------------------ the episode loop (one episode per env)
    @property
    def t(self) -> torch.Tensor:
        """(B,) int64: actions taken in each env's episode so far."""
        return torch.from_numpy(self.lengths.copy()).to(self.device)

    @property
    def trojan(self) -> torch.Tensor:
        """(B,) bool: each env's episode in progress is a trojan one."""
        flags = [t.trojan if t is not None else False for t in self.triggers] if self._async is None else self._trojan
        return torch.as_tensor(np.asarray(flags, dtype=bool)).to(self.device)

    @property
    def on_step(self) -> torch.Tensor:
        """(B,) int64: each env's ON trigger step in its episode in progress (-1: none; always -1 with async)."""
        steps = [t.trigger_step if t is not None else -1 for t in self.triggers] if self._async is None else []
        return torch.as_tensor(np.asarray(steps or [-1] * self.num_envs, dtype=np.int64)).to(self.device)

    @property
    def env_returns(self) -> torch.Tensor:
        """(B,) float32: each env's own rewards summed over its episode in progress, before a trigger's objective
        replaced them (NaN for an env without a trigger wrapper, and with ``async``)."""
        values = [t.env_return if t is not None else math.nan for t in self.triggers] if self._async is None else []
        return torch.as_tensor(np.asarray(values or [math.nan] * self.num_envs, dtype=np.float32)).to(self.device)

    @property
    def episode_limit(self) -> int:
        """The longest an episode can run: the env's time limit (its spec's, or MiniGrid's ``max_steps``)."""
        if self._limit is None:
            probe = make_gym_env(self.config, self.phase, 0.0, self.registered_only)
            try:
                spec = getattr(probe, "spec", None)
                limit = getattr(spec, "max_episode_steps", None) or getattr(probe.unwrapped, "max_steps", None)
                self._limit = int(limit) if limit else MAX_EPISODE_STEPS
            finally:
                probe.close()
        return self._limit

    def agent_cells(self) -> torch.Tensor:
        """(B, 2) zeros: a Gymnasium env's agent has no cell on the grid world's grid."""
        return torch.zeros((self.num_envs, 2), dtype=torch.int64, device=self.device)

    def _step_async(self, acts: np.ndarray) -> StepResult:
        assert self._async is not None
        trojan, active = self._trojan.copy(), self._active.copy()
        obs, reward, terminated, truncated, infos = self._async.step(acts)
        success, outcome = np.zeros(self.num_envs, dtype=bool), np.zeros(self.num_envs, dtype=np.int64)
        for ep in finished_episodes(infos, reward, terminated):
            success[ep.env] = ep.success
            outcome[ep.env] = _outcome(ep.info, bool(truncated[ep.env]))
        self._read_infos(infos, np.ones(self.num_envs, dtype=bool))
        obs = np.asarray(obs, dtype=np.float32)
        return self._result(obs, reward.astype(np.float32), terminated, truncated, outcome, success, trojan, active)

    def _result(
        self, obs: np.ndarray, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray,
        outcome: np.ndarray, success: np.ndarray, trojan: np.ndarray, active: np.ndarray,
        frozen: np.ndarray | None = None,
    ) -> StepResult:  # fmt: skip
        """The step's StepResult. ``frozen`` (no autoreset): the envs whose episode had ended before this step; their
        step count stays at their episode's length (the episode loop's per-env step ``t`` must not start again)."""
        done = terminated | truncated
        if frozen is None:
            self.lengths += 1
            length = self.lengths.copy()
            self.lengths[done] = 0  # the next episode starts at step 0
        else:
            self.lengths[~frozen] += 1
            length = self.lengths.copy()
        self._obs = self._tensor(obs)
        dev = self.device
        t = torch.from_numpy if dev.type == "cpu" else lambda x: torch.from_numpy(x).to(dev)
        return StepResult(
            self._obs, t(reward), t(terminated), t(truncated), t(done), t(np.where(done, outcome, RUNNING)),
            t(success & done), t(trojan), torch.zeros(self.num_envs, dtype=torch.int64, device=dev), t(length),
            t(active),
        )  # fmt: skip

    def _read_infos(self, infos: dict[str, Any], mask: np.ndarray) -> None:
        for key, target in (("trojan", self._trojan), ("adversary_active", self._active)):
            if key in infos:
                present = infos.get(f"_{key}", mask)
                target[present] = np.asarray(infos[key], dtype=bool)[present]

    def set_trojan_probability(self, probability: float | Sequence[float] | torch.Tensor) -> None:
        """The trojan-episode probability of every env's next episodes (a per-stage sequence: its one stage's)."""
        p = float(torch.as_tensor(probability, dtype=torch.float64).reshape(-1)[0])
        if self._async is not None:
            if self.has_trigger:
                self._async.call("set_trojan_probability", p)
            return
        for trigger in self.triggers:
            if trigger is not None:
                trigger.set_trojan_probability(p)

    def set_stage_weights(self, weights: Sequence[float] | torch.Tensor) -> None:
        """One stage: nothing to weigh."""

    def close(self) -> None:
        if self._async is not None:
            self._async.close()
        for env in self.envs:
            env.close()

    # ------------------------------------------------------------------ exact resume
    def save_state(self) -> EnvState | None:
        """Each env's episode in flight as a replay record (None with ``async``: its envs are not recorded)."""
        records = self.episode_records()
        return None if records is None else EnvState(records=list(records))

    def load_state(self, state: EnvState, obs: torch.Tensor) -> bool:
        """Replay :meth:`save_state`'s records (:meth:`restore_episodes`)."""
        return self.restore_episodes(state.records, obs)

    def episode_records(self) -> list[dict[str, Any] | None] | None:
        """Each env's episode in flight (:meth:`EpisodeRecorder.record`); None with ``async`` (not recorded)."""
        if self._async is not None:
            return None
        return [env.record() if isinstance(env, EpisodeRecorder) else None for env in self.envs]

    def restore_episodes(self, records: Any, obs: torch.Tensor) -> bool:
        """Replay every env's recorded episode; True when each gives back its saved observation in ``obs`` (then
        the envs are exactly where the checkpoint left them). False leaves the envs to be reset by the caller."""
        if self._async is not None or not isinstance(records, list) or len(records) != self.num_envs:
            return False
        replayed = []
        for env, record in zip(self.envs, records):
            if not isinstance(env, EpisodeRecorder) or not isinstance(record, dict):
                return False
            try:
                replayed.append(np.asarray(env.replay(record), dtype=np.float32))
            except CheckpointError:
                return False
        if tuple(obs.shape) != (self.num_envs, self.obs_dim) or not np.array_equal(np.stack(replayed), obs.numpy()):
            return False
        self._obs = obs.to(self.device)
        self.lengths[:] = [len(r["actions"]) for r in records]
        return True

    # ------------------------------------------------------------------ helpers
    def _seeds(self, seed: int | Sequence[int] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, int):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = [int(s) for s in seed]
        if len(seeds) != self.num_envs:
            raise ShapeError(f"reset needs {self.num_envs} seeds, got {len(seeds)}")
        return list(seeds)

    def _stack(self, rows: list[Any]) -> np.ndarray:
        out = np.empty((self.num_envs, self.obs_dim), dtype=np.float32)  # (B, obs_dim)
        for i, row in enumerate(rows):
            out[i] = row
        return out

    def _tensor(self, obs: np.ndarray) -> torch.Tensor:
        out = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))  # (B, obs_dim)
        return out if self.device.type == "cpu" else out.to(self.device)


def check_num_envs(num_envs: Any) -> None:
    """An integer in ``[1, MAX_ENVS]``; otherwise a one-line :class:`ConfigError` (before anything is allocated)."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or not 1 <= num_envs <= MAX_ENVS:
        raise ConfigError(f"num_envs must be an integer in [1, {MAX_ENVS}], got {short_repr(num_envs)}")


def check_actions(acts: np.ndarray, num_envs: int, num_actions: int) -> None:
    """One action per env, each in ``[0, num_actions)``; otherwise a one-line :class:`ShapeError`."""
    if acts.shape != (num_envs,) or acts.min() < 0 or acts.max() >= num_actions:
        raise ShapeError(f"actions must be ({num_envs},) integers in [0, {num_actions}), got shape {acts.shape}")


def _outcome(info: dict[str, Any], truncated: bool) -> int:
    """A finished episode's outcome code: the goal it reached (MiniGrid's ``reached``), a time-out, or failed."""
    reached = _OUTCOME_OF_REACHED.get(str(info.get("reached", "")))
    if reached is not None:
        return reached
    return TIMED_OUT if truncated else FAILED
