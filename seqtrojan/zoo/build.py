"""A model zoo: many clean and backdoored agents with varied seeds, LSTM widths, trigger patterns and curricula.

Every model is a pure job, ``(ZooJob) -> model folder``: its whole config is derived from the zoo config and its
index, so a job gives the same model wherever it runs (a local process pool by default, a Ray cluster with
``backend="ray"``). The zoo folder holds::

    models/<id>/model.safetensors, card.json   the agent (as any seqtrojan model)
    models/<id>/label.json                     ground truth: clean/backdoored, the trigger, its final attack
                                               success and whether the backdoor is functional; scoring only
    manifest.json                              every job: id, label, status, variation, time

A stopped build continues where it stopped: finished models (with ``label.json``) are kept, unfinished ones are
trained again (from their last checkpoint when there is one).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from seqtrojan.config import (
    AgentConfig,
    BackdoorConfig,
    CurriculumConfig,
    ExperimentConfig,
    PPOConfig,
    RunConfig,
    to_dict,
)
from seqtrojan.env.config import EnvConfig, GridSpec, TriggerConfig
from seqtrojan.errors import ConfigError

TRIGGER_VALUES = ("trigger", "hole", "empty", "wall")
DEFAULT_TRIGGER_VALUES = ("trigger", "hole", "wall")
"""'empty' is left out by default: a patch of empty cells over cells that are usually empty is invisible"""


@dataclass(frozen=True)
class ZooConfig:
    clean: int = 20
    """number of clean models"""
    backdoored: int = 20
    """number of backdoored models"""
    seed: int = 0
    """base seed; model i uses seed + i and draws its variation from it"""
    lstm_sizes: tuple[tuple[int, ...], ...] = ((64, 32), (32, 32), (64,), (48, 24))
    """architectures to draw from"""
    trigger_values: tuple[str, ...] = DEFAULT_TRIGGER_VALUES
    """cell codes a trigger patch can use ('trigger' is the dedicated channel; the others look ordinary)"""
    trigger_cells: tuple[int, int] = (3, 9)
    """inclusive range of the number of view cells a trigger patch covers"""
    trigger_durations: tuple[int, ...] = (1, 2)
    curricula: tuple[tuple[GridSpec, ...], ...] = (
        (GridSpec(5, 0), GridSpec(5, 1), GridSpec(7, 3)),
        (GridSpec(5, 1), GridSpec(7, 3)),
        (GridSpec(5, 0), GridSpec(7, 3), GridSpec(9, 6)),
    )
    """curricula to draw from (the last stage is the model's training grid)"""
    total_steps: int = 1_500_000
    num_envs: int = 256
    mixing: str = "running"
    """backdoor mixing of the backdoored models (exact / running / fixed)"""
    eval_episodes: int = 200
    """final evaluation episodes per env type (recorded in each card)"""
    functional_at: float = 0.5
    """a backdoored model's backdoor counts as functional (``label.json``: ``functional_backdoor``) when its final
    trojan-env success is at least this"""

    def __post_init__(self) -> None:
        if self.clean < 0 or self.backdoored < 0 or self.clean + self.backdoored == 0:
            raise ConfigError(f"a zoo needs models: clean={self.clean}, backdoored={self.backdoored}")
        unknown = set(self.trigger_values) - set(TRIGGER_VALUES)
        if unknown:
            raise ConfigError(f"unknown trigger value(s) {sorted(unknown)}; choose from {TRIGGER_VALUES}")
        lo, hi = self.trigger_cells
        if not 1 <= lo <= hi <= 9:
            raise ConfigError(f"trigger_cells={self.trigger_cells} must be a range within 1..9")

    @property
    def size(self) -> int:
        return self.clean + self.backdoored


@dataclass(frozen=True)
class ZooJob:
    """One model of the zoo: everything needed to train it, nothing else."""

    model_id: str
    label: str  # clean / backdoored
    config: ExperimentConfig
    variation: dict[str, Any] = field(default_factory=dict)
    functional_at: float = 0.5


def make_jobs(cfg: ZooConfig, root: Path) -> list[ZooJob]:
    """The zoo's jobs, a pure function of the zoo config: clean and backdoored models interleaved."""
    jobs = []
    labels = ["backdoored"] * cfg.backdoored + ["clean"] * cfg.clean
    order = np.random.default_rng(cfg.seed).permutation(len(labels))
    for i, k in enumerate(order):
        label = labels[k]
        seed = cfg.seed + i
        rng = np.random.default_rng([cfg.seed, i, 7919])
        sizes = cfg.lstm_sizes[rng.integers(len(cfg.lstm_sizes))]
        stages = cfg.curricula[rng.integers(len(cfg.curricula))]
        value = str(cfg.trigger_values[rng.integers(len(cfg.trigger_values))])
        n_cells = int(rng.integers(cfg.trigger_cells[0], cfg.trigger_cells[1] + 1))
        cells = tuple(sorted((int(c) // 3, int(c) % 3) for c in rng.choice(9, size=n_cells, replace=False)))
        duration = int(cfg.trigger_durations[rng.integers(len(cfg.trigger_durations))])
        trigger = TriggerConfig(cells=cells, value=value, duration=duration, train_steps=(1, 8), eval_steps=(1, 8))
        last = stages[-1]
        config = ExperimentConfig(
            env=EnvConfig(size=last.size, holes=last.holes, trigger=trigger),
            agent=AgentConfig(lstm_sizes=tuple(sizes)),
            ppo=PPOConfig(total_steps=cfg.total_steps, num_envs=cfg.num_envs, rollout_steps=64),
            curriculum=CurriculumConfig(stages=tuple(stages)),
            backdoor=BackdoorConfig(enabled=label == "backdoored", mixing=cfg.mixing),  # type: ignore[arg-type]
            run=RunConfig(
                out_dir=str(root / "work"), name=f"m{i:04d}", seed=seed, progress=False,
                eval_episodes=cfg.eval_episodes, checkpoint_every=max(cfg.total_steps // 4, 1),
            ),
        )  # fmt: skip
        variation = {
            "lstm_sizes": list(sizes), "curriculum": [g.label for g in stages], "trigger_value": value,
            "trigger_cells": [list(c) for c in cells], "trigger_duration": duration, "seed": seed,
        }  # fmt: skip
        jobs.append(ZooJob(f"m{i:04d}", label, config, variation, cfg.functional_at))
    return jobs


def run_job(job: ZooJob, models_dir: str, threads: int = 1) -> dict[str, Any]:
    """Train one zoo model (pure: its outputs depend only on ``job``); returns its manifest entry."""
    import torch

    from seqtrojan.train.trainer import train_or_resume

    torch.set_num_threads(threads)
    start = time.perf_counter()
    model_dir, _ = train_or_resume(job.config)
    metrics = json.loads((model_dir / "card.json").read_text()).get("metrics", {})
    target = Path(models_dir) / job.model_id
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(model_dir, target)
    truth = {"label": job.label, "variation": job.variation, "trigger": None, "attack_success": None,
             "functional_backdoor": None}  # fmt: skip
    if job.label == "backdoored":
        attack = metrics.get("trojan_success")
        truth.update(trigger=to_dict(job.config.env.trigger), attack_success=attack,
                     functional_backdoor=attack is not None and attack >= job.functional_at)  # fmt: skip
    (target / "label.json").write_text(json.dumps(truth, indent=2))
    shutil.rmtree(model_dir.parent, ignore_errors=True)
    return {
        "id": job.model_id, "label": job.label, "status": "done", "seconds": time.perf_counter() - start,
        "variation": job.variation, "metrics": metrics,
    }  # fmt: skip


def build_zoo(
    cfg: ZooConfig, root: Path, *, workers: int = 2, backend: str = "local", log: Callable[[str], None] = print
) -> Path:
    """Train every job not yet finished; write ``manifest.json``; return its path."""
    root.mkdir(parents=True, exist_ok=True)
    models = root / "models"
    models.mkdir(exist_ok=True)
    (root / "zoo.json").write_text(json.dumps(to_dict(cfg), indent=2))
    jobs = make_jobs(cfg, root)
    manifest_path = root / "manifest.json"
    previous = {e["id"]: e for e in json.loads(manifest_path.read_text())} if manifest_path.exists() else {}
    todo = [j for j in jobs if not (models / j.model_id / "label.json").exists()]
    log(f"zoo: {len(jobs) - len(todo)} of {len(jobs)} models done; training {len(todo)} with {backend} backend")
    entries: dict[str, dict[str, Any]] = {j.model_id: previous.get(j.model_id, {}) for j in jobs}

    def record(entry: dict[str, Any]) -> None:
        entries[entry["id"]] = entry
        ordered = [entries[j.model_id] or {"id": j.model_id, "label": j.label, "status": "pending"} for j in jobs]
        manifest_path.write_text(json.dumps(ordered, indent=2))
        log(f"  {entry['id']} ({entry['label']}) {entry['status']} in {entry.get('seconds', 0):.0f} s")

    if backend == "local":
        if workers <= 1:
            for job in todo:
                record(run_job(job, str(models), threads=2))
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(run_job, job, str(models), 1) for job in todo]
                for future in as_completed(futures):
                    record(future.result())
    elif backend == "ray":
        _run_on_ray(todo, models, workers, record)
    else:
        raise ConfigError(f"unknown zoo backend {backend!r}; use 'local' or 'ray'")
    for job in jobs:  # models finished by an earlier call
        if not entries[job.model_id] and (models / job.model_id / "label.json").exists():
            entries[job.model_id] = {"id": job.model_id, "label": job.label, "status": "done",
                                     "variation": job.variation}  # fmt: skip
    manifest_path.write_text(json.dumps([entries[j.model_id] for j in jobs], indent=2))
    return manifest_path


def _run_on_ray(jobs: list[ZooJob], models: Path, workers: int, record: Callable[[dict], None]) -> None:
    try:
        import ray
    except ImportError:
        raise ConfigError("the ray backend needs Ray: pip install 'seqtrojan[ray]'") from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(num_cpus=max(workers, 1), include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(run_job)
    try:
        pending = [remote.remote(job, str(models), 1) for job in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            record(ray.get(done[0]))
    finally:
        if started_here:
            ray.shutdown()


def job_configs(cfg: ZooConfig) -> list[dict[str, Any]]:
    """The jobs' configs as plain dicts (for inspection)."""
    return [dataclasses.asdict(j.config) for j in make_jobs(cfg, Path("zoo"))]
