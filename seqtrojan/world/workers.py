"""A Gymnasium env's episodes stepped in a few worker processes (``env.vectorization: workers``).

A MiniGrid env steps in Python, one env after another: on a machine with more cores than the learner keeps busy,
that loop is the collection's bottleneck. :class:`WorkerBatchedEnv` splits the ``num_envs`` envs into
``env.workers`` contiguous slices, each a :class:`~seqtrojan.world.gymnasium.GymnasiumBatchedEnv` (sync) in its own
process, and steps the slices at the same time. Env ``i`` is seeded ``seed + i`` wherever its slice runs, and each
slice replays and records its episodes as the sync env does, so training with workers gives bitwise the results of
``sync`` (tested), and a checkpoint resumes exactly.

Unlike Gymnasium's ``AsyncVectorEnv`` (one process per env, several times slower per step than ``sync`` for an env
as cheap as MiniGrid's) a worker holds many envs: two workers on a 2-core machine. Workers are forked (as
Gymnasium's vector envs are on Linux), take a step's command over a pipe and write its observations and per-episode
facts into memory shared with the parent (each worker its rows, so nothing is pickled or joined), and exit when the
pipe closes, so they die with the process that made them.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import torch

from seqtrojan.env.core import EnvState, StepResult
from seqtrojan.errors import SeqTrojanError, ShapeError
from seqtrojan.world.config import GymnasiumEnvConfig
from seqtrojan.world.gymnasium import (
    GymnasiumBatchedEnv,
    check_actions,
    check_num_envs,
    check_spaces,
    make_gym_env,
)

_FLAGS = ("terminated", "truncated", "done", "outcome", "success", "trojan", "stage", "length", "adversary_active")
"""a step's per-episode facts other than obs and reward, kept as int64 rows of the shared ``facts`` array"""
_BOOLEAN = frozenset({"terminated", "truncated", "done", "success", "trojan", "adversary_active"})


@dataclass
class SharedStep:
    """What one step writes, in memory shared by the parent and its workers: each worker writes its rows."""

    obs: np.ndarray  # (B, obs_dim) float32
    reward: np.ndarray  # (B,) float32
    facts: np.ndarray  # (len(_FLAGS), B) int64

    @staticmethod
    def allocate(context: Any, num_envs: int, obs_dim: int) -> SharedStep:
        def shared(dtype: Any, shape: tuple[int, ...]) -> np.ndarray:
            size = int(np.prod(shape)) * np.dtype(dtype).itemsize
            return np.frombuffer(context.RawArray("b", size), dtype=dtype).reshape(shape)

        return SharedStep(
            shared(np.float32, (num_envs, obs_dim)), shared(np.float32, (num_envs,)),
            shared(np.int64, (len(_FLAGS), num_envs)),
        )  # fmt: skip


class WorkerError(SeqTrojanError):
    """A worker process failed or vanished; the message names the worker and its error."""


def _serve(
    conn: Connection, config: GymnasiumEnvConfig, rows: tuple[int, int], shared: SharedStep, options: dict[str, Any]
) -> None:
    """A worker's loop: build a sync batched env of the envs ``rows`` (start, stop), answer commands until the pipe
    closes; steps and resets write into ``shared``'s rows."""
    torch.set_num_threads(1)
    try:
        env = GymnasiumBatchedEnv(config, rows[1] - rows[0], **options)
        conn.send(("ok", (env.obs_dim, env.num_actions, env.image, env.has_trigger, env.episode_limit)))
    except Exception as err:  # reported to the parent in one line
        conn.send(("error", f"{type(err).__name__}: {err}"))
        return
    try:
        while True:
            try:
                command, args = conn.recv()
            except (EOFError, OSError):  # the parent is gone
                return
            try:
                conn.send(("ok", _answer(env, command, args, shared, slice(*rows))))
            except Exception as err:  # reported to the parent in one line
                conn.send(("error", f"{type(err).__name__}: {err}"))
            if command == "close":
                return
    finally:
        env.close()


def _answer(env: Any, command: str, args: tuple, shared: SharedStep, rows: slice) -> Any:
    """What the sync env in a worker answers to one command (plain values; a step or reset writes ``shared``)."""
    if command == "step":
        actions, autoreset = args
        result = env.step(torch.from_numpy(actions), autoreset=autoreset, check=False)
        shared.obs[rows] = result.obs.numpy()
        shared.reward[rows] = result.reward.numpy()
        for k, name in enumerate(_FLAGS):
            shared.facts[k, rows] = getattr(result, name).numpy()
        return None
    if command == "reset":
        shared.obs[rows] = env.reset(args[0]).numpy()
        return None
    if command == "flags":
        return env.t.numpy(), env.trojan.numpy(), env.on_step.numpy(), env.env_returns.numpy()
    if command == "set_trojan_probability":
        return env.set_trojan_probability(args[0])
    if command == "episode_records":
        return env.episode_records()
    if command == "restore_episodes":
        records, obs = args
        return env.restore_episodes(records, torch.from_numpy(obs))
    if command == "close":
        return None
    raise ValueError(f"unknown command {command!r}")


class WorkerBatchedEnv:
    """``num_envs`` envs of ``config`` in ``config.workers`` worker processes (see the module docstring); the
    same seam and answers as :class:`~seqtrojan.world.gymnasium.GymnasiumBatchedEnv` with ``sync``."""

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
        check_num_envs(num_envs)  # before the shared buffers are allocated
        workers = max(1, min(config.workers, num_envs))
        self.config, self.num_envs, self.device = config, num_envs, torch.device(device)
        self.bounds = [(num_envs * w // workers, num_envs * (w + 1) // workers) for w in range(workers)]
        """each worker's envs: a contiguous slice [start, stop) of the batch"""
        sync = dataclasses.replace(config, vectorization="sync")
        probe = make_gym_env(sync, phase, trojan_probability, registered_only)  # the spaces, before allocating
        try:
            obs_dim, _ = check_spaces(probe, config.id)
        finally:
            probe.close()
        context = multiprocessing.get_context("fork")
        self._shared = SharedStep.allocate(context, num_envs, obs_dim)
        self._conns: list[Connection] = []
        self._processes: list[Any] = []
        for start, stop in self.bounds:
            options = dict(seed=seed + start, phase=phase, trojan_probability=trojan_probability,
                           registered_only=registered_only)  # fmt: skip
            parent, child = context.Pipe()
            args = (child, sync, (start, stop), self._shared, options)
            process = context.Process(target=_serve, args=args, daemon=True)
            process.start()
            child.close()
            self._conns.append(parent)
            self._processes.append(process)
        try:
            facts = self._gather()
        except WorkerError:
            self.close()
            raise
        self.obs_dim, self.num_actions, self.image, self.has_trigger, self.episode_limit = facts[0]
        self._obs = self.reset(seed)

    # ------------------------------------------------------------------ talking to the workers
    def _send(self, command: str, per_worker: Sequence[tuple] | None = None) -> None:
        for w, conn in enumerate(self._conns):
            try:
                conn.send((command, per_worker[w] if per_worker is not None else ()))
            except (BrokenPipeError, OSError) as err:
                raise WorkerError(f"env worker {w} of {len(self._conns)} is gone ({err})") from None

    def _gather(self) -> list[Any]:
        answers = []
        for w, conn in enumerate(self._conns):
            try:
                status, value = conn.recv()
            except (EOFError, OSError):
                code = self._processes[w].exitcode
                raise WorkerError(f"env worker {w} of {len(self._conns)} died (exit code {code})") from None
            if status != "ok":
                raise WorkerError(f"env worker {w} of {len(self._conns)}: {value}")
            answers.append(value)
        return answers

    def _call(self, command: str, per_worker: Sequence[tuple] | None = None) -> list[Any]:
        self._send(command, per_worker)
        return self._gather()

    def _slices(self, array: np.ndarray) -> list[np.ndarray]:
        return [array[start:stop] for start, stop in self.bounds]

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        out = torch.from_numpy(array)
        return out if self.device.type == "cpu" else out.to(self.device)

    # ------------------------------------------------------------------ the seam
    def reset(self, seed: int | Sequence[int] | None = None) -> torch.Tensor:
        """Start a fresh episode in every env (env ``i`` seeded ``seed + i``); returns the observations (B, obs_dim)."""
        if seed is None:
            per_worker: list[tuple] = [(None,)] * len(self.bounds)
        elif isinstance(seed, int):
            per_worker = [(int(seed) + start,) for start, _ in self.bounds]
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != self.num_envs:
                raise ShapeError(f"reset needs {self.num_envs} seeds, got {len(seeds)}")
            per_worker = [(seeds[start:stop],) for start, stop in self.bounds]
        self._call("reset", per_worker)
        self._obs = self._tensor(self._shared.obs.copy())
        return self._obs

    def observe(self) -> torch.Tensor:
        """The current observations (B, obs_dim) float32."""
        return self._obs

    def step(self, actions: torch.Tensor, autoreset: bool = True, check: bool = True) -> StepResult:
        """As :meth:`GymnasiumBatchedEnv.step`, the slices stepped at the same time."""
        acts = actions.detach().cpu().numpy()
        if check:
            check_actions(acts, self.num_envs, self.num_actions)
        self._call("step", [(part, autoreset) for part in self._slices(acts)])
        shared = self._shared
        facts = {
            name: self._tensor(row.astype(bool) if name in _BOOLEAN else row.copy())
            for name, row in zip(_FLAGS, shared.facts, strict=True)
        }
        result = StepResult(obs=self._tensor(shared.obs.copy()), reward=self._tensor(shared.reward.copy()), **facts)
        self._obs = result.obs
        return result

    def _flags(self) -> list[np.ndarray]:
        return [np.concatenate(parts) for parts in zip(*self._call("flags"), strict=True)]

    @property
    def t(self) -> torch.Tensor:
        """(B,) int64: actions taken in each env's episode so far."""
        return self._tensor(self._flags()[0])

    @property
    def trojan(self) -> torch.Tensor:
        """(B,) bool: each env's episode in progress is a trojan one."""
        return self._tensor(self._flags()[1])

    @property
    def on_step(self) -> torch.Tensor:
        """(B,) int64: each env's ON trigger step in its episode in progress (-1: none)."""
        return self._tensor(self._flags()[2])

    @property
    def env_returns(self) -> torch.Tensor:
        """(B,) float32: each env's own rewards summed over its episode in progress (NaN without a trigger)."""
        return self._tensor(self._flags()[3])

    def agent_cells(self) -> torch.Tensor:
        """(B, 2) zeros: a Gymnasium env's agent has no cell on the grid world's grid."""
        return torch.zeros((self.num_envs, 2), dtype=torch.int64, device=self.device)

    def set_trojan_probability(self, probability: float | Sequence[float] | torch.Tensor) -> None:
        """The trojan-episode probability of every env's next episodes (a per-stage sequence: its one stage's)."""
        p = float(torch.as_tensor(probability, dtype=torch.float64).reshape(-1)[0])
        self._call("set_trojan_probability", [(p,)] * len(self.bounds))

    def set_stage_weights(self, weights: Sequence[float] | torch.Tensor) -> None:
        """One stage: nothing to weigh."""

    def close(self) -> None:
        """Stop the workers (each closes its envs); safe to call twice."""
        for conn in self._conns:
            try:
                conn.send(("close", ()))
                conn.recv()
            except (BrokenPipeError, EOFError, OSError):
                pass
            conn.close()
        for process in self._processes:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
                process.join()
        self._conns, self._processes = [], []

    # ------------------------------------------------------------------ exact resume
    def save_state(self) -> EnvState | None:
        """Each env's episode in flight as a replay record."""
        records = self.episode_records()
        return None if records is None else EnvState(records=list(records))

    def load_state(self, state: EnvState, obs: torch.Tensor) -> bool:
        """Replay :meth:`save_state`'s records in each worker; True when every env is back where it was."""
        return self.restore_episodes(state.records, obs)

    def episode_records(self) -> list[dict[str, Any] | None] | None:
        """Each env's episode in flight (:meth:`EpisodeRecorder.record`), in batch order."""
        parts = self._call("episode_records")
        if any(part is None for part in parts):
            return None
        return [record for part in parts for record in part]

    def restore_episodes(self, records: Any, obs: torch.Tensor) -> bool:
        """Replay every env's recorded episode (see :meth:`GymnasiumBatchedEnv.restore_episodes`)."""
        if not isinstance(records, list) or len(records) != self.num_envs or obs.shape[0] != self.num_envs:
            return False
        host = obs.detach().cpu().numpy()
        restored = self._call("restore_episodes", [(records[a:b], host[a:b]) for a, b in self.bounds])
        if not all(restored):
            return False
        self._obs = obs
        return True

    def __del__(self) -> None:
        if getattr(self, "_conns", None):
            self.close()
