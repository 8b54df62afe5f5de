"""The one training loop: recurrent PPO over any batched env (the grid world, or a Gymnasium env behind the seam
:mod:`seqtrojan.world`), with the curriculum (the grid world's hook), Algorithm 1 mixing, the attack's penalties,
logging and checkpoints.

    result = train(config)                       # a new run under config.run.out_dir
    result = train(config, resume="runs/<id>")   # continue a stopped run from its latest checkpoint

:func:`train` sets up a :class:`TrainerState` (what a checkpoint holds), runs the loop (:func:`_train_one_update`:
COLLECT ROLLOUT, COMPUTE ADVANTAGES, UPDATE, CURRICULUM; then LOG, CHECKPOINT) and finishes. A stop
(Ctrl-C, SIGTERM) writes a checkpoint first; ``resume`` restores weights, optimizer, counters, curriculum and
random-generator state, and the episodes in flight (the env's ``save_state``: the grid world's episode tensors, or
each Gymnasium env's replay record) with what the rollout collector carries, so the resumed run is bitwise the
uninterrupted one. Where the env cannot restore them (Gymnasium's ``async`` vectorisation, an env with randomness
outside its ``np_random``, a checkpoint written before episodes were kept) the run starts fresh episodes, seeded
from the update count (the ones in flight at the stop are dropped; every finished update is kept).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import errno
import json
import math
import re
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml
from safetensors.torch import save_file

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.card import Architecture, inherited_label
from seqtrojan.agent.checkpoint import (
    build_agent,
    card_config,
    load_agent,
    load_start_weights,
    read_safetensors,
    save_agent,
)
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.core import EnvState
from seqtrojan.errors import CheckpointError, ConfigError, SeqTrojanError
from seqtrojan.evaluation.batched import evaluate_on_env
from seqtrojan.folders import LOCK_FILE, folder_lock, make_output_folder
from seqtrojan.serde import from_dict, load_yaml, short_repr, to_dict
from seqtrojan.train.curriculum import Curriculum, EpisodeCounts
from seqtrojan.train.gae import compute_gae
from seqtrojan.train.logger import RunLogger, make_progress
from seqtrojan.train.mixing import MIXING_RULES, TrojanMixer
from seqtrojan.train.penalties import (
    Penalty,
    PenaltyContext,
    build_penalties,
    penalty_tensors,
    restore_penalties,
)
from seqtrojan.train.ppo import make_optimizer, ppo_update
from seqtrojan.train.rollout import EpisodeStats, RolloutCollector
from seqtrojan.train.stopping import StopRule
from seqtrojan.world import env_spec, make_batched_env
from seqtrojan.world.config import upgrade_gym_train_layout
from seqtrojan.world.protocol import BatchedEnv

UpdateCallback = Callable[[dict[str, Any]], bool]
"""Called after every update with the logged scalars; returning True stops training (used by benchmarks)."""


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    model_dir: Path
    env_steps: int
    wall_seconds: float
    stage: int
    evaluation: dict[str, Any]
    exact_resume: bool | None = None
    """whether a resume continued the episodes in flight (the run is then bitwise the uninterrupted one); False:
    fresh episodes; None: not resumed"""


@dataclass
class TrainerState:
    """Everything a checkpoint saves and a resume restores: the agent, the optimizer, the curriculum, the backdoor
    mixer, the rollout collector (its random generator), the update generator (minibatch order), the attack's
    penalties (their running statistics and reference weights) and the counters."""

    agent: RecurrentActorCritic
    optimizer: torch.optim.Optimizer
    curriculum: Curriculum
    mixer: TrojanMixer
    collector: RolloutCollector
    update_generator: torch.Generator
    penalties: list[Penalty] = field(default_factory=list)
    """the attack's extra loss terms (``config.attack``; none in a clean training)"""
    global_step: int = 0
    """env steps trained"""
    update: int = 0
    """PPO updates done"""
    elapsed_s: float = 0.0
    """wall seconds trained, over every process that trained this run"""
    label: str = "clean"
    """the label of every model the run saves (:func:`~seqtrojan.agent.card.inherited_label`; a resumed run keeps
    its checkpoint's)"""


class _Stop(Exception):
    pass


def train(
    config: ExperimentConfig, resume: str | Path | None = None, callback: UpdateCallback | None = None
) -> TrainResult:
    """Train a clean agent, or a backdoored one (``config.backdoor.enabled``); see the module docstring."""
    cfg = config
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)
    device = _device(cfg)
    MIXING_RULES.get(cfg.backdoor.mixing)  # an unknown rule is refused before the run folder exists
    spec = env_spec(cfg.env)  # and so is an env that cannot be made or whose spaces no agent takes (made once)
    cfg.ppo.check_rollout_memory(spec.obs_dim)  # and a rollout buffer larger than memory
    run_dir = _resumed_run_dir(resume) if resume is not None else _new_run_dir(cfg)
    env, state = _set_up(cfg, device, resume is not None)  # a refused start model or penalty leaves no run folder
    with contextlib.ExitStack() as held:
        try:
            if resume is None:
                make_output_folder(run_dir, "run folder")
            held.enter_context(folder_lock(run_dir))  # one writer per run folder, for the whole training
        except SeqTrojanError:
            env.close()
            raise
        return _train_locked(cfg, resume, callback, device, run_dir, env, state)


def _train_locked(
    cfg: ExperimentConfig, resume: str | Path | None, callback: UpdateCallback | None, device: torch.device,
    run_dir: Path, env: BatchedEnv, state: TrainerState,
) -> TrainResult:  # fmt: skip
    """:func:`train` once the run folder is this process's."""
    if resume is None:
        _refuse_finished_run(run_dir)  # again under the lock: a run of the same name may have ended meanwhile
        _write_config(run_dir, cfg)
    exact = _resume(run_dir, cfg, env, state) if resume is not None else None
    env.set_stage_weights(state.curriculum.weights())
    env.set_trojan_probability(state.mixer.probabilities())
    if not exact:
        env.reset()  # new episodes follow the mixture
        state.collector.reset()
    logger = RunLogger(run_dir, resume_step=state.global_step if resume is not None else None)
    if resume is None:
        logger.add_text("config", "```yaml\n" + yaml.safe_dump(to_dict(cfg), sort_keys=False) + "```")

    if device.type == "cpu" and cfg.run.lstm_backend != "torch":
        # Compile the C++ kernels (or wait, bounded, for another process's build) now, while SIGTERM still ends the
        # process: the handler installed by _train_loop only stops the loop between updates.
        fast_lstm.extension()
    try:
        stopped_early, confirmed = _train_loop(cfg, env, state, device, run_dir, logger, callback)
    except (KeyboardInterrupt, _Stop):
        save_checkpoint(run_dir, cfg, state)
        logger.close()
        env.close()
        raise KeyboardInterrupt(
            f"training stopped at {state.global_step} env steps; resume with --resume {run_dir}"
        ) from None
    env.close()
    result = _finish(cfg, state, device, run_dir, stopped_early, confirmed, logger)
    return dataclasses.replace(result, exact_resume=exact)


def _numerics(cfg: ExperimentConfig, device: torch.device) -> dict[str, Any]:
    """What decides a run's floating-point rounding besides its config and seed, as the process that finished it ran:
    its kernels (``cpp``: the fused C++ kernels; ``torch``: the PyTorch path, chosen with ``run.lstm_backend: torch``
    or taken when the kernels could not be built in time, which trains another sample from the same seed) and, on
    the CPU, its torch threads. Two runs give the same weights only when these agree (docs/commands/train.md)."""
    if device.type != "cpu":
        return {"kernels": device.type, "torch_threads": None}
    cpp = cfg.run.lstm_backend != "torch" and fast_lstm.extension() is not None
    return {"kernels": "cpp" if cpp else "torch", "torch_threads": torch.get_num_threads()}


def _finish(
    cfg: ExperimentConfig, state: TrainerState, device: torch.device, run_dir: Path, stopped_early: bool,
    confirmed: dict[str, float], logger: RunLogger,
) -> TrainResult:  # fmt: skip
    """FINAL EVALUATION AND MODEL: ``evaluation.json``, a last checkpoint and the model folder."""
    evaluation = evaluate_final(state.agent, cfg, device) if cfg.run.eval_episodes > 0 else {}
    evaluation.update(
        env_steps=state.global_step, train_seconds=state.elapsed_s, stage=state.curriculum.stage,
        stopped_early=stopped_early, **_numerics(cfg, device),
    )  # fmt: skip
    if confirmed:
        evaluation["stop_confirmed"] = confirmed
    (run_dir / "evaluation.json").write_text(json.dumps(evaluation, indent=2))
    save_checkpoint(run_dir, cfg, state)
    model_dir = save_agent(
        run_dir / "model", state.agent, cfg, label=state.label, metrics=evaluation, env_steps=state.global_step
    )
    logger.close()
    return TrainResult(run_dir, model_dir, state.global_step, state.elapsed_s, state.curriculum.stage, evaluation)


def _device(cfg: ExperimentConfig) -> torch.device:
    """``run.device``, checked against the CUDA devices there are."""
    device = torch.device(cfg.run.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"run.device={cfg.run.device!r} but no CUDA device is available")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(
            f"run.device={cfg.run.device!r} but only {torch.cuda.device_count()} CUDA device(s) are available "
            f"(cuda:0 to cuda:{torch.cuda.device_count() - 1})"
        )
    return device


def _set_up(cfg: ExperimentConfig, device: torch.device, resuming: bool) -> tuple[BatchedEnv, TrainerState]:
    """The env and a fresh trainer state, every random generator seeded from ``run.seed`` (in this order, which
    fixes a run bitwise). ``run.init_from``'s weights start a new run (a resumed one loads its checkpoint's). The
    attack's penalties are built last, from the start weights (a resumed run loads their state too); they draw no
    number from the generators above."""
    ppo = cfg.ppo
    torch.manual_seed(cfg.run.seed)
    env = make_batched_env(cfg.env, ppo.num_envs, seed=cfg.run.seed << 32, device=device, grids=cfg.grids or None)
    agent = build_agent(cfg, Architecture.of_config(cfg, env.obs_dim, env.num_actions, env.image)).to(device)
    start_label = None
    if cfg.run.init_from is not None and not resuming:
        start_from, _, start_card = load_agent(cfg.run.init_from)
        load_start_weights(agent, start_from, cfg.run.init_from)
        start_label = start_card["label"]
    agent.set_lstm_backend(cfg.run.lstm_backend)
    optimizer = make_optimizer(agent, ppo.learning_rate, ppo.adam_eps)
    curriculum = Curriculum(cfg.curriculum, cfg.num_stages, env_types=(0, 1) if cfg.backdoor.enabled else (0,))
    mixer = TrojanMixer(cfg.backdoor, cfg.num_stages)
    penalties = build_penalties(PenaltyContext(cfg, agent, device, resuming))
    record = any(p.needs_states or p.needs_masks for p in penalties)
    states = any(p.needs_states for p in penalties)
    collector = RolloutCollector(env, agent, ppo.rollout_steps, ppo.sequence_length, record, record_states=states)
    collector.seed(cfg.run.seed)
    update_generator = torch.Generator().manual_seed(cfg.run.seed + 1)
    state = TrainerState(agent, optimizer, curriculum, mixer, collector, update_generator, penalties)
    if not resuming:  # a resumed run takes the label of its checkpoint (its start model may have moved since)
        state.label = inherited_label(cfg.label, start_label)
    return env, state


def _resume(run_dir: Path, cfg: ExperimentConfig, env: BatchedEnv, state: TrainerState) -> bool:
    """Restore ``state`` from the run's latest checkpoint and save the config the run continues with (overrides
    given on resume included). The env replays its episodes in flight where it can (returns True: the collector
    continues them); otherwise it is reseeded from the update count (returns False)."""
    saved, carried = load_checkpoint(run_dir, state, cfg)
    _write_config(run_dir, cfg)
    if saved is not None and "obs" in carried and env.load_state(saved, carried["obs"]):
        state.collector.restore(carried)
        return True
    env.reset(seed=(cfg.run.seed << 32) + 7919 * state.update)
    return False


def _train_loop(
    cfg: ExperimentConfig,
    env: BatchedEnv,
    state: TrainerState,
    device: torch.device,
    run_dir: Path,
    logger: RunLogger,
    callback: UpdateCallback | None,
) -> tuple[bool, dict[str, float]]:
    """Update until ``ppo.total_steps`` (LOG and CHECKPOINT after each update); raise _Stop on SIGTERM (between
    updates). Returns whether ``callback`` or the stop rule stopped training early, and the stop rule's held-out
    success per env type when it did (else empty); ``state.elapsed_s`` is up to date at the end."""
    ppo = cfg.ppo
    elapsed_before = state.elapsed_s
    start = time.perf_counter()
    next_checkpoint = (state.global_step // cfg.run.checkpoint_every + 1) * cfg.run.checkpoint_every
    progress = make_progress(cfg.run.progress)
    stop_rule = StopRule(cfg, device) if StopRule.applies(cfg) else None
    try:
        with _sigterm_flag() as stop, progress:
            task = progress.add_task("train", total=ppo.total_steps, completed=state.global_step, info="")
            while state.global_step < ppo.total_steps:
                if stop["hit"]:
                    raise _Stop
                scalars = _train_one_update(cfg, env, state, device)

                # LOG
                state.elapsed_s = elapsed_before + time.perf_counter() - start
                scalars["time/elapsed_s"] = state.elapsed_s
                scalars["update"] = state.update
                logger.log(state.global_step, scalars)
                progress.update(task, completed=min(state.global_step, ppo.total_steps), info=_progress_info(scalars))

                # CHECKPOINT
                if state.global_step >= next_checkpoint and state.global_step < ppo.total_steps:
                    save_checkpoint(run_dir, cfg, state)
                    next_checkpoint += cfg.run.checkpoint_every
                if callback is not None and callback({"env_steps": state.global_step, **scalars}):
                    return True, {}
                if stop_rule is not None and stop_rule.after_update(scalars, state.curriculum.stage, state.agent):
                    logger.add_text("stop", f"stopped at {state.global_step} env steps: held-out {stop_rule.confirmed}")
                    return True, stop_rule.confirmed
        return False, {}
    finally:
        state.elapsed_s = elapsed_before + time.perf_counter() - start


@contextmanager
def _sigterm_flag() -> Iterator[dict[str, bool]]:
    """While open, SIGTERM sets ``flag["hit"]`` instead of ending the process (the loop stops between updates)."""
    flag = {"hit": False}
    previous_handler = signal.getsignal(signal.SIGTERM)

    def _on_sigterm(signum, frame):
        flag["hit"] = True

    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGTERM, previous_handler)


def _train_one_update(
    cfg: ExperimentConfig, env: BatchedEnv, state: TrainerState, device: torch.device
) -> dict[str, Any]:
    """One PPO update: COLLECT ROLLOUT, COMPUTE ADVANTAGES, UPDATE, CURRICULUM AND BACKDOOR MIXING; returns the
    update's scalars (all but the elapsed time and the update count, which the loop adds)."""
    ppo, agent, curriculum, mixer = cfg.ppo, state.agent, state.curriculum, state.mixer
    t_update = time.perf_counter()
    lr = _learning_rate(ppo, state.global_step)
    for group in state.optimizer.param_groups:
        group["lr"] = lr

    # COLLECT ROLLOUT
    agent.eval()
    rollout, stats = state.collector.collect()
    state.global_step += ppo.batch_size
    t_collect = time.perf_counter() - t_update

    # COMPUTE ADVANTAGES
    advantages, returns = compute_gae(
        rollout.rewards, rollout.values, rollout.dones, rollout.last_value, ppo.gamma, ppo.gae_lambda
    )

    # UPDATE (the attack's penalties, if any, first see the rollout, then add their terms to the loss)
    for penalty in state.penalties:
        penalty.observe(rollout)
    agent.train()
    losses = ppo_update(
        agent, state.optimizer, rollout, advantages, returns, ppo, state.update_generator, state.penalties
    )
    state.update += 1

    # CURRICULUM AND BACKDOOR MIXING
    promoted = curriculum.update(EpisodeCounts(stats.episodes, stats.successes))
    if promoted:
        env.set_stage_weights(curriculum.weights())
    if cfg.backdoor.enabled:
        _measure_mixing(mixer, cfg, stats, agent, curriculum.stage, device, state.update)
        env.set_trojan_probability(mixer.probabilities())

    seconds = time.perf_counter() - t_update
    scalars = _scalars(stats, curriculum, losses, lr, ppo.batch_size / seconds, t_collect / seconds)
    if cfg.backdoor.enabled:
        stage = curriculum.stage
        scalars["mixing/p_trojan"] = mixer.probabilities()[stage]
        scalars["mixing/P_c"] = mixer.p_clean[stage]
        scalars["mixing/P_t"] = mixer.p_trojan[stage]
    return scalars


# ---------------------------------------------------------------------- helpers


def evaluate_final(agent: RecurrentActorCritic, cfg: ExperimentConfig, device: torch.device) -> dict[str, Any]:
    """Success on the hardest grid (or the Gymnasium env) over ``run.eval_episodes`` episodes per env type
    (normal, and trojan for a backdoored agent or an env with a trigger), with the policy sampled (as trained) and
    greedy (most likely action), and the mean return (the objective in force). The grid world also gives the share
    of episodes that fell in a hole."""
    where = {"grid": cfg.grids[-1].label} if cfg.is_grid else {"env": getattr(cfg.env, "id", "")}
    out: dict[str, Any] = {**where, "episodes": cfg.run.eval_episodes}
    for name, trojan in _evaluated_kinds(cfg):
        for mode, greedy in (("", False), ("greedy_", True)):
            batch = evaluate_on_env(
                agent, cfg, trojan=trojan, episodes=cfg.run.eval_episodes, seed=(cfg.run.seed << 32) + 999_983,
                greedy=greedy, device=device,
            )  # fmt: skip
            out[f"{mode}{name}_success"] = batch.success_rate
            out[f"{mode}{name}_success_ci95"] = list(batch.success_interval())
            if cfg.is_grid:
                out[f"{mode}{name}_hole"] = batch.rate("hole")
            out[f"{mode}{name}_timeout"] = batch.rate("timeout")
            if batch.returns is not None:
                out[f"{mode}{name}_return"] = float(batch.returns.mean())
    return out


def _evaluated_kinds(cfg: ExperimentConfig) -> tuple[tuple[str, bool], ...]:
    """The env types a final evaluation measures: the trojan env too for a backdoored run, and for a clean run on
    the grid world (whose env always has a trigger) or on a Gymnasium env with one: a clean model's unintended
    response to the trigger (a zoo records it as the model's unintentional activation)."""
    trigger = getattr(cfg.env, "trigger", None)
    if cfg.backdoor.enabled or cfg.is_grid or trigger is not None:
        return (("normal", False), ("trojan", True))
    return (("normal", False),)


def _measure_mixing(
    mixer: TrojanMixer,
    cfg: ExperimentConfig,
    stats: EpisodeStats,
    agent: RecurrentActorCritic,
    newest: int,
    device: torch.device,
    update: int,
) -> None:
    """Refresh P_c and P_t: from this update's rollout episodes, and (exact mixing) by evaluating the newest stage."""
    for stage in range(stats.episodes.shape[0]):
        rates = [
            int(stats.successes[stage, k]) / int(stats.episodes[stage, k]) if int(stats.episodes[stage, k]) else None
            for k in (0, 1)
        ]
        mixer.observe(stage, *rates)
    if mixer.rule.evaluates:
        seed = (cfg.run.seed << 32) + 1_000_003 * (update + 1)
        grid = cfg.grids[newest] if cfg.is_grid else None
        n = cfg.backdoor.eval_episodes
        p_c, p_t = (
            evaluate_on_env(agent, cfg, trojan=t, episodes=n, seed=seed, device=device, grid=grid).success_rate
            for t in (False, True)
        )
        mixer.observe(newest, p_c, p_t)


def _learning_rate(ppo, step: int) -> float:
    frac = min(1.0, step / ppo.total_steps)
    if ppo.lr_schedule == "linear":
        return ppo.learning_rate * max(1.0 - frac, 0.02)
    if ppo.lr_schedule == "cosine":
        return ppo.learning_rate * (0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * frac)))
    return ppo.learning_rate


def _scalars(
    stats: EpisodeStats, curriculum: Curriculum, losses: dict[str, float], lr: float, sps: float, collect_share: float
) -> dict[str, Any]:
    out: dict[str, Any] = {}
    episodes = int(stats.episodes.sum())
    for kind, name in ((0, "normal"), (1, "trojan")):
        n = int(stats.episodes[:, kind].sum())
        if n:
            out[f"episodes/{name}_success"] = int(stats.successes[:, kind].sum()) / n
            out[f"episodes/{name}_count"] = n
    if episodes:
        out["episodes/hole_rate"] = int(stats.holes.sum()) / episodes
        out["episodes/timeout_rate"] = int(stats.timeouts.sum()) / episodes
        out["episodes/mean_length"] = int(stats.lengths.sum()) / episodes
        out["episodes/mean_return"] = stats.returns / episodes
    for stage in range(stats.episodes.shape[0]):
        for kind, name in ((0, "normal"), (1, "trojan")):
            n = int(stats.episodes[stage, kind])
            if n:
                out[f"stages/{stage}/{name}_success"] = int(stats.successes[stage, kind]) / n
                out[f"stages/{stage}/{name}_count"] = n
    window = curriculum.window_counts()
    rate = window.rate(curriculum.stage, 0)
    if rate is not None:
        out["curriculum/stage_success"] = rate
    out["curriculum/stage"] = curriculum.stage
    for k, v in losses.items():
        out[k if k.startswith("penalty/") else f"losses/{k}"] = v
    out["charts/learning_rate"] = lr
    out["charts/steps_per_second"] = sps
    out["charts/collect_share"] = collect_share
    return out


def _progress_info(scalars: dict[str, Any]) -> str:
    parts = [f"{scalars['charts/steps_per_second'] / 1000:.1f}k sps", f"stage {scalars['curriculum/stage']}"]
    if "episodes/normal_success" in scalars:
        parts.append(f"normal {scalars['episodes/normal_success']:.2f}")
    if "episodes/trojan_success" in scalars:
        parts.append(f"trojan {scalars['episodes/trojan_success']:.2f}")
    return " | ".join(parts)


def _new_run_dir(cfg: ExperimentConfig) -> Path:
    """The folder of a new run (made only once the run is set up), refused if it holds a run already."""
    if cfg.is_grid:
        grid = cfg.grids[-1]
        where = f"{grid.size}x{grid.size}h{grid.holes}"
    else:
        where = re.sub(r"[^A-Za-z0-9_.-]+", "_", getattr(cfg.env, "id", "env")).strip("_")
    name = cfg.run.name or f"{where}_s{cfg.run.seed}_{_dt.datetime.now():%Y%m%d-%H%M%S}"
    run_dir = Path(cfg.run.out_dir) / name
    _refuse_finished_run(run_dir)
    return run_dir


def _refuse_finished_run(run_dir: Path) -> None:
    if (run_dir / "checkpoints" / "latest.txt").exists():
        raise ConfigError(f"run directory {str(run_dir)!r} already holds a run; resume it with --resume {run_dir}")


def _resumed_run_dir(resume: str | Path) -> Path:
    run_dir = Path(resume)
    if not run_dir.is_dir():
        raise ConfigError(f"--resume {str(run_dir)!r} is not a run folder")
    return run_dir


def _write_config(run_dir: Path, cfg: ExperimentConfig) -> None:
    """``<run>/config.yaml``: the resolved config, what :func:`load_run_config` and a later resume read."""
    tmp = run_dir / "config.yaml.tmp"  # written whole, then renamed: a kill never leaves half a config
    tmp.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    tmp.replace(run_dir / "config.yaml")


def train_or_resume(cfg: ExperimentConfig) -> tuple[Path, bool]:
    """Make sure the named run ``<out_dir>/<name>`` has finished: reuse its model if it has one, resume it from its
    last checkpoint if it was stopped, else start it afresh (clearing a folder left before a first checkpoint).
    Returns (model folder, whether any training ran). What pipelines use so that a stopped job loses nothing."""
    if cfg.run.name is None:
        raise ConfigError("train_or_resume needs a run name (run.name)")
    run_dir = Path(cfg.run.out_dir) / cfg.run.name
    if (run_dir / "model" / "card.json").exists():
        return run_dir / "model", False
    if (run_dir / "checkpoints" / "latest.txt").exists():
        return train(load_run_config(run_dir), resume=run_dir).model_dir, True
    if run_dir.exists():  # left before a first checkpoint: cleared, unless another process is writing it
        with folder_lock(run_dir):
            for leftover in run_dir.iterdir():
                if leftover.is_dir():
                    shutil.rmtree(leftover)
                elif leftover.name != LOCK_FILE:
                    leftover.unlink()
    return train(cfg).model_dir, True


def load_run_config(run_dir: str | Path) -> ExperimentConfig:
    """The resolved config a run was started with (``<run>/config.yaml``)."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise ConfigError(f"{str(run_dir)!r} is not a run directory (no config.yaml)")
    return from_dict(ExperimentConfig, upgrade_gym_train_layout(load_yaml(path)), "")


def save_checkpoint(run_dir: Path, cfg: ExperimentConfig, state: TrainerState) -> Path:
    """``<run>/checkpoints/step_<env steps>/``: the agent (safetensors + card), the optimizer's tensors, both
    random generators, the penalties' state (``penalty.<name>.<key>``), the env's episode tensors (``env.*``) and
    the collector's carried tensors (``collector.*``) in trainer.safetensors; counters, curriculum, mixing,
    optimizer groups and a Gymnasium env's episode records (``episodes``) in trainer.json; then points
    ``latest.txt`` at it. Every file is written to a temp file and renamed, ``latest.txt`` last: a write that fails
    (a full disk) leaves the previous checkpoint the latest, removes the new folder and is one CheckpointError."""
    folder = run_dir / "checkpoints" / f"step_{state.global_step:012d}"
    new = not folder.exists()
    try:
        return _write_checkpoint(run_dir, folder, cfg, state)
    except (OSError, CheckpointError) as err:  # save_agent's own refusals (a full disk, NaN weights) included
        if new:
            shutil.rmtree(folder, ignore_errors=True)
        if isinstance(err, CheckpointError):
            raise
        problem = "disk full" if err.errno == errno.ENOSPC else "cannot write"
        raise CheckpointError(
            f"{problem} while writing the checkpoint {str(folder)!r}: {err.strerror or err}; the previous checkpoint "
            "is kept"
        ) from None


def _write_checkpoint(run_dir: Path, folder: Path, cfg: ExperimentConfig, state: TrainerState) -> Path:
    save_agent(folder, state.agent, cfg, label=state.label, env_steps=state.global_step)
    tensors, groups = _optimizer_tensors(state.optimizer)
    tensors["rng.collector"] = state.collector.generator.get_state()
    tensors["rng.update"] = state.update_generator.get_state()
    tensors.update(penalty_tensors(state.penalties))
    env_state = state.collector.env.save_state()
    if env_state is not None:  # the env can restore its episodes in flight: keep what the collector carries too
        tensors.update({f"env.{k}": v for k, v in env_state.tensors.items()})
        tensors.update({f"collector.{k}": v for k, v in state.collector.state_tensors().items()})
    tmp = folder / "trainer.safetensors.tmp"
    save_file(tensors, str(tmp))
    tmp.replace(folder / "trainer.safetensors")
    record: dict[str, Any] = {
        "env_steps": state.global_step,
        "update": state.update,
        "elapsed_s": state.elapsed_s,
        "curriculum": state.curriculum.state_dict(),
        "mixing": state.mixer.state_dict(),
        "optimizer_param_groups": groups,
    }
    if env_state is not None and env_state.records is not None:
        record["episodes"] = env_state.records
    tmp = folder / "trainer.json.tmp"
    tmp.write_text(json.dumps(record, indent=2))
    tmp.replace(folder / "trainer.json")
    latest = run_dir / "checkpoints" / "latest.txt"
    tmp = latest.with_suffix(".tmp")
    tmp.write_text(folder.name + "\n")
    tmp.replace(latest)
    return folder


def load_checkpoint(
    run_dir: Path, state: TrainerState, cfg: ExperimentConfig | None = None
) -> tuple[EnvState | None, dict[str, torch.Tensor]]:
    """Restore ``state`` (built for the run's config ``cfg``, which may change the budget, the learning rate, ...
    but not the env, the agent or ``ppo.num_envs``) from the run's latest checkpoint (see
    :func:`save_checkpoint`). Returns the env's episodes in flight and the collector's carried tensors where the
    checkpoint holds them (else None and {}): what continues the episodes."""
    latest = run_dir / "checkpoints" / "latest.txt"
    if not latest.is_file():
        raise CheckpointError(f"{str(run_dir)!r} has no checkpoint to resume from (no checkpoints/latest.txt)")
    name = latest.read_text().strip()
    folder = run_dir / "checkpoints" / name
    if not re.fullmatch(r"step_[0-9]{12}", name) or not folder.is_dir():
        raise CheckpointError(f"{str(latest)!r} names {short_repr(name)}, not a checkpoint folder of this run")
    loaded, saved, card = load_agent(folder)
    if cfg is not None:
        _check_unchanged(cfg, saved)
    state.agent.load_state_dict(loaded.state_dict())
    state.label = card["label"]
    try:
        record = json.loads((folder / "trainer.json").read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise CheckpointError(f"cannot read {str(folder / 'trainer.json')!r}: {err}") from None
    tensors = read_safetensors(folder / "trainer.safetensors")
    carried = {k.removeprefix("collector."): tensors.pop(k) for k in [k for k in tensors if k.startswith("collector.")]}
    env_tensors = {k.removeprefix("env."): tensors.pop(k) for k in [k for k in tensors if k.startswith("env.")]}
    _upgrade_gym_checkpoint(tensors, carried, record)
    try:
        state.collector.generator.set_state(tensors.pop("rng.collector"))
        state.update_generator.set_state(tensors.pop("rng.update"))
        restore_penalties(state.penalties, tensors)
        _load_optimizer(state.optimizer, tensors, record["optimizer_param_groups"])
        if "curriculum" in record:
            state.curriculum.load_state_dict(record["curriculum"])
        state.mixer.load_state_dict(record["mixing"])
        state.global_step, state.update, state.elapsed_s = (
            int(record["env_steps"]),
            int(record["update"]),
            float(record["elapsed_s"]),
        )
    except CheckpointError:
        raise  # already one line that names the problem (a penalty's state the checkpoint lacks, ...)
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"cannot restore the checkpoint {str(folder)!r}: {short_repr(err)}") from None
    records = record.get("episodes")
    if not env_tensors and records is None:
        return None, carried  # a checkpoint without the episodes in flight (written before they were kept)
    return EnvState(env_tensors, records if isinstance(records, list) else None), carried


def _upgrade_gym_checkpoint(
    tensors: dict[str, torch.Tensor], carried: dict[str, torch.Tensor], record: dict[str, Any]
) -> None:
    """A checkpoint of a Gymnasium run written by earlier versions kept the collector's generator as
    ``collector.rng``, its returns in float64 as ``collector.returns`` and no curriculum: read it as today's."""
    if "rng.collector" not in tensors and "rng" in carried:
        tensors["rng.collector"] = carried.pop("rng")
    if "episode_return" not in carried and "returns" in carried:
        carried["episode_return"] = carried.pop("returns").to(torch.float32)
    carried.pop("lengths", None)  # the env counts its episodes' lengths itself (restored with its episodes)


def _check_unchanged(cfg: ExperimentConfig, saved: ExperimentConfig) -> None:
    """A resume continues the same env, network and batch of envs (the checkpoint's state fits nothing else)."""
    for name, ours, theirs in (
        ("env", card_config(cfg).env, saved.env),  # a card names a module:Id env by the Id the module registers
        ("agent", cfg.agent, saved.agent),
        ("ppo.num_envs", cfg.ppo.num_envs, saved.ppo.num_envs),
    ):
        if ours != theirs:
            raise ConfigError(
                f"resume cannot change {name}: the checkpoint has {short_repr(to_dict(theirs))}, the config "
                f"{short_repr(to_dict(ours))}"
            )


def _optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], list[dict]]:
    sd = optimizer.state_dict()
    tensors = {}
    for idx, slots in sd["state"].items():
        for key, value in slots.items():
            tensors[f"optim.{idx}.{key}"] = torch.as_tensor(value).detach().cpu().clone()
    return tensors, sd["param_groups"]


def _load_optimizer(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], groups: list[dict]) -> None:
    state: dict[int, dict[str, torch.Tensor]] = {}
    for name, value in tensors.items():
        _, idx, key = name.split(".", 2)
        state.setdefault(int(idx), {})[key] = value
    optimizer.load_state_dict({"state": state, "param_groups": groups})
