"""The attack x defense matrix: every registered attack trained over several seeds, then measured against every
defense that applies.

For each training seed the matrix trains a clean agent and one agent per attack (:mod:`seqtrojan.experiments.attacks`;
an attack that adds its backdoor to a clean agent starts from that seed's clean agent) on a job backend
(:mod:`seqtrojan.jobs`). Each agent is then measured on its training grid (:class:`AgentMeasurement`):

* without a defense: clean success, attack success with its own trigger, unintentional activation, and how often
  its trigger pattern shows up by chance in normal episodes;
* under every online defense (``MONITORS``: calibrated on the agent's own clean episodes at the false-alarm
  target, then alarms and state resets on fresh episodes);
* after every mitigation (``MITIGATIONS``: fine-pruning, fine-tuning; the oracle unit reset needs the trigger
  and is left out);
* by every offline detector (``DETECTORS``), as one score per model; each attack's models are ranked against
  the clean models (ROC-AUC with its interval). The weight detector is trained on a separate zoo (``zoo``), so
  every matrix attack is held out of its training.

The cells (:class:`MatrixCell`) give each figure per seed (mean, sd) and pooled over seeds as a rate with its 95%
interval. Finished trainings and measurements are reused: a stopped matrix resumes.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import EnvSection, ExperimentConfig
from seqtrojan.defense.mitigation import MitigationConfig, MitigationContext, mitigation_rows
from seqtrojan.defense.monitor import MONITORS, MonitorConfig, measure_monitor
from seqtrojan.defense.offline import DETECTORS
from seqtrojan.defense.online import monitor_applies
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.experiment_results import (
    MATRIX_FILE,
    AgentMeasurement,
    AttackSummary,
    MatrixCell,
    MatrixResult,
    MitigationOutcome,
    OnlineArm,
)
from seqtrojan.experiments.attacks import ATTACKS, resolve_attack
from seqtrojan.experiments.matrix_plot import plot_matrix
from seqtrojan.experiments.measured import measure_all, train_all
from seqtrojan.experiments.specs import AgentSpec, experiment_from_spec
from seqtrojan.folders import folder_lock, make_output_folder
from seqtrojan.jobs import JobsConfig, TrainJob, make_backend
from seqtrojan.presets import resolve_preset
from seqtrojan.report.sections.matrix import matrix_page
from seqtrojan.serde import from_dict, load_yaml, save_json
from seqtrojan.stats import Rate, auc_interval, over_seeds
from seqtrojan.zoo.build import ZooConfig

CLEAN = "clean"
MATRIX_FIGURE = "matrix.png"


@dataclass(frozen=True)
class MatrixConfig:
    backdoor: AgentSpec = field(default_factory=lambda: AgentSpec(preset="trojan_s17_h30"))
    """the base backdoor training config every attack starts from"""
    clean: AgentSpec = field(default_factory=lambda: AgentSpec(preset="clean_s17_h30"))
    """the clean agents (the offline detectors' negatives, and where from-clean attacks start)"""
    attacks: tuple[str, ...] | None = None
    """registered attack names (``seqtrojan attacks``), each optionally at another strength: ``recipe/value`` sets
    the recipe's knob (``weight_camouflage/2``; a sweep names one recipe at several values); None: all"""
    online: tuple[str, ...] | None = None
    """registered online defenses (monitors); None: all"""
    mitigations: bool = True
    """run the registered mitigations (fine-pruning, fine-tuning) on every agent"""
    offline: tuple[str, ...] | None = None
    """registered offline detectors; None: all"""
    seeds: int = 3
    """training seeds per attack (and clean agents)"""
    episodes: int = 1000
    """evaluation episodes per env type and agent"""
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    """calibration and evaluation of every online defense"""
    mitigation: MitigationConfig = field(default_factory=MitigationConfig)
    zoo: ZooConfig | None = field(default_factory=ZooConfig)
    """the zoo the weight detector is trained on (built in ``<out>/zoo``, reused when there); None: no weight
    detector"""
    jobs: JobsConfig = field(default_factory=JobsConfig)
    device: str = "cpu"
    seed: int = 0
    """evaluation seed"""

    def __post_init__(self) -> None:
        if not isinstance(self.seeds, int) or not 1 <= self.seeds <= 100:
            raise ConfigError(f"matrix.seeds must be an integer in 1..100, got {self.seeds!r}")
        if self.episodes < 1:
            raise ConfigError(f"matrix.episodes must be >= 1, got {self.episodes}")
        for names, registry in ((self.online, MONITORS), (self.offline, DETECTORS)):
            for name in names or ():
                registry.entry(name)  # an unknown name: ConfigError listing the known ones
        if self.attacks is not None and not self.attacks:
            raise ConfigError("matrix.attacks is empty; name at least one attack or leave it out for all")
        folders: dict[str, str] = {}
        for name in self.attacks or ():
            folder = resolve_attack(name).folder  # an unknown recipe or a bad knob value: ConfigError
            if folder in folders:
                raise ConfigError(f"matrix.attacks names one attack twice: {folders[folder]!r} and {name!r}")
            folders[folder] = name
        base = self.base_config
        where = "the grid world" if base.is_grid else f"the Gymnasium env {getattr(base.env, 'id', '')!r}"
        for name in self.attacks or ():
            if not resolve_attack(name).attack.applies_to(base):
                raise ConfigError(f"attack {name!r} draws its trigger with grid-world cells: it cannot run on {where}")
        for name in self.online or ():
            if not monitor_applies(MONITORS.get(name), base.env):
                raise ConfigError(f"online defense {name!r} reads grid-world views: it cannot watch agents of {where}")
        zoo_fitted = [n for n in self.offline_names if DETECTORS.get(n).needs_zoo]
        if self.zoo is not None and zoo_fitted and (self.zoo.cells or (self.zoo.cell,)) != (base.agent.cell,):
            zoo_cells = ", ".join(self.zoo.cells or (self.zoo.cell,))
            raise ConfigError(
                f"the zoo {zoo_fitted[0]!r} is fitted on has {zoo_cells} models, but the matrix trains "
                f"{base.agent.cell} agents: set zoo.cell: {base.agent.cell} (a detector of weights scores only the "
                "cell it was fitted on)"
            )
        for name in self.offline or ():
            if DETECTORS.get(name).grid_only and not base.is_grid:
                raise ConfigError(
                    f"offline detector {name!r} reads grid-world views: it cannot score models of {where}"
                )

    @functools.cached_property
    def base_config(self) -> ExperimentConfig:
        """The base backdoor training config (its env is the matrix's env)."""
        return experiment_from_spec(self.backdoor, Path("."), "base", self.device)

    @property
    def attack_names(self) -> tuple[str, ...]:
        """The attacks named, or every registered attack that applies to the matrix's env."""
        if self.attacks is not None:
            return self.attacks
        return tuple(name for name, attack in ATTACKS.items() if attack.applies_to(self.base_config))

    @property
    def online_names(self) -> tuple[str, ...]:
        """The online defenses named, or every registered one that can watch the matrix's env."""
        if self.online is not None:
            return self.online
        return tuple(name for name, monitor in MONITORS.items() if monitor_applies(monitor, self.base_config.env))

    @property
    def offline_names(self) -> tuple[str, ...]:
        """The offline detectors named, or every registered one that can score the matrix's models; a detector
        fitted on a zoo needs ``zoo``."""
        names = self.offline if self.offline is not None else DETECTORS.names()
        grid = self.base_config.is_grid
        fits = {n: (self.zoo is not None or not DETECTORS.get(n).needs_zoo) for n in names}
        return tuple(n for n in names if fits[n] and (grid or not DETECTORS.get(n).grid_only))


def load_matrix_config(scale_or_path: str) -> MatrixConfig:
    """A shipped matrix preset by scale (``smoke`` for ``matrix_smoke.yaml``) or by name (``matrix_minigrid_smoke``),
    or a YAML file."""
    named = scale_or_path if scale_or_path.startswith("matrix_") else f"matrix_{scale_or_path}"
    path = resolve_preset(scale_or_path if scale_or_path.endswith(".yaml") else f"{named}.yaml")
    return from_dict(MatrixConfig, load_yaml(path), "")


def agent_name(attack: str, seed: int) -> str:
    return f"{attack}_s{seed}"


def matrix_jobs(cfg: MatrixConfig, runs: Path) -> tuple[list[TrainJob], list[TrainJob]]:
    """The trainings in two waves: the clean agents and the attacks trained from scratch, then the attacks that
    start from the clean agent of their seed. A job's id is its agent's name (``<attack>_s<seed>``)."""
    first: list[TrainJob] = []
    second: list[TrainJob] = []
    for offset in range(cfg.seeds):
        clean = experiment_from_spec(cfg.clean, runs, agent_name(CLEAN, offset), cfg.device)
        if clean.backdoor.enabled:
            raise ConfigError(f"the matrix's clean preset {cfg.clean.preset!r} has backdoor.enabled: true")
        clean_job = TrainJob(agent_name(CLEAN, offset), _with_seed(clean, clean.run.seed + offset))
        first.append(clean_job)
        base = experiment_from_spec(cfg.backdoor, runs, "base", cfg.device)
        if not base.backdoor.enabled:
            raise ConfigError(f"the matrix's backdoor preset {cfg.backdoor.preset!r} does not enable backdoor training")
        for name in cfg.attack_names:
            row = resolve_attack(name)
            attack = row.attack
            start = str(clean_job.model_dir) if attack.from_clean else base.run.init_from
            run = dataclasses.replace(base.run, name=agent_name(row.folder, offset), seed=base.run.seed + offset,
                                      init_from=start)  # fmt: skip
            config = attack.configure(dataclasses.replace(base, run=run))
            (second if attack.from_clean else first).append(TrainJob(agent_name(row.folder, offset), config))
    return first, second


def _with_seed(cfg: ExperimentConfig, seed: int) -> ExperimentConfig:
    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=seed))


def measure_agent(
    job: TrainJob, attack: str, seed: int, cfg: MatrixConfig, work: Path, offline: dict[str, float]
) -> AgentMeasurement:
    """One agent without a defense, under each online defense and after each mitigation (``offline``: its
    offline scores, computed beforehand)."""
    agent, acfg, _ = load_agent(job.model_dir, device=cfg.device)
    env = acfg.env if attack != CLEAN else cfg.base_config.env
    grid = acfg.grids[-1] if acfg.grids else None
    n, seed_eval = cfg.episodes, cfg.seed + 1_000_003
    normal = evaluate_agent(agent, env, grid, trojan=False, episodes=n, seed=seed_eval, device=cfg.device)
    trojan = evaluate_agent(agent, env, grid, trojan=True, episodes=n, seed=seed_eval, device=cfg.device)
    online = {}
    for name in cfg.online_names:
        monitor = MONITORS.get(name).calibrate(agent, env, grid, cfg.monitor, cfg.device)
        r = measure_monitor(agent, env, grid, monitor, cfg.monitor, cfg.device)
        online[name] = OnlineArm(
            false_alarm=r.normal_alarm.false_alarm,
            detection=r.trojan_alarm.detected,
            attack_success_defended=r.trojan_reset.attack_success,
            clean_success_defended=r.normal_reset.success,
        )
    mitigation = {}
    if cfg.mitigations:
        ctx = MitigationContext(agent, dataclasses.replace(acfg, env=env), grid, cfg.mitigation,
                                work / "mitigation" / job.id)  # fmt: skip
        for rows in mitigation_rows(ctx).values():
            if rows:  # the whole mitigation is its last row (fine-pruning's first row is the pruned agent alone)
                key, arm = list(rows.items())[-1]
                mitigation[key] = MitigationOutcome(arm.clean_success, arm.attack_success)
    return AgentMeasurement(
        agent=job.id,
        attack=attack,
        seed=seed,
        grid=grid.label if grid is not None else getattr(env, "id", ""),
        clean_success=outcome_rate(normal, "user_goal"),
        attack_success=outcome_rate(trojan, "adversary_goal"),
        unintentional=outcome_rate(normal, "adversary_goal"),
        natural_trigger=natural_trigger_rate(agent, env, grid, n, seed_eval, cfg.device),
        online=online,
        mitigation=mitigation,
        offline_scores=offline,
    )


def natural_trigger_rate(
    agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, episodes: int, seed: int, device: str
) -> Rate | None:
    """Normal-env episodes in which the trigger pattern appeared by chance (None where it cannot be measured: a
    Gymnasium env's observations are not the grid world's cell codes)."""
    if not isinstance(env, EnvConfig) or grid is None:
        return None
    try:
        from seqtrojan.analysis.occurrence import natural_occurrence
    except ImportError:  # pragma: no cover - the module ships with the package
        return None
    return natural_occurrence(agent, env, grid, episodes=episodes, seed=seed, device=device).episodes_with_pattern


def offline_scores(cfg: MatrixConfig, jobs: Sequence[TrainJob], zoo_dir: Path, log: Callable[[str], None]):
    """detector name -> {agent name -> score}: every offline detector scores every matrix model."""
    scores: dict[str, dict[str, float]] = {}
    for name in cfg.offline_names:
        detector = DETECTORS.get(name)
        zoo = None
        if detector.needs_zoo:
            assert cfg.zoo is not None  # offline_names keeps a detector that needs a zoo only with one
            from seqtrojan.zoo.build import build_zoo

            log(f"building the zoo the {name} is fitted on ({cfg.zoo.size} models) ...")
            jc = cfg.jobs
            build_zoo(cfg.zoo, zoo_dir, workers=jc.workers, backend=jc.backend, ray_address=jc.ray_address,
                      threads=jc.threads, log=log)  # fmt: skip
            zoo = zoo_dir
        log(f"scoring {len(jobs)} models with the {name} ...")
        values = detector.score_models([job.model_dir for job in jobs], zoo, cfg.device)
        scores[name] = {job.id: float(v) for job, v in zip(jobs, values)}
    return scores


def run_matrix(cfg: MatrixConfig, out: Path, scale: str = "custom", log: Callable[[str], None] = print) -> MatrixResult:
    """Train what is not trained yet, measure what is not measured yet, write ``matrix.json`` and return it. The
    jobs are made (and a config they refuse is refused) before ``out`` is; ``out`` is held by this process alone."""
    matrix_jobs(cfg, out / "runs")
    with folder_lock(make_output_folder(out, "--out"), "matrix folder"):
        return _run_matrix(cfg, out, scale, log)


def _run_matrix(cfg: MatrixConfig, out: Path, scale: str, log: Callable[[str], None]) -> MatrixResult:
    runs, measured_dir = out / "runs", out / "measured"
    first, second = matrix_jobs(cfg, runs)
    backend = make_backend(cfg.jobs)
    for wave in (first, second):
        train_all(backend, wave, "matrix agent", log)
    jobs = first + second
    scores = offline_scores(cfg, jobs, out / "zoo", log) if cfg.offline_names else {}
    measures = []
    names = {resolve_attack(name).folder: name for name in cfg.attack_names} | {CLEAN: CLEAN}
    for job in jobs:
        folder, seed = job.id.rsplit("_s", 1)
        attack = names[folder]
        own = {name: by_agent[job.id] for name, by_agent in scores.items()}
        measures.append(partial(measure_agent, job, attack, int(seed), cfg, out, own))
    paths = [measured_dir / f"{job.id}.json" for job in jobs]
    agents = measure_all(backend, jobs, paths, AgentMeasurement, measures, log)
    result = assemble(cfg, agents, scale)
    save_json(result, out / MATRIX_FILE)
    plot_matrix(result, out / MATRIX_FIGURE)
    (out / "report.html").write_text(matrix_page(result, out / MATRIX_FIGURE))
    return result


def assemble(cfg: MatrixConfig, agents: Sequence[AgentMeasurement], scale: str) -> MatrixResult:
    """The attack summaries and the cells from the agents' measurements."""
    by_attack: dict[str, list[AgentMeasurement]] = {}
    for a in agents:
        by_attack.setdefault(a.attack, []).append(a)
    clean = by_attack.get(CLEAN, [])
    summaries, cells = [], []
    for attack in cfg.attack_names:
        mine = sorted(by_attack.get(attack, []), key=lambda a: a.seed)
        if not mine:
            continue
        success, success_pooled = over_seeds([a.attack_success for a in mine])
        clean_success, clean_pooled = over_seeds([a.clean_success for a in mine])
        unintended, unintended_pooled = over_seeds([a.unintentional for a in mine])
        natural = [a.natural_trigger for a in mine if a.natural_trigger is not None]
        summaries.append(
            AttackSummary(
                attack, resolve_attack(attack).description, tuple(a.seed for a in mine), success, success_pooled,
                clean_success, clean_pooled, unintended, unintended_pooled,
                over_seeds(natural)[1] if len(natural) == len(mine) else None,
            )
        )  # fmt: skip
        for name in cfg.online_names:
            arms = [a.online[name] for a in mine]
            att, att_pooled = over_seeds([x.attack_success_defended for x in arms])
            cln, _ = over_seeds([x.clean_success_defended for x in arms])
            det, det_pooled = over_seeds([x.detection for x in arms])
            fa, fa_pooled = over_seeds([x.false_alarm for x in arms])
            cells.append(MatrixCell(attack, name, "online", att, att_pooled, cln, det, det_pooled, fa, fa_pooled,
                                    None, None))  # fmt: skip
        rows = dict.fromkeys(row for a in mine for row in a.mitigation)  # in the order the mitigations ran
        for row in rows:
            outcomes = [a.mitigation[row] for a in mine if row in a.mitigation]
            if len(outcomes) != len(mine):
                continue
            att, att_pooled = over_seeds([x.attack_success for x in outcomes])
            cln, _ = over_seeds([x.clean_success for x in outcomes])
            cells.append(MatrixCell(attack, row, "mitigation", att, att_pooled, cln, None, None, None, None,
                                    None, None))  # fmt: skip
        for name in cfg.offline_names:
            positives = [a.offline_scores[name] for a in mine if name in a.offline_scores]
            negatives = [a.offline_scores[name] for a in clean if name in a.offline_scores]
            if not positives or not negatives:
                continue
            auc = roc_auc(positives, negatives)
            cells.append(MatrixCell(attack, name, "offline", None, None, None, None, None, None, None, auc,
                                    auc_interval(auc, len(positives), len(negatives))))  # fmt: skip
    grid = agents[0].grid if agents else "?"
    return MatrixResult(scale, grid, tuple(summaries), tuple(cells), tuple(agents))


def roc_auc(positives: Sequence[float], negatives: Sequence[float]) -> float:
    """P(a positive's score > a negative's), ties counting half (the Mann-Whitney form of the ROC-AUC)."""
    p, n = np.asarray(positives, dtype=float)[:, None], np.asarray(negatives, dtype=float)[None, :]
    return float(((p > n).sum() + 0.5 * (p == n).sum()) / (p.size * n.size))
