"""The ``seqtrojan`` command: one subcommand per stage, each parsed by tyro from a typed dataclass.

seqtrojan demo --out outputs/demo
seqtrojan <command> --help

No ``from __future__ import annotations`` here: tyro reads the annotations of the argument dataclasses that some
commands define after a local (lazy) import, and string annotations could not be resolved from there.
"""

import contextlib
import dataclasses
import difflib
import errno
import sys
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import tyro

from seqtrojan.errors import ConfigError, SeqTrojanError

if TYPE_CHECKING:
    from seqtrojan.experiments.cells import CellsConfig
    from seqtrojan.experiments.matrix import MatrixConfig


T = TypeVar("T")


def _cli(cls: type[T], argv: list[str], prog: str, **kwargs: Any) -> T:
    """``tyro.cli(cls)`` whose refusals are one line: a misspelt option is named, with the closest known option (tyro's
    own suggestion engine fails on some config types), and a config value refused while the parsed options are
    built raises its own :class:`SeqTrojanError`, which :func:`main` prints as one line."""
    with _one_line_parse_errors(cls):
        return tyro.cli(cls, args=argv, prog=prog, **kwargs)


@contextlib.contextmanager
def _one_line_parse_errors(cls: type) -> Iterator[None]:
    errors = getattr(tyro, "_errors", None)  # tyro's parse-error hook (private; without it, tyro's own messages)
    if errors is None or not hasattr(errors, "on_parse_error"):
        yield
        return

    def hook(event: Any) -> None:
        if isinstance(event, errors.UnrecognizedArgs):
            raise ConfigError(_unrecognized(event.tokens, cls))
        if isinstance(event, errors.InstantiationFailure):
            err = sys.exc_info()[1]
            while err is not None and not isinstance(err, SeqTrojanError):
                err = err.__cause__ or err.__context__
            if err is not None:
                raise err

    with errors.on_parse_error(hook):
        yield


def _unrecognized(tokens: list[str], cls: type) -> str:
    """``unrecognized option --x (did you mean --y?)`` for the first token that looks like an option."""
    options = [t for t in tokens if t.startswith("-")] or tokens
    flag = options[0].split("=", 1)[0] if options else "?"
    close = difflib.get_close_matches(flag, sorted(_flags(cls)), n=1, cutoff=0.6)
    also = f" (and {len(options) - 1} more)" if len(options) > 1 else ""
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unrecognized option {flag}{also}{hint} (--help lists the options)"


def _flags(cls: Any, prefix: str = "") -> Iterator[str]:
    """The option names tyro makes of the dataclass ``cls``'s fields (nested dataclasses as ``--a.b``, booleans also
    as ``--no-...``), for suggestions."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # an unresolvable annotation: no suggestions from this class
        return
    for f in dataclasses.fields(cls):
        name = f.name.rstrip("_").replace("_", "-")
        members = typing.get_args(hints[f.name]) if _is_union(hints[f.name]) else (hints[f.name],)
        nested = [m for m in members if dataclasses.is_dataclass(m)]
        for member in nested:
            yield from _flags(member, f"{prefix}{name}.")
        if not nested:
            yield f"--{prefix}{name}"
        if hints[f.name] is bool:
            yield f"--{prefix}no-{name}"


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType)


def _pop_option(argv: list[str], name: str) -> tuple[str | None, list[str]]:
    """Remove ``--name VALUE`` or ``--name=VALUE`` from argv."""
    rest, value, i = [], None, 0
    while i < len(argv):
        arg = argv[i]
        if arg == name:
            if i + 1 >= len(argv):
                raise ConfigError(f"{name} needs a value")
            value, i = argv[i + 1], i + 2
            continue
        if arg.startswith(name + "="):
            value = arg.split("=", 1)[1]
        else:
            rest.append(arg)
        i += 1
    return value, rest


def _cli_with_config_file(args_cls: type, config_cls: type, argv: list[str], prog: str):
    """Parse ``args_cls`` (whose ``config`` field is a ``config_cls``) with tyro; ``--config-file FILE.yaml`` or
    ``--config PRESET|FILE`` (a shipped preset's name, e.g. benchmark_tiny) sets that config's starting values (the
    layout of the matching section of configs/reproduce_*.yaml), and ``--config.*`` flags override them."""
    from seqtrojan.presets import resolve_preset

    path, argv = _pop_option(argv, "--config-file")
    preset, argv = _pop_option(argv, "--config")
    if path is not None and preset is not None:
        raise ConfigError(f"{prog} takes --config PRESET or --config-file FILE, not both")
    if preset is not None:
        path = str(resolve_preset(preset))
    if path is None:
        return _cli(args_cls, argv, prog)
    from seqtrojan.serde import from_dict, load_yaml

    config: Any = from_dict(config_cls, load_yaml(Path(path)), "")
    required = {f.name: tyro.MISSING for f in dataclasses.fields(args_cls) if f.name != "config"
                and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}  # fmt: skip
    return _cli(args_cls, argv, prog, default=args_cls(config=config, **required))


NOT_TRAINING_PRESETS = ("reproduce_", "matrix_", "cells_", "benchmark_")
"""shipped presets that are not training configs (reproduction scales, matrix and cells scales, benchmark zoos)"""


def parse_experiment(argv: list[str], prog: str, description: str):
    """An ExperimentConfig from ``--config PRESET`` (a shipped preset's name or a YAML file) or ``--resume RUN_DIR``
    (the run's saved config), plus dotted overrides. The two are read first, as they set the starting values that
    the other options override, and parsed again with the rest so that ``--help`` lists them."""
    from typing import Annotated

    from seqtrojan.config import ExperimentConfig
    from seqtrojan.presets import list_presets, resolve_preset
    from seqtrojan.serde import from_dict, load_yaml

    preset, rest = _pop_option(argv, "--config")
    resume, _ = _pop_option(rest, "--resume")
    if preset is not None and resume is not None:
        raise ConfigError(f"{prog} takes --config PRESET|FILE or --resume RUN_DIR, not both")
    if resume is not None:
        from seqtrojan.train.trainer import load_run_config

        base = load_run_config(resume)
    elif preset is not None:
        base = from_dict(ExperimentConfig, load_yaml(resolve_preset(preset)), "")
    else:
        base = ExperimentConfig()

    names = ", ".join(n for n in list_presets() if not n.startswith(NOT_TRAINING_PRESETS))
    config_help = f"a preset's name ({names}) or a YAML file; the options below override it"
    resume_help = "continue the stopped run in this folder from its last checkpoint, with its saved config"

    env_type: Any = type(base.env)  # the env section's own fields as options (--env.size, or --env.id ...)

    @dataclasses.dataclass(frozen=True)
    class TrainArgs(ExperimentConfig):  # the config's fields (--env.size, ...) plus the two options
        env: env_type = dataclasses.field(default_factory=type(ExperimentConfig().env))
        config: Annotated[str | None, tyro.conf.arg(help=config_help, metavar="PRESET|FILE")] = None
        resume: Annotated[str | None, tyro.conf.arg(help=resume_help, metavar="RUN_DIR")] = None

    fields = [f.name for f in dataclasses.fields(ExperimentConfig)]
    default = TrainArgs(**{name: getattr(base, name) for name in fields}, config=preset, resume=resume)
    args = _cli(TrainArgs, argv, prog, default=default, description=description)
    return ExperimentConfig(**{name: getattr(args, name) for name in fields}), args.resume


def _train(argv: list[str]) -> None:
    from seqtrojan.train.trainer import train

    description = (
        "Train a recurrent PPO agent on the grid world or a Gymnasium env (env.kind: gymnasium: MiniGrid tasks, your "
        "own env). --config PRESET loads a shipped preset by name (or a YAML file); --resume RUN_DIR continues a "
        "stopped run from its last checkpoint with its saved config (a Gymnasium env's episodes in flight too); "
        "every other option overrides. SIGTERM or Ctrl-C stops between updates and writes a checkpoint."
    )
    cfg, resume = parse_experiment(argv, "seqtrojan train", description)
    result = train(cfg, resume=resume)
    ev = result.evaluation
    print(f"run: {result.run_dir}\nmodel: {result.model_dir}")
    if result.exact_resume is not None:
        print("resumed " + ("replaying the episodes in flight" if result.exact_resume else "with fresh episodes"))
    print(f"env steps: {result.env_steps:,}  wall: {result.wall_seconds / 60:.1f} min  final stage: {result.stage}")
    where = ev.get("grid", ev.get("env", ""))
    for kind in ("normal", "trojan"):
        if f"{kind}_success" in ev:
            lo, hi = ev[f"{kind}_success_ci95"]
            print(
                f"success on {where} ({kind} env, {ev['episodes']} episodes): {ev[f'{kind}_success']:.3f} "
                f"[{lo:.3f}, {hi:.3f}], greedy {ev[f'greedy_{kind}_success']:.3f}"
                + (f"; mean return {ev[f'{kind}_return']:.3f}" if f"{kind}_return" in ev else "")
            )


@dataclasses.dataclass
class EvaluateArgs:
    """Success rates of trained models, with 95% intervals. A grid-world model is evaluated over grid configs
    (default: the paper's 14) beside the paper's numbers; a model of a Gymnasium env on that env: clean success,
    trojan success and the trojan's persistence. A model stated clean is evaluated in the normal env only; a
    backdoored one, one of unknown lineage (an imported suspect) and a Gymnasium model whose env has a trigger in
    the normal and the trojan env."""

    models: tuple[Path, ...]
    """model folders (each with model.safetensors and card.json; an earlier version's gym_card.json also loads)"""
    configs: str = "paper"
    """grid-world models: 'paper' (Tables 1 and 2) or a list like '7x7/0,11x11/11,17x17/30'"""
    episodes: int = 1000
    """trials per (model, env, config); a grid world's run as one batch"""
    out: Path = Path("results/evaluate")
    """folder for evaluation.json and evaluation.csv (grid world) and <model>/env_evaluation.json (Gymnasium)"""
    seed: int = 0
    greedy: bool = False
    """take the most likely action instead of sampling"""
    horizons: tuple[int, ...] = (0, 5, 10)
    """Gymnasium models: persistence horizons, steps after the trigger's first step"""
    device: str = "cpu"


def _evaluate(argv: list[str]) -> None:
    from rich.console import Console

    from seqtrojan.agent.checkpoint import load_agent
    from seqtrojan.evaluation.sweep import evaluate_sweep, parse_configs, write_sweep
    from seqtrojan.evaluation.tables import sweep_table

    args = _cli(EvaluateArgs, argv, "seqtrojan evaluate")
    if args.episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {args.episodes}")
    grid_agents: list[tuple[str, Path, Any, Any, dict]] = []
    gym_agents: list[tuple[str, Path, Any, Any, dict]] = []
    for folder in args.models:
        agent, cfg, card = load_agent(folder, device=args.device)
        name = folder.parent.name if folder.name == "model" else folder.name
        (grid_agents if cfg.is_grid else gym_agents).append((name, folder, agent, cfg, card))
    if grid_agents:
        rows = evaluate_sweep(
            [(name, agent, cfg) for name, _, agent, cfg, _ in grid_agents], parse_configs(args.configs),
            episodes=args.episodes, seed=args.seed, greedy=args.greedy, device=args.device,
            labels=[card["label"] for *_, card in grid_agents],
        )  # fmt: skip
        Console().print(sweep_table(rows))
        paths = write_sweep(rows, args.out)
        print("wrote " + ", ".join(str(p) for p in paths))
    for name, folder, agent, cfg, card in gym_agents:
        _evaluate_on_its_env(args, name, folder, agent, cfg, card)


def _evaluate_on_its_env(args: EvaluateArgs, name: str, folder: Path, agent: Any, cfg: Any, card: dict) -> None:
    from seqtrojan.evaluation.env_report import ENV_EVALUATION_FILE, evaluate_model
    from seqtrojan.serde import save_json

    report = evaluate_model(
        agent, cfg, model=str(folder), label=str(card.get("label", "")), episodes=args.episodes, seed=args.seed,
        greedy=args.greedy, horizons=args.horizons, device=args.device,
    )  # fmt: skip
    print(f"model: {folder} ({report.label}, {report.env_id}), {args.episodes} episodes per type")
    print(f"clean success:  {report.clean_success.text()}")
    if report.clean_return is not None:
        print(f"clean mean return: {report.clean_return.text()}")
    if report.trojan_success is not None and report.trojan_reached_adversary is not None:
        print(f"trojan success: {report.trojan_success.text()}")
        if report.trojan_env_return is not None:
            print(f"trojan episodes' mean return under the env's own reward: {report.trojan_env_return.text()}")
        if report.target_action is not None:
            clean = report.clean_target_share.text() if report.clean_target_share is not None else "none"
            shown = report.target_share.text() if report.target_share is not None else "none"
            print(f"target action {report.target_action} after the trigger: {shown} (normal episodes: {clean})")
            for p in report.action_persistence:
                print(f"  action persistence k={p.horizon}: {p.adversary.text()} (n = {p.adversary.n})")
        else:
            print(f"trojan episodes at the adversary's object: {report.trojan_reached_adversary.text()}")
            for p in report.persistence:
                print(f"  persistence k={p.horizon}: {p.adversary.text()} (n = {p.adversary.n})")
    else:
        print("trojan episodes: none (the env has no trigger)")
    (args.out / name).mkdir(parents=True, exist_ok=True)
    print(f"wrote {save_json(report, args.out / name / ENV_EVALUATION_FILE)}")


@dataclasses.dataclass
class ReproduceArgs:
    """Train, evaluate, plot and report the paper's results end to end (resumable: finished stages are kept)."""

    scale: str = "smoke"
    """a shipped scale's name ('smoke': minutes, 'paper': the paper's setting; see seqtrojan/presets/reproduce_*.yaml)
    or a reproduce YAML file"""
    out: Path | None = None
    """output folder (default: results/<scale>)"""
    device: str | None = None
    """torch device (default: the scale file's, cpu)"""
    backend: Literal["serial", "pool", "ray"] | None = None
    """job backend of the stages that train many agents (curves, trade-off, zoo): serial, pool (local worker
    processes) or ray (default: the scale file's jobs.backend, pool)"""
    workers: int | None = None
    """trainings at once on the pool or a local Ray instance (default: the scale file's jobs.workers, 2)"""
    ray_address: str | None = None
    """the Ray cluster to run on, e.g. 10.0.0.5:6379 (default: the scale file's; none: a local Ray instance)"""
    threads: int | None = None
    """torch threads per training (default: the cores shared out among the workers)"""


def _reproduce(argv: list[str]) -> None:
    from seqtrojan.experiments.reproduce import load_reproduce_config, reproduce

    args = _cli(ReproduceArgs, argv, "seqtrojan reproduce")
    config = load_reproduce_config(args.scale)
    if args.device is not None:
        config = dataclasses.replace(config, device=args.device)
    chosen: dict[str, Any] = {"backend": args.backend, "workers": args.workers, "ray_address": args.ray_address,
                              "threads": args.threads}  # fmt: skip
    jobs = dataclasses.replace(config.jobs, **{k: v for k, v in chosen.items() if v is not None})
    config = dataclasses.replace(config, jobs=jobs)
    scale = Path(args.scale).stem.removeprefix("reproduce_")
    reproduce(config, args.out or Path("results") / scale, scale=scale)


@dataclasses.dataclass
class StudyArgs:
    """The options of the studies that train many agents (matrix, cells)."""

    seeds: int | None = None
    """training seeds (default: the scale file's)"""
    device: str | None = None
    """torch device of the trainings and measurements: cpu, cuda, cuda:1 (default: the scale file's, cpu)"""
    backend: Literal["serial", "pool", "ray"] | None = None
    """job backend of the trainings (default: the scale file's jobs.backend, pool)"""
    workers: int | None = None
    """jobs run at once by the pool or a local Ray instance (default: the scale file's jobs.workers)"""
    ray_address: str | None = None
    """the Ray cluster to run on with --backend ray, e.g. 10.0.0.5:6379 or 'auto' (default: a local Ray instance)"""
    threads: int | None = None
    """torch threads per job (default: the scale file's jobs.threads, or the cores shared out among the workers)"""


@dataclasses.dataclass
class MatrixArgs(StudyArgs):
    """Train every attack over several seeds and measure it against every defense (resumable: finished trainings and
    measurements are kept). Writes matrix.json, matrix.png and report.html."""

    scale: str = "smoke"
    """a shipped scale ('smoke': minutes; 'paper'; see seqtrojan/presets/matrix_*.yaml) or a matrix YAML file"""
    config: str | None = None
    """a matrix preset by name, any env (matrix_smoke, matrix_paper, matrix_minigrid_smoke) or a YAML file; used
    instead of --scale"""
    out: Path | None = None
    """output folder (default: results/matrix_<scale or preset>)"""
    attacks: str | None = None
    """comma-separated attack names, each optionally at another knob value (recipe/value, e.g.
    weight_camouflage/2) (default: the file's, or every registered attack that applies to its env)"""


def _matrix(argv: list[str]) -> None:
    from seqtrojan.experiments.matrix import load_matrix_config, run_matrix

    args = _cli(MatrixArgs, argv, "seqtrojan matrix")
    chosen = args.config if args.config is not None else args.scale
    config = _with_study_options(load_matrix_config(chosen), args, "attacks", args.attacks)
    scale = Path(chosen).stem.removeprefix("matrix_")
    out = args.out or Path("results") / f"matrix_{scale}"
    result = run_matrix(config, out, scale=scale)
    for a in result.attacks:
        print(f"{a.attack:<22} attack success {a.attack_success.text()}  clean success {a.clean_success.text()}")
    print(f"wrote {out / 'matrix.json'} and {out / 'report.html'}")


@dataclasses.dataclass
class CellsArgs(StudyArgs):
    """Train the same backdoor into each sequence model (LSTM, peephole LSTM, GRU, windowed Transformer) over
    several seeds and measure each the same way (resumable). Writes cells.json, cells.png and report.html."""

    scale: str = "smoke"
    """a shipped scale ('smoke'; 'paper'; see seqtrojan/presets/cells_*.yaml) or a YAML file"""
    out: Path | None = None
    """output folder (default: results/cells_<scale>)"""
    cells: str | None = None
    """comma-separated cell names (default: the scale file's, or all)"""


StudyConfig = TypeVar("StudyConfig", "MatrixConfig", "CellsConfig")


def _with_study_options(config: StudyConfig, args: StudyArgs, names: str, chosen: str | None) -> StudyConfig:
    """``config`` with the options given on the command line: the names to run (``chosen``, comma-separated, into
    the field ``names``), seeds, device and the job backend's settings."""
    changes: dict[str, Any] = {}
    if chosen is not None:
        changes[names] = tuple(n.strip() for n in chosen.split(",") if n.strip())
    if args.seeds is not None:
        changes["seeds"] = args.seeds
    if args.device is not None:
        changes["device"] = args.device
    jobs: dict[str, Any] = {
        "backend": args.backend, "workers": args.workers, "ray_address": args.ray_address, "threads": args.threads,
    }  # fmt: skip
    changes["jobs"] = dataclasses.replace(config.jobs, **{k: v for k, v in jobs.items() if v is not None})
    return dataclasses.replace(config, **changes)


def _cells(argv: list[str]) -> None:
    from seqtrojan.experiments.cells import load_cells_config, run_cells

    args = _cli(CellsArgs, argv, "seqtrojan cells")
    config = _with_study_options(load_cells_config(args.scale), args, "cells", args.cells)
    scale = Path(args.scale).stem.removeprefix("cells_")
    out = args.out or Path("results") / f"cells_{scale}"
    result = run_cells(config, out, scale=scale)
    for s in result.summaries:
        print(f"{s.cell:<14} clean success {s.clean_success.text()}  attack success {s.attack_success.text()}")
    print(f"wrote {out / 'cells.json'} and {out / 'report.html'}")


def _is_gymnasium_model(argv: list[str], flag: str) -> bool:
    """Whether the model folder given as ``flag`` is one of a Gymnasium env (its card's env section); False when
    the flag is absent (the grid world's options are then parsed, and ``--help`` shows them)."""
    from seqtrojan.agent.card import read_card

    folder, _ = _pop_option(argv, flag)
    return folder is not None and not read_card(Path(folder)).config.is_grid


def _analyze(argv: list[str]) -> None:
    if _is_gymnasium_model(argv, "--backdoor"):
        _analyze_gymnasium(argv)
        return
    from seqtrojan.analysis.pipeline import ANALYSIS_FILE, AnalysisConfig, run_analysis

    @dataclasses.dataclass
    class AnalyzeArgs:
        """Record the LSTM states of a clean and a backdoored agent, classify unit responses, plot them, edit the
        goal units, sweep for unintentional triggers and search for new ones (see seqtrojan.analysis)."""

        clean: Path
        """the clean model folder"""
        backdoor: Path
        """the backdoored model folder (a Gymnasium env's model takes other options: seqtrojan analyze --backdoor
        MODEL --help)"""
        out: Path = Path("results/analysis")
        config: AnalysisConfig = dataclasses.field(default_factory=AnalysisConfig)
        device: str = "cpu"

    args = _cli_with_config_file(AnalyzeArgs, AnalysisConfig, argv, "seqtrojan analyze")
    summary = run_analysis(args.clean, args.backdoor, args.out, args.config, device=args.device)
    totals = summary.responses.step_units_total
    print(f"step-type units: clean {totals['clean']}, backdoored {totals['backdoor']} -> {summary.responses.finding}")
    for r in summary.interventions.results:
        print(f"  {r.direction:<10} editing {r.units:<12} switch {r.switch.value:.3f}  hole {r.hole.value:.3f}")
    print(f"wrote {args.out}/{ANALYSIS_FILE} and {args.out}/figures/")


def _analyze_gymnasium(argv: list[str]) -> None:
    from seqtrojan.agent.checkpoint import load_agent
    from seqtrojan.analysis.config import ResponseRule
    from seqtrojan.analysis.goal_switch import GOAL_SWITCH_FILE, analyze_goal_switch
    from seqtrojan.serde import save_json

    @dataclasses.dataclass
    class AnalyzeGymnasiumArgs:
        """Look inside the model of a Gymnasium env: each unit's response type to the trigger (impulse, none,
        step), the goal units, and whether setting them switches the goal (beside random units). Writes
        goal_switch.json."""

        backdoor: Path
        """the model folder"""
        trigger_step: int | None = None
        """the step the trigger is shown at (default: the earliest of the env's evaluation range)"""
        episodes: int = 300
        """recorded episodes per type for the response types"""
        intervention_episodes: int = 300
        """episodes per arm of the intervention experiment"""
        goal_units: int = 8
        """how many of the most persistent step-type units are edited"""
        selection_episodes: int = 100
        """normal episodes per layer part on which the goal units are chosen (by their edit's effect)"""
        rule: ResponseRule = dataclasses.field(default_factory=ResponseRule)
        """the response-type rule (short episodes may need a smaller late window)"""
        seed: int = 0
        """seeds the envs and action sampling"""
        out: Path = Path("results/analysis")
        """folder for goal_switch.json"""
        device: str = "cpu"
        """torch device of the network (the envs step on the CPU)"""

    args = _cli(AnalyzeGymnasiumArgs, argv, "seqtrojan analyze")
    agent, cfg, _ = load_agent(args.backdoor)
    report = analyze_goal_switch(
        agent.to(args.device), cfg, model=str(args.backdoor), trigger_step=args.trigger_step,
        episodes=args.episodes, intervention_episodes=args.intervention_episodes, goal_units=args.goal_units,
        selection_episodes=args.selection_episodes, rule=args.rule, seed=args.seed, device=args.device,
    )  # fmt: skip
    print(
        f"model: {args.backdoor} ({report.env_id}); trigger at step {report.trigger_step}, {report.episodes} episodes"
    )
    for r in report.responses:
        counts = " / ".join(f"{r.counts[k]} {k}" for k in ("impulse", "none", "step"))
        print(f"layer {r.layer} {r.which}: {counts}")
    for c in report.candidates:
        print(f"  candidate layer {c.layer} {c.which} {list(c.units)}: activates {c.activated.text()}")
    print(f"goal units: {report.goal_source}: {list(report.goal_units)}")
    for sw in report.switches:
        print(f"  {sw.direction:<10} edited {sw.edited:<12} switched {sw.switched.text()}")
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"wrote {save_json(report, args.out / GOAL_SWITCH_FILE)}")


def _defend(argv: list[str]) -> None:
    from seqtrojan.defense.pipeline import DEFENSE_FILE, DefenseConfig, run_defense

    @dataclasses.dataclass
    class DefendArgs:
        """Run the online state monitor and every registered mitigation (`seqtrojan defenses`) on a model."""

        model: Path
        """the model folder to defend (a grid-world model or a Gymnasium env's)"""
        out: Path = Path("results/defense")
        config: DefenseConfig = dataclasses.field(default_factory=DefenseConfig)
        device: str = "cpu"

    args = _cli_with_config_file(DefendArgs, DefenseConfig, argv, "seqtrojan defend")
    result = run_defense(args.model, args.out, args.config, device=args.device)
    mon = result.monitor
    print(
        f"monitor on {mon.grid}: false alarms {mon.normal_alarm.false_alarm.value:.3f}, detection "
        f"{mon.trojan_alarm.detected.value:.3f}; attack success {mon.attack_success_undefended.value:.3f}"
        f" -> {mon.trojan_reset.attack_success.value:.3f} with resets; clean success "
        f"{mon.clean_success_undefended.value:.3f} -> {mon.normal_reset.success.value:.3f}"
    )
    for name, m in result.mitigation.items():
        print(f"  {name:<24} attack {m.attack_success.value:.3f}  clean {m.clean_success.value:.3f}")
    print(f"wrote {args.out}/{DEFENSE_FILE}")


def _zoo(argv: list[str]) -> None:
    from rich.console import Console
    from rich.table import Table

    from seqtrojan.defense.offline import detect_zoo
    from seqtrojan.defense.results import DETECTION_FILE
    from seqtrojan.serde import save_json
    from seqtrojan.zoo.build import ZooConfig, build_zoo

    @dataclasses.dataclass
    class ZooBuild:
        """Train a zoo of clean and backdoored agents (resumable; serially, on local worker processes or on Ray)."""

        out: Path = Path("results/zoo")
        config: ZooConfig = dataclasses.field(default_factory=ZooConfig)
        workers: int = 2
        """models trained at once (at most one per core; the cores are shared out as torch threads)"""
        backend: Literal["serial", "pool", "ray"] = "pool"
        """job backend: serial (this process), pool (local worker processes) or ray"""
        ray_address: str | None = None
        """the Ray cluster to run on, e.g. 10.0.0.5:6379 (none: a local Ray instance)"""
        threads: int | None = None
        """torch threads per model (default: the cores shared out among the workers; 1 on a Ray cluster)"""
        limit: int | None = None
        """train at most this many of the unfinished models, then stop (a long build in installments; a zoo of
        parts trains its parts' models in turn, so a partial build holds every part; 0: train none, only check the
        finished models and rewrite outdated labels, as after a new learned_at); none: all of them"""

    @dataclasses.dataclass
    class ZooDetect:
        """Score offline backdoor detection on a zoo. With --out: the benchmark leaderboard (every registered
        benchmark detector fitted on the train split, scored on test and holdout: ROC-AUC, cross-entropy, Brier and
        runtime with 95% bootstrap intervals; OUT/leaderboard.json and OUT/report.html; resumable). Without: the
        weight detector by k-fold cross-validation (ZOO/detection.json)."""

        zoo: Path = Path("results/zoo")
        out: Path | None = None
        """the leaderboard's folder (splits.json, predictions/, leaderboard.json, report.html); none: the k-fold
        weight detector"""
        folds: int = 5
        """k of the k-fold weight detector (without --out)"""
        seed: int = 0
        """the split's and the bootstrap's seed (--out), the folds' seed (without)"""
        test_share: float = 0.5
        """share of each label's non-holdout models in the test split (--out)"""
        holdout: tuple[str, ...] = ()
        """FACTOR=VALUE pairs whose models only the holdout split holds (--out), e.g. 'lstm_sizes=[64, 32]' or
        trigger_value=wall or attack=sequence; factors: env, cell, lstm_sizes, trigger_value, attack"""
        detectors: tuple[str, ...] = ()
        """the benchmark detectors to score (--out; default: every registered one)"""
        budget_s: float | None = None
        """seconds a detector may take per model (--out); a slower answer counts as one half. None: no limit"""

    if not argv or argv[0] not in ("build", "detect"):
        print("usage: seqtrojan zoo {build,detect} [options]   (seqtrojan zoo build --help)", file=sys.stderr)
        raise SystemExit(2)
    if argv[0] == "build":
        from seqtrojan.experiments.attacks import RECIPES

        args = _cli_with_config_file(ZooBuild, ZooConfig, argv[1:], "seqtrojan zoo build")
        manifest = build_zoo(args.config, args.out, workers=args.workers, backend=args.backend,
                             ray_address=args.ray_address, threads=args.threads, recipes=RECIPES,
                             limit=args.limit, progress=True)  # fmt: skip
        print(f"wrote {manifest}")
        return
    args = _cli(ZooDetect, argv[1:], "seqtrojan zoo detect")
    if args.out is not None:
        _zoo_leaderboard(args.zoo, args.out, args.seed, args.test_share, args.holdout, args.detectors, args.budget_s)
        return
    result = detect_zoo(args.zoo, args.folds, args.seed)
    save_json(result, args.zoo / DETECTION_FILE)
    table = Table(title=f"Offline detection on {args.zoo} (held-out, {result.scores[0].folds}-fold)")
    for col in ("features", "n", "ROC-AUC", "cross-entropy", "Brier"):
        table.add_column(col, justify="right")
    for r in result.scores:
        table.add_row(r.group, str(r.features), f"{r.roc_auc:.3f}", f"{r.cross_entropy:.3f}", f"{r.brier:.3f}")
    Console().print(table)
    for h in result.held_out:
        if h.roc_auc is not None:
            print(f"held out by {h.key} ({len(h.groups)} values, each unseen in training): ROC-AUC "
                  f"{h.roc_auc:.3f}, cross-entropy {h.cross_entropy:.3f}, Brier {h.brier:.3f}")  # fmt: skip
    for bad in result.rejected:
        print(f"rejected {bad.model}: {bad.reason}")
    print(f"wrote {args.zoo}/{DETECTION_FILE}")


def _zoo_leaderboard(
    zoo: Path, out: Path, seed: int, test_share: float, holdout: tuple[str, ...], detectors: tuple[str, ...],
    budget_s: float | None,
) -> None:  # fmt: skip
    from seqtrojan.benchmark.leaderboard import LEADERBOARD_FILE, run_leaderboard, zoo_holdout
    from seqtrojan.benchmark.splits import SplitConfig
    from seqtrojan.report.sections.leaderboard import leaderboard_page

    held: dict[str, list[str]] = {}
    if not holdout:  # the zoo's own (zoo.json), if it was built as a benchmark
        held = {k: list(v) for k, v in zoo_holdout(zoo).items()}
    for pair in holdout:
        factor, sep, value = pair.partition("=")
        if not sep or not factor or not value:
            raise ConfigError(f"--holdout takes FACTOR=VALUE pairs, got {pair!r}")
        held.setdefault(factor.strip(), []).append(value.strip())
    splits = SplitConfig(test_share, {k: tuple(v) for k, v in held.items()}, seed=seed)
    board = run_leaderboard(zoo, out, splits, detectors or None, budget_s=budget_s, progress=True)
    print(f"benchmark leaderboard on {zoo}: train {board.models['train']}, test {board.models['test']}, holdout "
          f"{board.models['holdout']} models; ROC-AUC with Newcombe's interval, cross-entropy and Brier with 95% "
          "bootstrap intervals over models (the bootstrap's AUC interval is in leaderboard.json)")  # fmt: skip

    def short(metric: Any) -> str:
        if metric.value is None:
            return "n/a"
        return f"{metric.value:.3f}" + ("" if metric.low is None else f" [{metric.low:.2f}, {metric.high:.2f}]")

    width = max(len(d.detector) for d in board.detectors)
    print(
        f"{'detector':<{width}}  split    n (poisoned)  {'ROC-AUC':<20}  {'cross-entropy':<20}  {'Brier':<20}  ms/model"
    )
    for d in board.detectors:
        for r in d.splits:
            sc = r.scores
            print(
                f"{d.detector:<{width}}  {r.split:<7}  {f'{sc.models} ({sc.poisoned})':<12}  "
                f"{short(sc.roc_auc_newcombe):<20}  {short(sc.cross_entropy):<20}  {short(sc.brier):<20}  "
                f"{1000 * (sc.runtime_s.value or 0.0):.1f}"
            )
    for d in board.detectors:
        if d.over_budget:
            print(f"{d.detector}: {d.over_budget} answer(s) over the {budget_s} s budget, each scored as one half")
    (out / "report.html").write_text(leaderboard_page(board))
    print(f"wrote {out / LEADERBOARD_FILE} and {out / 'report.html'}")


def _list_registered(family: Literal["attack", "defense"], first: tuple[Any, ...], argv: list[str]) -> None:
    """One line per registered thing of ``family``: name, kind, description. The registries ``first`` lead, in that
    order, then any other registry of the family that an imported module created."""
    from seqtrojan.registry import registries

    if argv:
        print(f"usage: seqtrojan {family}s   (takes no options)", file=sys.stderr)
        raise SystemExit(2)
    order = [*first, *(r for r in registries(family) if r not in first)]
    entries = [e for registry in order for e in registry.entries()]
    name_width = max((len(e.name) for e in entries), default=0)
    kind_width = max((len(e.kind) for e in entries), default=0)
    for e in entries:
        print(f"{e.name:<{name_width}}  {e.kind:<{kind_width}}  {e.description}")


def _attacks(argv: list[str]) -> None:
    from seqtrojan.env.config import REWARDS, TRIGGERS
    from seqtrojan.experiments.attacks import ATTACKS
    from seqtrojan.train.mixing import MIXING_RULES
    from seqtrojan.train.penalties import PENALTIES

    _list_registered("attack", (ATTACKS, TRIGGERS, MIXING_RULES, REWARDS, PENALTIES), argv)


def _defenses(argv: list[str]) -> None:
    import seqtrojan.defense.pipeline  # noqa: F401  (it imports any further module that registers a mitigation)
    from seqtrojan.benchmark.detectors import DETECTORS as BENCHMARK_DETECTORS
    from seqtrojan.defense.mitigation import MITIGATIONS
    from seqtrojan.defense.monitor import MONITORS
    from seqtrojan.defense.offline import DETECTORS

    _list_registered("defense", (MONITORS, DETECTORS, BENCHMARK_DETECTORS, MITIGATIONS), argv)


def _import(argv: list[str]) -> None:
    from typing import Annotated

    from seqtrojan.agent.card import read_card
    from seqtrojan.agent.imports import import_agent

    @dataclasses.dataclass
    class ImportArgs:
        """Import a recurrent agent trained elsewhere as a seqtrojan model folder (safetensors + card), without
        unpickling anything: an sb3-contrib RecurrentPPO zip (MlpLstmPolicy) or a CleanRL LSTM state dict (its
        Atari CNN agent, or an MLP in the CNN's place). Every
        seqtrojan tool (evaluate, analyze, defend, ...) then runs on it, also for an agent trained on a Gymnasium
        env (MiniGrid, your own: give its preset with --config). See docs/import.md."""

        source: tyro.conf.Positional[Path]
        """the model file: an sb3 .zip or a CleanRL state dict (.pt)"""
        from_: Annotated[Literal["sb3", "cleanrl"], tyro.conf.arg(name="from")]
        """the file's kind"""
        out: Path
        """the model folder to write (new or empty)"""
        label: Literal["clean", "backdoored"] | None = None
        """what you state the agent is (the card's label); unset writes 'unknown' (a suspect: evaluated in
        both envs, never taken as ground truth) and marks the card's provenance.label_stated false"""
        obs_dim: int | None = None
        """observation inputs (required for cleanrl; checked for sb3)"""
        actions: int | None = None
        """number of discrete actions (required for cleanrl; checked for sb3)"""
        activation: Literal["relu", "tanh"] = "relu"
        """cleanrl: the activation after each encoder layer (network.*)"""
        conv_strides: tuple[int, ...] | None = None
        """cleanrl: the stride of each conv layer of its CNN (a state dict does not record them); default: CleanRL's
        Atari CNN's 4 2 1 (for its kernels 8 4 3)"""
        config: str | None = None
        """a preset's name or a YAML file whose env the agent acts in (the grid world or a Gymnasium env such as
        minigrid_two_goals; default: the grid world's default env, a 3x3 view and four moves); the agent's
        observation size and action count are checked against that env"""

    args = _cli(ImportArgs, argv, "seqtrojan import")
    config = None
    if args.config is not None:
        from seqtrojan.config import ExperimentConfig
        from seqtrojan.presets import resolve_preset
        from seqtrojan.serde import from_dict, load_yaml

        config = from_dict(ExperimentConfig, load_yaml(resolve_preset(args.config)), "")
    out = import_agent(
        args.from_, args.source, args.out, config=config, label=args.label, obs_dim=args.obs_dim,
        num_actions=args.actions, activation=args.activation, conv_strides=args.conv_strides,
    )  # fmt: skip
    card = read_card(out)
    provenance = card.provenance or {}
    label, described = card.label, card.architecture.describe()
    where = "" if card.config.is_grid else f" (for the Gymnasium env {card.config.gym_env.id})"
    print(f"imported {args.source} ({args.from_}) -> {out}{where}")
    print(f"architecture: {described}")
    print(f"label: {label}" + ("" if provenance.get("label_stated") else " (not stated: pass --label)"))
    if provenance.get("value") == "zeroed":
        print("value head: zero (the original's separate critic is not imported; the policy is exact)")


def _demo(argv: list[str]) -> None:
    from seqtrojan.demo import DemoArgs, run_demo

    run_demo(_cli(DemoArgs, argv, "seqtrojan demo"))


COMMANDS: dict[str, tuple[Callable[[list[str]], None], str]] = {
    "train": (_train, "train an agent with recurrent PPO, grid world or Gymnasium env (--config, --resume RUN_DIR)"),
    "evaluate": (_evaluate, "success rates with 95% CIs: grid configs beside the paper's tables, or the model's env"),
    "analyze": (_analyze, "state traces, response types, interventions, unintentional triggers, search"),
    "defend": (
        _defend,
        "online state monitors and mitigations (fine-pruning, fine-tuning, state bounds, ...) on a model",
    ),
    "zoo": (_zoo, "zoo build: train clean and backdoored agents; zoo detect: offline detection scored like TrojAI"),
    "reproduce": (_reproduce, "train, evaluate, plot and write the HTML report (--scale smoke|paper)"),
    "matrix": (_matrix, "every attack against every defense over seeds (--scale smoke|paper) -> matrix.json"),
    "cells": (_cells, "LSTM, peephole LSTM, GRU and Transformer agents compared over seeds -> cells.json"),
    "attacks": (_attacks, "list the registered attacks: trigger kinds, mixing rules, rewards, penalties"),
    "defenses": (_defenses, "list the registered defenses: monitors, detectors, mitigations"),
    "import": (_import, "import an agent trained elsewhere (sb3-contrib RecurrentPPO zip, CleanRL LSTM state dict)"),
    "demo": (_demo, "build envs, run random and scripted agents, render episodes (text and PNG)"),
}


def _usage() -> str:
    lines = ["usage: seqtrojan <command> [options]", "", "commands:"]
    lines += [f"  {name:<12} {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += ["", "Run 'seqtrojan <command> --help' for a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        from seqtrojan import __version__

        print(f"seqtrojan {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"seqtrojan: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        COMMANDS[name][0](rest)
    except SeqTrojanError as err:
        print(f"seqtrojan {name}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        if err.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # a full disk while writing a log or a result file (checkpoints and models say so themselves, keeping the
        # previous checkpoint): what was finished stays, and the run resumes once there is room
        where = f" ({err.filename})" if err.filename else ""
        print(f"seqtrojan {name}: error: disk full{where}: free some space and rerun (finished work is kept)",
              file=sys.stderr)  # fmt: skip
        return 2
    except KeyboardInterrupt as err:
        print(f"seqtrojan {name}: {err or 'interrupted'}", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
