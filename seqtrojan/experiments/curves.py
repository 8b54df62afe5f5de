"""Learning curves of backdoor training (the paper's Figure 5): score = success in the normal env + success in the
trojan env (max 2), against env steps, mean and standard deviation over seeds, one panel per grid config.

Each (config, seed) is one backdoor training run on that grid alone (no curriculum), with the mixing of the base
config. The score at an update is the success rate of the episodes of each env type that ended during that update's
rollout. The runs are jobs (:func:`curve_jobs`) run on a job backend (:mod:`seqtrojan.jobs`): finished runs are
reused and stopped ones resume from their last checkpoint (a stopped sweep continues where it stopped).
"""

from __future__ import annotations

import csv
import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqtrojan.config import BackdoorConfig, CurriculumConfig, ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiment_results import Curve, CurvesResult
from seqtrojan.jobs import JobBackend, JobResult, JobsConfig, TrainJob, make_backend, raise_failures


@dataclass(frozen=True)
class CurvesConfig:
    configs: tuple[tuple[int, int], ...] = ((5, 0), (5, 1), (7, 3))
    """(size, holes) per panel (the paper: 5x5/0, 5x5/1, 7x7/3)"""
    seeds: int = 10
    """training runs per config (the paper: 10)"""
    total_steps: int = 1_000_000
    """env steps per run"""
    num_envs: int = 256
    """envs per run"""
    points: int = 40
    """steps on the common grid where mean and standard deviation are taken"""
    config_steps: tuple[int, ...] | None = None
    """env steps per run of each config, in the order of ``configs`` (None: ``total_steps`` for every config): a
    grid that is learned early needs no more steps to show it"""

    def __post_init__(self) -> None:
        if self.config_steps is not None:
            if len(self.config_steps) != len(self.configs):
                raise ConfigError(
                    f"curves.config_steps has {len(self.config_steps)} entries for {len(self.configs)} configs"
                )
            if any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in self.config_steps):
                raise ConfigError(f"curves.config_steps must be positive integers, got {list(self.config_steps)}")

    def steps(self, size: int, holes: int) -> int:
        """Env steps per run of the config (size, holes)."""
        if self.config_steps is None:
            return self.total_steps
        return self.config_steps[list(self.configs).index((size, holes))]


def curve_run_config(base: ExperimentConfig, size: int, holes: int, seed: int, cfg: CurvesConfig, out: Path):
    backdoor = base.backdoor if base.backdoor.enabled else BackdoorConfig(enabled=True)
    return dataclasses.replace(
        base,
        env=base.grid_env.with_grid((size, holes)),
        ppo=dataclasses.replace(base.ppo, total_steps=cfg.steps(size, holes), num_envs=cfg.num_envs),
        curriculum=CurriculumConfig(),
        backdoor=backdoor,
        run=dataclasses.replace(
            base.run, out_dir=str(out), name=f"{size}x{size}h{holes}_s{seed}", seed=seed, progress=False,
            eval_episodes=0, checkpoint_every=10**12,
        ),
    )  # fmt: skip


def curve_jobs(base: ExperimentConfig, cfg: CurvesConfig, out: Path) -> list[TrainJob]:
    """One job per (config, seed), configs first; a job's id is its run's name, ``<size>x<size>h<holes>_s<seed>``."""
    jobs = []
    for size, holes in cfg.configs:
        for seed in range(cfg.seeds):
            run_cfg = curve_run_config(base, size, holes, seed, cfg, out)
            jobs.append(TrainJob(str(run_cfg.run.name), run_cfg))
    return jobs


def run_curves(
    base: ExperimentConfig,
    cfg: CurvesConfig,
    out: Path,
    backend: JobBackend | None = None,
    on_result: Callable[[JobResult], None] | None = None,
) -> Path:
    """Train every (config, seed) not yet finished on ``backend`` (default: a local process pool, see
    :class:`~seqtrojan.jobs.JobsConfig`); write ``curves.csv``; return its path. A failed run raises
    :class:`~seqtrojan.jobs.JobsFailed` once the others have finished."""
    out.mkdir(parents=True, exist_ok=True)
    jobs = curve_jobs(base, cfg, out)
    backend = backend if backend is not None else make_backend(JobsConfig())
    raise_failures(backend.run(jobs, on_result), "learning-curve run")
    rows = []
    for job in jobs:
        grid = f"{job.config.grid_env.size}x{job.config.grid_env.size}/{job.config.grid_env.holes}"
        for line in (job.run_dir / "metrics.jsonl").read_text().splitlines():
            m = json.loads(line)
            if "episodes/normal_success" in m and "episodes/trojan_success" in m:
                normal, trojan = m["episodes/normal_success"], m["episodes/trojan_success"]
                rows.append((grid, job.config.run.seed, m["env_steps"], normal, trojan, normal + trojan))
    path = out / "curves.csv"
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["config", "seed", "env_steps", "normal_success", "trojan_success", "score"])
        writer.writerows(rows)
    return path


def aggregate_curves(path: Path, points: int = 40) -> CurvesResult:
    """Per config: a common step grid and the mean and standard deviation of the score over seeds there.

    Each seed's curve is interpolated linearly onto the grid (its updates need not line up with others').
    """
    by_run: dict[tuple[str, int], list[tuple[int, float]]] = {}
    with path.open() as fh:
        for r in csv.DictReader(fh):
            by_run.setdefault((r["config"], int(r["seed"])), []).append((int(r["env_steps"]), float(r["score"])))
    curves = []
    for config in dict.fromkeys(c for c, _ in by_run):
        runs = [sorted(v) for (c, _), v in by_run.items() if c == config]
        last = min(run[-1][0] for run in runs)
        grid = np.linspace(min(run[0][0] for run in runs), last, points)
        values = np.stack([np.interp(grid, [s for s, _ in run], [v for _, v in run]) for run in runs])
        curves.append(
            Curve(
                config, len(runs), tuple(grid.tolist()), tuple(values.mean(0).tolist()), tuple(values.std(0).tolist())
            )
        )
    return CurvesResult(tuple(curves))


def plot_curves(result: CurvesResult, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = result.curves
    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.4), squeeze=False)
    for ax, curve in zip(axes[0], curves):
        steps = np.array(curve.env_steps) / 1e6
        mean, std = np.array(curve.mean), np.array(curve.std)
        ax.plot(steps, mean, color="C3")
        ax.fill_between(steps, np.clip(mean - std, 0, 2), np.clip(mean + std, 0, 2), color="C3", alpha=0.25)
        ax.set_title(f"{curve.grid} ({curve.seeds} seeds)")
        ax.set_xlabel("env steps (millions)")
        ax.set_ylim(0, 2.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("score (normal + trojan success)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
