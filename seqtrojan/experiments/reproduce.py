"""The paper's results end to end: train a clean and a backdoored agent, evaluate them over the paper's configs,
learning curves, the trajectory figure, the analysis of their internal states (response types, interventions,
unintentional triggers, searches), and a self-contained HTML report beside the paper's numbers.

    seqtrojan reproduce --scale smoke      # minutes on 2 cores: the README's main job
    seqtrojan reproduce --scale paper      # the paper's setting (17x17/30 agents, 1000 trials, 10 seeds)

Each stage writes its outputs under ``--out`` and is skipped when they exist, so a stopped reproduction continues
where it stopped (training runs resume from their last checkpoint).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.analysis.pipeline import AnalysisConfig, run_analysis
from seqtrojan.artifacts import RunLayout, TrajectoryResult
from seqtrojan.config import ExperimentConfig
from seqtrojan.defense.offline import detect_zoo
from seqtrojan.defense.pipeline import DefenseConfig, run_defense
from seqtrojan.env.config import GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.results import save_rows
from seqtrojan.evaluation.seeds import summarise_over_seeds
from seqtrojan.evaluation.sweep import SweepRow, evaluate_sweep, load_sweep, parse_configs, write_sweep
from seqtrojan.experiments.curves import CurvesConfig, aggregate_curves, plot_curves, run_curves
from seqtrojan.experiments.tradeoff import TradeoffConfig, measure_tradeoff_agent, summarise_penalties, tradeoff_agents
from seqtrojan.jobs import JobBackend, JobResult, JobsConfig, TrainJob, make_backend, raise_failures
from seqtrojan.presets import resolve_preset
from seqtrojan.report.figures import frames_to_text, plot_trajectory_pair, run_pair
from seqtrojan.report.html import build_report
from seqtrojan.serde import from_dict, load_yaml, save_json, to_dict
from seqtrojan.train.trainer import load_run_config
from seqtrojan.zoo.build import ZooConfig, build_zoo


@dataclass(frozen=True)
class AgentSpec:
    """A training preset (a name in configs/ or a path) and overrides merged into it."""

    preset: str = "clean_s17_h30"
    set: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EvaluationSpec:
    configs: str = "paper"
    """'paper' (Tables 1 and 2) or a list like '7x7/0,11x11/11'"""
    episodes: int = 1000
    seed: int = 0
    greedy: bool = False


@dataclass(frozen=True)
class TrajectorySpec:
    size: int = 17
    holes: int = 30
    trigger_step: int = 12
    """the paper's Figure 6 shows the trigger at step 12"""
    seed: int = 0
    """layout seed; the first layout of this seed is used"""
    greedy: bool = True


@dataclass(frozen=True)
class ReproduceConfig:
    clean: AgentSpec = field(default_factory=AgentSpec)
    backdoor: AgentSpec = field(default_factory=lambda: AgentSpec(preset="trojan_s17_h30"))
    seeds: int = 1
    """training seeds of the headline clean and backdoored agents (run.seed = the preset's seed + 0 .. seeds-1);
    Tables 1-2 and the headline report mean +- sd over them; the seed-0 agents feed every later stage"""
    evaluation: EvaluationSpec = field(default_factory=EvaluationSpec)
    curves: CurvesConfig | None = field(default_factory=CurvesConfig)
    """learning curves; None skips them"""
    trajectory: TrajectorySpec | None = field(default_factory=TrajectorySpec)
    """the one-layout trajectory figure; None skips it"""
    analysis: AnalysisConfig | None = field(default_factory=AnalysisConfig)
    """looking inside the agents; None skips it"""
    defense: DefenseConfig | None = field(default_factory=DefenseConfig)
    """monitor and mitigation of the backdoored agent; None skips it"""
    tradeoff: TradeoffConfig | None = None
    """the adversary's trade-off (penalty on unintentional activation); None skips it"""
    zoo: ZooConfig | None = None
    """a zoo for offline detection; None skips it"""
    jobs: JobsConfig = field(default_factory=JobsConfig)
    """how the stages that train many agents (curves, trade-off, zoo) run them: backend (serial, pool, ray), workers,
    ray_address, threads (see seqtrojan.jobs)"""
    zoo_workers: int | None = None
    """the old name of jobs.workers (older scale files set it); None once read"""
    device: str = "cpu"

    def __post_init__(self) -> None:
        if not isinstance(self.seeds, int) or not 1 <= self.seeds <= 100:
            raise ConfigError(f"seeds must be an integer in 1..100, got {self.seeds!r}")
        if self.zoo_workers is not None:  # an older scale file: zoo_workers is now jobs.workers
            if self.jobs.workers not in (JobsConfig().workers, self.zoo_workers):
                raise ConfigError(
                    f"zoo_workers={self.zoo_workers!r} and jobs.workers={self.jobs.workers} disagree; set only "
                    "jobs.workers (zoo_workers is its old name)"
                )
            object.__setattr__(self, "jobs", dataclasses.replace(self.jobs, workers=self.zoo_workers))
            object.__setattr__(self, "zoo_workers", None)


def deep_merge(base: dict, update: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def experiment_from_spec(spec: AgentSpec, out_dir: Path, name: str, device: str) -> ExperimentConfig:
    data = deep_merge(load_yaml(resolve_preset(spec.preset)), spec.set)
    data = deep_merge(data, {"run": {"out_dir": str(out_dir), "name": name, "device": device}})
    return from_dict(ExperimentConfig, data, "")


def load_reproduce_config(scale_or_path: str) -> ReproduceConfig:
    path = resolve_preset(scale_or_path if scale_or_path.endswith(".yaml") else f"reproduce_{scale_or_path}.yaml")
    return from_dict(ReproduceConfig, load_yaml(path), "")


class _Timer:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.times: dict[str, float] = json.loads(path.read_text()) if path.exists() else {}

    def record(self, stage: str, seconds: float) -> None:
        self.times[stage] = seconds
        self.path.write_text(json.dumps(self.times, indent=2))


def reproduce(config: ReproduceConfig, out: Path, scale: str = "custom", log=print) -> Path:
    """Run every stage not yet done; return the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "reproduce.yaml").write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    timer = _Timer(out / "timings.json")
    start = time.perf_counter()

    seed_models = _train_headline(config, out, make_backend(config.jobs), timer, log)
    models = seed_models[0]  # role -> the seed-0 model, used by every later stage

    agents = []
    for role, folder in models.items():
        agent, cfg, _ = load_agent(folder, device=config.device)
        agents.append((role, agent, cfg))

    _evaluate_seeds(config, seed_models, out / "evaluation", timer, log)

    curves_dir = out / "curves"
    if config.curves is not None and not (curves_dir / "curves.json").exists():
        log("learning curves ...")
        t0 = time.perf_counter()
        base = load_run_config(out / "runs" / "backdoor")
        csv_path = run_curves(base, config.curves, curves_dir, make_backend(config.jobs), _job_log(log))
        curves = aggregate_curves(csv_path, config.curves.points)
        plot_curves(curves, curves_dir / "curves.png")
        (curves_dir / "curves.json").write_text(json.dumps(curves))
        timer.record("curves", time.perf_counter() - t0)

    traj_png = out / "trajectory.png"
    if config.trajectory is not None and not traj_png.exists():
        log("trajectory figure ...")
        t0 = time.perf_counter()
        _trajectory_figure(agents[1][1], agents[1][2], config.trajectory, out, config.device)
        timer.record("trajectory", time.perf_counter() - t0)

    layout = RunLayout(out)
    if config.analysis is not None and not layout.analysis_file.exists():
        log("looking inside the agents ...")
        t0 = time.perf_counter()
        run_analysis(models["clean"], models["backdoor"], layout.analysis_dir, config.analysis, config.device, log)
        timer.record("analysis", time.perf_counter() - t0)

    if config.defense is not None and not layout.defense_file.exists():
        log("defending the backdoored agent ...")
        t0 = time.perf_counter()
        run_defense(models["backdoor"], layout.defense_dir, config.defense, config.device, log)
        timer.record("defense", time.perf_counter() - t0)

    if config.tradeoff is not None and not (out / "tradeoff" / "tradeoff.json").exists():
        _tradeoff(config, out, models["backdoor"], make_backend(config.jobs), timer, log)

    if config.zoo is not None and not layout.detection_file.exists():
        log(f"building a zoo of {config.zoo.size} models and scoring offline detection ...")
        t0 = time.perf_counter()
        jobs = config.jobs
        build_zoo(config.zoo, out / "zoo", workers=jobs.workers, backend=jobs.backend, ray_address=jobs.ray_address,
                  threads=jobs.threads, log=log)  # fmt: skip
        timer.record("zoo_build", time.perf_counter() - t0)
        save_json(detect_zoo(layout.zoo_dir), layout.detection_file)

    timer.record("last_call_before_report", time.perf_counter() - start)
    report = build_report(out, scale=scale, machine=machine_summary())
    log(f"report: {report}")
    return report


def headline_run_name(role: str, offset: int) -> str:
    """Run folder of a headline agent: ``clean``/``backdoor`` for the first seed, ``<role>_seed<k>`` after."""
    return role if offset == 0 else f"{role}_seed{offset}"


def _evaluate_seeds(
    config: ReproduceConfig, seed_models: list[dict[str, Path]], eval_dir: Path, timer: _Timer, log
) -> None:
    """Evaluate each seed's pair over the configs (one file per seed, so a stopped stage resumes), then write
    every row to evaluation.json/.csv and the per-cell summary over seeds to summary.json."""
    ev = config.evaluation
    configs = parse_configs(ev.configs)
    eval_dir.mkdir(parents=True, exist_ok=True)
    rows: list[SweepRow] = []
    for offset, pair in enumerate(seed_models):
        seed_file = eval_dir / f"seed{offset}.json"
        if not seed_file.exists():
            log(f"evaluating training seed {offset} over the grid configs ...")
            t0 = time.perf_counter()
            agents = []
            for role, folder in pair.items():
                agent, cfg, _ = load_agent(folder, device=config.device)
                agents.append((role, agent, cfg))
            last = agents[-1][2].grids[-1]
            cells = configs if (last.size, last.holes) in configs else [*configs, (last.size, last.holes)]
            seed_rows = evaluate_sweep(
                agents, cells, episodes=ev.episodes, seed=ev.seed, greedy=ev.greedy, device=config.device,
                training_seed=offset,
            )  # fmt: skip
            save_rows(seed_rows, seed_file)
            timer.record(f"evaluation_seed{offset}", time.perf_counter() - t0)
        rows += load_sweep(seed_file)
    write_sweep(rows, eval_dir)
    summaries = [s.to_dict() for s in summarise_over_seeds(rows)]
    (eval_dir / "summary.json").write_text(json.dumps(summaries, indent=2))


def _train_headline(
    config: ReproduceConfig, out: Path, backend: JobBackend, timer: _Timer, log
) -> list[dict[str, Path]]:
    """The clean and backdoored agents of every training seed, on the job backend; per seed: role -> model."""
    jobs: list[TrainJob] = []
    for offset in range(config.seeds):
        for role, spec in (("clean", config.clean), ("backdoor", config.backdoor)):
            name = headline_run_name(role, offset)
            cfg = experiment_from_spec(spec, out / "runs", name, config.device)
            if role == "clean" and cfg.backdoor.enabled:
                raise ConfigError(f"the clean preset {spec.preset!r} has backdoor.enabled: true")
            if role == "backdoor" and not cfg.backdoor.enabled:
                raise ConfigError(f"the backdoor preset {spec.preset!r} does not enable backdoor training")
            jobs.append(
                TrainJob(name, dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=cfg.run.seed + offset)))
            )
    todo = sum(not job.done() for job in jobs)
    if todo:
        grid, steps = jobs[-1].config.grids[-1].label, jobs[-1].config.ppo.total_steps
        log(f"training {todo} headline agent(s) ({grid}, {steps:,} env steps each) on the {backend.name} backend "
            f"({backend.describe(todo)}) ...")  # fmt: skip
    raise_failures(backend.run(jobs, _job_log(log, timer)), "headline agent")
    return [
        {role: jobs[2 * offset + i].model_dir for i, role in enumerate(("clean", "backdoor"))}
        for offset in range(config.seeds)
    ]


def _job_log(log, timer: _Timer | None = None):
    """A job backend's ``on_result``: log each job trained or failed (and record its training time in ``timer``)."""

    def on_result(result: JobResult) -> None:
        if not result.ok:
            log(f"  {result.id} failed: {result.error}")
        elif result.trained:
            log(f"  {result.id} trained in {result.seconds:.0f} s")
            if timer is not None:
                timer.record(f"train_{result.id}", result.seconds)

    return on_result


def _tradeoff(
    config: ReproduceConfig, out: Path, backdoor_model: Path, backend: JobBackend, timer: _Timer, log
) -> None:
    cfg = config.tradeoff
    assert cfg is not None  # called only when the config has a trade-off section
    base = load_run_config(out / "runs" / "backdoor")
    agents = tradeoff_agents(base, cfg, out / "runs")  # the penalty == base agent reuses the backdoored agent
    jobs = [a.job for a in agents if a.job is not None]
    todo = sum(not job.done() for job in jobs)
    if todo:
        log(f"training {todo} trade-off agent(s) on the {backend.name} backend ({backend.describe(todo)}) ...")
    raise_failures(backend.run(jobs, _job_log(log, timer)), "trade-off agent")
    rows = []
    for a in agents:
        model = backdoor_model if a.job is None else a.job.model_dir
        seed = a.config.run.seed
        log(f"measuring the trade-off for false_activation={a.penalty:g}, seed {seed} ...")
        t0 = time.perf_counter()
        agent, _, _ = load_agent(model, device=config.device)
        row = measure_tradeoff_agent(agent, a.config, cfg, a.penalty)
        rows.append({**row, "seed": seed, "model": str(model.relative_to(out))})
        timer.record(f"tradeoff_measure{a.penalty:g}_seed{seed}", time.perf_counter() - t0)
    (out / "tradeoff").mkdir(exist_ok=True)
    record = {"config": dataclasses.asdict(cfg), "agents": rows, "penalties": summarise_penalties(rows)}
    (out / "tradeoff" / "tradeoff.json").write_text(json.dumps(record, indent=2))


def _trajectory_figure(agent, cfg: ExperimentConfig, spec: TrajectorySpec, out: Path, device: str) -> None:
    env = cfg.env.with_grid((spec.size, spec.holes))
    core = TrojanGridCore(env, 1, seed=spec.seed, device=device, phase="eval")
    runs = run_pair(
        core, core.layout(0), spec.trigger_step, lambda: AgentPolicy(agent, greedy=spec.greedy, seed=spec.seed)
    )
    for name, (frames, _) in runs.items():
        (out / f"trajectory_{name}.txt").write_text(frames_to_text(frames))
    title = f"Backdoored agent, {GridSpec(spec.size, spec.holes).label}: same layout without and with the trigger"
    plot_trajectory_pair(runs, title, out / "trajectory.png")
    outcomes = {name: outcome for name, (_, outcome) in runs.items()}
    save_json(TrajectoryResult(spec.trigger_step, outcomes), RunLayout(out).trajectory_file)


def machine_summary() -> dict[str, Any]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    from seqtrojan import __version__

    return {
        "seqtrojan": __version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cpu": cpu,
        "threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }
