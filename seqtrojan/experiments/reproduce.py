"""The paper's results end to end: train a clean and a backdoored agent, evaluate them over the paper's configs,
learning curves, the trajectory figure, the analysis of their internal states (response types, interventions,
unintentional triggers, searches), and a self-contained HTML report beside the paper's numbers.

    seqtrojan reproduce --scale smoke      # minutes on 2 cores: the main job (make reproduce)
    seqtrojan reproduce --scale paper      # the paper's setting (17x17/30 agents, 1000 trials, 10 seeds)

:func:`reproduce` is a list of stages (:func:`reproduce_stages`: training (headline agents, curves, trade-off in one
queue), evaluation, curves, trajectory, analysis, defense, trade-off, zoo, report; a section set to None in the
config is not in the list) run by :func:`seqtrojan.experiments.stages.run_stages`. Each stage writes its outputs
under ``--out`` at the paths of :class:`seqtrojan.artifacts.RunLayout` and is skipped when they exist, so a stopped
reproduction continues where it stopped (training runs resume from their last checkpoint).
"""

from __future__ import annotations

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
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.analysis.pipeline import AnalysisConfig, run_analysis
from seqtrojan.artifacts import HEADLINE_ROLES, RunLayout, TrajectoryResult
from seqtrojan.config import ExperimentConfig
from seqtrojan.defense.offline import detect_zoo
from seqtrojan.defense.pipeline import DefenseConfig, run_defense
from seqtrojan.env.config import GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.results import save_rows
from seqtrojan.evaluation.seeds import summarise_over_seeds
from seqtrojan.evaluation.sweep import SweepRow, evaluate_sweep, load_sweep, parse_configs, write_sweep
from seqtrojan.experiment_results import TradeoffResult
from seqtrojan.experiments.cells import CellsConfig, run_cells
from seqtrojan.experiments.curves import CurvesConfig, aggregate_curves, curve_jobs, plot_curves, run_curves
from seqtrojan.experiments.specs import AgentSpec, experiment_from_spec
from seqtrojan.experiments.stages import Stage, StageContext, run_stages
from seqtrojan.experiments.tradeoff import TradeoffConfig, measure_tradeoff_agent, summarise_penalties, tradeoff_agents
from seqtrojan.experiments.tradeoff import settings as tradeoff_settings
from seqtrojan.folders import folder_lock, make_output_folder
from seqtrojan.jobs import JobBackend, JobResult, JobsConfig, TrainJob, make_backend, raise_failures
from seqtrojan.presets import resolve_preset
from seqtrojan.report.figures import frames_to_text, plot_trajectory_pair, run_pair
from seqtrojan.report.html import build_report
from seqtrojan.serde import from_dict, load_yaml, save_json, to_dict
from seqtrojan.timings import Timings
from seqtrojan.train.trainer import load_run_config
from seqtrojan.zoo.build import ZooConfig, build_zoo


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
    cells: CellsConfig | None = None
    """the sequence-model comparison (LSTM, peephole LSTM, GRU, Transformer; :mod:`seqtrojan.experiments.cells`),
    trained on this reproduction's job backend; None skips it"""
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


def load_reproduce_config(scale_or_path: str) -> ReproduceConfig:
    path = resolve_preset(scale_or_path if scale_or_path.endswith(".yaml") else f"reproduce_{scale_or_path}.yaml")
    return from_dict(ReproduceConfig, load_yaml(path), "")


@dataclass(frozen=True)
class ReproduceContext(StageContext):
    """A reproduction's stages run with its config, the scale's name (for the report) and when the call started."""

    config: ReproduceConfig
    scale: str
    start: float

    def models(self, offset: int = 0) -> dict[str, Path]:
        """role -> the model folder of training seed ``offset``'s headline agent (seed 0 feeds every later stage)."""
        return {role: self.layout.model(headline_run_name(role, offset)) for role in HEADLINE_ROLES}

    def backend(self) -> JobBackend:
        return make_backend(self.config.jobs)


def reproduce(config: ReproduceConfig, out: Path, scale: str = "custom", log=print) -> Path:
    """Run every stage not yet done; return the report's path. The headline jobs are made (and a config they refuse
    is refused) before ``out`` is; ``out`` is held by this process alone."""
    layout = RunLayout(out)
    headline_jobs(config, layout)
    with folder_lock(make_output_folder(out, "--out"), "reproduction folder"):
        return _reproduce(config, layout, scale, log)


def _reproduce(config: ReproduceConfig, layout: RunLayout, scale: str, log) -> Path:
    layout.config.write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    context = ReproduceContext(layout, log, Timings(layout.timings), config, scale, time.perf_counter())
    run_stages(reproduce_stages(config), context)
    log(f"report: {layout.report}")
    return layout.report


def reproduce_stages(config: ReproduceConfig) -> list[Stage[ReproduceContext]]:
    """The reproduction's stages in order; a stage set to None in the config is not in the list."""
    optional: list[tuple[object, Stage[ReproduceContext]]] = [
        (config.curves, CurvesStage()),
        (config.trajectory, TrajectoryStage()),
        (config.analysis, AnalysisStage()),
        (config.defense, DefenseStage()),
        (config.tradeoff, TradeoffStage()),
        (config.zoo, ZooStage()),
        (config.cells, CellsStage()),
    ]
    return [
        TrainingQueue(config),
        EvaluationStage(config),
        *(stage for section, stage in optional if section is not None),
        ReportStage(),
    ]


def headline_run_name(role: str, offset: int) -> str:
    """Run folder of a headline agent: ``clean``/``backdoor`` for the first seed, ``<role>_seed<k>`` after."""
    return role if offset == 0 else f"{role}_seed{offset}"


def headline_jobs(config: ReproduceConfig, layout: RunLayout) -> list[TrainJob]:
    """The clean and backdoored agent of every training seed (seed by seed, clean first), as jobs."""
    jobs: list[TrainJob] = []
    for offset in range(config.seeds):
        for role, spec in (("clean", config.clean), ("backdoor", config.backdoor)):
            name = headline_run_name(role, offset)
            cfg = experiment_from_spec(spec, layout.runs, name, config.device)
            if role == "clean" and cfg.backdoor.enabled:
                raise ConfigError(f"the clean preset {spec.preset!r} has backdoor.enabled: true")
            if role == "backdoor" and not cfg.backdoor.enabled:
                raise ConfigError(f"the backdoor preset {spec.preset!r} does not enable backdoor training")
            jobs.append(
                TrainJob(name, dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=cfg.run.seed + offset)))
            )
    return jobs


def queued_jobs(config: ReproduceConfig, layout: RunLayout) -> list[TrainJob]:
    """Every training job known before any agent exists (the headline agents, the learning curves' runs, the
    trade-off's agents), longest first: run on one backend, no worker waits at the end of a stage for the last
    job of that stage while jobs of the next are pending, and the shortest jobs fill the end. The zoo builds its
    own models (its manifest records them)."""
    jobs = headline_jobs(config, layout)
    base = next(job.config for job in jobs if job.id == headline_run_name("backdoor", 0))
    if config.curves is not None:
        jobs += curve_jobs(base, config.curves, layout.curves_dir)
    if config.tradeoff is not None:
        agents = tradeoff_agents(base, config.tradeoff, layout.runs, trained_seeds=config.seeds)
        jobs += [a.job for a in agents if a.job is not None]
    return sorted(jobs, key=lambda job: (-job.config.ppo.total_steps, not job.config.backdoor.enabled))


@dataclass(frozen=True)
class TrainingQueue:
    """Every job of :func:`queued_jobs` on the job backend in one queue (each job's training time is recorded as
    ``train_<id>``); the stages that use them then find them finished."""

    config: ReproduceConfig
    name: str = "training"

    def done(self, layout: RunLayout) -> bool:
        return all(job.done() for job in queued_jobs(self.config, layout))

    def run(self, context: ReproduceContext) -> None:
        jobs = queued_jobs(self.config, context.layout)
        backend = context.backend()
        todo = [job for job in jobs if not job.done()]
        steps = sum(job.config.ppo.total_steps for job in todo)
        where = f"the {backend.name} backend ({backend.describe(len(todo))})"
        context.log(f"training {len(todo)} agent(s) (headline, learning curves, trade-off; {steps:,} env steps at "
                    f"most) on {where}, longest first ...")  # fmt: skip
        raise_failures(backend.run(todo, _job_log(context.log, context.timings)), "training job")


@dataclass(frozen=True)
class EvaluationStage:
    """Each seed's pair over the configs (one file per seed, so a stopped stage resumes, timed as
    ``evaluation_seed<k>``), then every row in evaluation.json/.csv and the per-cell summary over seeds in
    summary.json. Done when evaluation.json holds exactly the config's seeds and the summary exists."""

    config: ReproduceConfig
    name: str = "evaluation"

    def done(self, layout: RunLayout) -> bool:
        if not (layout.evaluation_file.exists() and layout.evaluation_summary.exists()):
            return False
        return {row.seed for row in layout.evaluation()} == set(range(self.config.seeds))

    def run(self, context: ReproduceContext) -> None:
        ev, layout = self.config.evaluation, context.layout
        configs = parse_configs(ev.configs)
        layout.evaluation_dir.mkdir(parents=True, exist_ok=True)
        rows: list[SweepRow] = []
        for offset in range(self.config.seeds):
            seed_file = layout.evaluation_seed_file(offset)
            if not seed_file.exists():
                context.log(f"evaluating training seed {offset} over the grid configs ...")
                t0 = time.perf_counter()
                agents = _load_agents(context.models(offset), self.config.device)
                last = agents[-1][2].grids[-1]
                cells = configs if (last.size, last.holes) in configs else [*configs, (last.size, last.holes)]
                seed_rows = evaluate_sweep(
                    agents, cells, episodes=ev.episodes, seed=ev.seed, greedy=ev.greedy, device=self.config.device,
                    training_seed=offset,
                )  # fmt: skip
                save_rows(seed_rows, seed_file)
                context.timings.record(f"evaluation_seed{offset}", time.perf_counter() - t0)
            rows += load_sweep(seed_file)
        write_sweep(rows, layout.evaluation_dir)
        summaries = [s.to_dict() for s in summarise_over_seeds(rows)]
        layout.evaluation_summary.write_text(json.dumps(summaries, indent=2))


@dataclass(frozen=True)
class CurvesStage:
    """Learning curves: backdoor training on each curve grid alone, aggregated over seeds, with their figure."""

    name: str = "curves"

    def done(self, layout: RunLayout) -> bool:
        return layout.curves_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg, layout = context.config.curves, context.layout
        assert cfg is not None  # in the list only when the config has a curves section
        context.log("learning curves ...")
        base = load_run_config(layout.run("backdoor"))
        csv_path = run_curves(base, cfg, layout.curves_dir, context.backend(), _job_log(context.log))
        curves = aggregate_curves(csv_path, cfg.points)
        plot_curves(curves, layout.curves_figure)
        save_json(curves, layout.curves_file)


@dataclass(frozen=True)
class TrajectoryStage:
    """The backdoored agent on one layout without and with the trigger: frames, outcomes and the figure."""

    name: str = "trajectory"

    def done(self, layout: RunLayout) -> bool:
        return layout.trajectory_figure.exists()

    def run(self, context: ReproduceContext) -> None:
        spec, device, layout = context.config.trajectory, context.config.device, context.layout
        assert spec is not None  # in the list only when the config has a trajectory section
        context.log("trajectory figure ...")
        agent, cfg, _ = load_agent(context.models()["backdoor"], device=device)
        env = cfg.grid_env.with_grid((spec.size, spec.holes))
        core = TrojanGridCore(env, 1, seed=spec.seed, device=device, phase="eval")
        runs = run_pair(
            core, core.layout(0), spec.trigger_step, lambda: AgentPolicy(agent, greedy=spec.greedy, seed=spec.seed)
        )
        for name, (frames, _) in runs.items():
            layout.trajectory_frames(name).write_text(frames_to_text(frames))
        title = f"Backdoored agent, {GridSpec(spec.size, spec.holes).label}: same layout without and with the trigger"
        plot_trajectory_pair(runs, title, layout.trajectory_figure)
        outcomes = {name: outcome for name, (_, outcome) in runs.items()}
        save_json(TrajectoryResult(spec.trigger_step, outcomes), layout.trajectory_file)


@dataclass(frozen=True)
class AnalysisStage:
    """Looking inside the seed-0 agents (:func:`seqtrojan.analysis.pipeline.run_analysis`)."""

    name: str = "analysis"

    def done(self, layout: RunLayout) -> bool:
        return layout.analysis_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg = context.config.analysis
        assert cfg is not None  # in the list only when the config has an analysis section
        context.log("looking inside the agents ...")
        models = context.models()
        run_analysis(
            models["clean"], models["backdoor"], context.layout.analysis_dir, cfg, context.config.device, context.log
        )


@dataclass(frozen=True)
class DefenseStage:
    """Monitor and mitigation of the seed-0 backdoored agent (:func:`seqtrojan.defense.pipeline.run_defense`)."""

    name: str = "defense"

    def done(self, layout: RunLayout) -> bool:
        return layout.defense_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg = context.config.defense
        assert cfg is not None  # in the list only when the config has a defense section
        context.log("defending the backdoored agent ...")
        run_defense(context.models()["backdoor"], context.layout.defense_dir, cfg, context.config.device, context.log)


@dataclass(frozen=True)
class TradeoffStage:
    """The adversary's trade-off: agents trained with each penalty on unintentional activation (the base penalty's
    seed k is the headline backdoored agent of training seed k, for every seed the headline has), each measured
    (timed as ``tradeoff_measure<penalty>_seed<k>``)."""

    name: str = "tradeoff"

    def done(self, layout: RunLayout) -> bool:
        return layout.tradeoff_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg, layout, log = context.config.tradeoff, context.layout, context.log
        assert cfg is not None  # in the list only when the config has a trade-off section
        backend = context.backend()
        base = load_run_config(layout.run("backdoor"))
        # the base penalty's seed-k agent is the headline backdoored agent of training seed k (same config)
        agents = tradeoff_agents(base, cfg, layout.runs, trained_seeds=context.config.seeds)
        jobs = [a.job for a in agents if a.job is not None]
        todo = sum(not job.done() for job in jobs)
        if todo:
            log(f"training {todo} trade-off agent(s) on the {backend.name} backend ({backend.describe(todo)}) ...")
        raise_failures(backend.run(jobs, _job_log(log, context.timings)), "trade-off agent")
        measured = []
        for a in agents:
            model = context.models(a.seed_offset)["backdoor"] if a.job is None else a.job.model_dir
            seed = a.config.run.seed
            log(f"measuring the trade-off for false_activation={a.penalty:g}, seed {seed} ...")
            t0 = time.perf_counter()
            agent, _, _ = load_agent(model, device=context.config.device)
            measured.append(measure_tradeoff_agent(agent, a.config, cfg, a.penalty, str(model.relative_to(layout.out))))
            context.timings.record(f"tradeoff_measure{a.penalty:g}_seed{seed}", time.perf_counter() - t0)
        layout.tradeoff_dir.mkdir(exist_ok=True)
        result = TradeoffResult(tradeoff_settings(cfg), tuple(measured), summarise_penalties(measured))
        save_json(result, layout.tradeoff_file)


@dataclass(frozen=True)
class ZooStage:
    """A zoo of clean and backdoored models (its build reuses finished models) and offline detection over it."""

    name: str = "zoo"

    def done(self, layout: RunLayout) -> bool:
        return layout.detection_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg, jobs, layout = context.config.zoo, context.config.jobs, context.layout
        assert cfg is not None  # in the list only when the config has a zoo section
        context.log(f"building a zoo of {cfg.size} models and scoring offline detection ...")
        build_zoo(cfg, layout.zoo_dir, workers=jobs.workers, backend=jobs.backend, ray_address=jobs.ray_address,
                  threads=jobs.threads, log=context.log)  # fmt: skip
        save_json(detect_zoo(layout.zoo_dir), layout.detection_file)


@dataclass(frozen=True)
class CellsStage:
    """The sequence-model comparison (its own trainings and measurements resume; see ``seqtrojan cells``)."""

    name: str = "cells"

    def done(self, layout: RunLayout) -> bool:
        return layout.cells_file.exists()

    def run(self, context: ReproduceContext) -> None:
        cfg = context.config.cells
        assert cfg is not None  # in the list only when the config has a cells section
        cfg = dataclasses.replace(cfg, jobs=context.config.jobs, device=context.config.device)
        run_cells(cfg, context.layout.cells_dir, scale=context.scale, log=context.log)


@dataclass(frozen=True)
class ReportStage:
    """report.html from every stage's outputs; never done, so that each call rebuilds it from what exists (it
    records ``last_call_before_report``, the call's seconds before the report)."""

    name: str = "report"

    def done(self, layout: RunLayout) -> bool:
        return False

    def run(self, context: ReproduceContext) -> None:
        context.timings.record("last_call_before_report", time.perf_counter() - context.start)
        build_report(context.layout.out, scale=context.scale, machine=machine_summary())


def _load_agents(models: dict[str, Path], device: str) -> list[tuple[str, RecurrentActorCritic, ExperimentConfig]]:
    agents = []
    for role, folder in models.items():
        agent, cfg, _ = load_agent(folder, device=device)
        agents.append((role, agent, cfg))
    return agents


def _job_log(log, timings: Timings | None = None):
    """A job backend's ``on_result``: log each job trained or failed (and record its training time in
    ``timings``)."""

    def on_result(result: JobResult) -> None:
        if not result.ok:
            log(f"  {result.id} failed: {result.error}")
        elif result.trained:
            log(f"  {result.id} trained in {result.seconds:.0f} s")
            if timings is not None:
                timings.record(f"train_{result.id}", result.seconds)

    return on_result


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
