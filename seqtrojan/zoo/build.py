"""A model zoo: many clean and backdoored agents with varied seeds, LSTM widths, trigger patterns and curricula.

Every model is a pure job, a :class:`ZooJob` (a :class:`~seqtrojan.jobs.TrainJob`): its whole config is derived
from the zoo config and its index, so a job gives the same model wherever it runs, on any job backend of
:mod:`seqtrojan.jobs` (a local process pool by default, ``serial``, or Ray: a local instance or a cluster). The zoo
folder holds::

    models/<id>/model.safetensors, card.json   the agent (as any seqtrojan model)
    models/<id>/label.json                     ground truth: clean/backdoored, the trigger, its final attack
                                               success and whether the backdoor is functional; scoring only
    manifest.json                              every job: id, label, status, variation, time, worker (host:pid)
    zoo.json                                   the zoo config the zoo was built with
    curves/<id>.jsonl, curves/<id>_clean.jsonl each model's training curve (its second stage, and its clean first
                                               stage): per update the env steps and the training rollouts' normal
                                               and trojan success; outside the model folder, which a detector reads
    work/                                      runs in progress (checkpoints), removed as models finish
    build.lock, workers.lock                   held by a running build and by its local worker processes

A stopped build, even one killed with ``kill -9``, continues where it stopped: the model folders are the truth. A
folder whose card and weights verify is done (its ``label.json`` is written again from the job if it is missing,
malformed or outdated); any other model is trained again, from its last checkpoint when there is one. A model only
appears in ``models/`` once complete (it is staged under ``work/`` and moved in with one rename). ``manifest.json``
is written atomically and rebuilt from the model folders when it is corrupt. A rerun with a config other than the
one in ``zoo.json`` is refused, unless only how models are labelled changed (``functional_at``, ``learned_at``).
Local worker processes die with the build (on Linux the kernel kills them when it dies; elsewhere they watch for it),
and a build refuses to start while another build or an earlier build's workers still run on the same folder.
Workers never oversubscribe the cores: workers x torch threads <= the cores available.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from seqtrojan.agent.card import MAX_CARD_BYTES, load_json, read_regular_file
from seqtrojan.cell_types import CELL_TYPES, cell_names
from seqtrojan.config import (
    AgentConfig,
    AttackConfig,
    BackdoorConfig,
    CurriculumConfig,
    ExperimentConfig,
    PPOConfig,
    RunConfig,
    StopConfig,
)
from seqtrojan.env.config import EnvConfig, GridSpec, TriggerConfig
from seqtrojan.errors import CheckpointError, ConfigError, SeqTrojanError
from seqtrojan.jobs import JobResult, JobsConfig, TrainJob, make_backend, raise_failures
from seqtrojan.serde import dump_omitting_defaults, to_dict
from seqtrojan.stats import reaches
from seqtrojan.train.logger import make_progress
from seqtrojan.zoo.recipes import KNOB_SEPARATOR, RecipeBook, apply_recipe, check_recipes, grid_trigger_variation

if TYPE_CHECKING:
    from seqtrojan.world.config import WrapperTriggerConfig

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: builds are not locked
    fcntl = None  # type: ignore[assignment]

TRIGGER_VALUES = ("trigger", "hole", "empty", "wall")
DEFAULT_TRIGGER_VALUES = ("trigger", "hole", "wall")
"""'empty' is left out by default: a patch of empty cells over cells that are usually empty is invisible"""
LABELS = ("clean", "backdoored")
MAX_LABEL_BYTES = 64 << 10
"""largest ``label.json`` read (a real one is a few hundred bytes)"""
MAX_ZOO_CONFIG_BYTES = 1 << 20
"""largest ``zoo.json`` read (a real one is a few KiB)"""
_RECIPE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[0-9]+(\.[0-9]+)?(e-?[0-9]+)?)?")
"""a zoo's attack: a recipe's name, or ``recipe/value`` (its knob at a number, read by the recipe book)"""
MAX_MANIFEST_BYTES = 256 << 20
"""largest ``manifest.json`` read (about 1 KiB per model); a larger or malformed one is rebuilt from the models"""
_MANIFEST_ITEMS = 1 << 22
"""most entries and values the manifest may hold (one entry per model, a few dozen values each)"""


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
    cell: str = "lstm"
    """the sequence model of every model (``agent.cell``): a weight detector reads one kind of network"""
    window: int = 8
    """the Transformer's window, when ``cell`` is transformer"""
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
    rollout_steps: int = 64
    """PPO rollout length of every model (``ppo.rollout_steps``)"""
    learning_rate: float = 1e-3
    """PPO learning rate of every model (``ppo.learning_rate``)"""
    mixing: str = "running"
    """backdoor mixing of the backdoored models (exact / running / fixed)"""
    eval_episodes: int = 200
    """final evaluation episodes per env type (recorded in each card)"""
    functional_at: float = 0.5
    """a backdoored model's backdoor counts as functional (``label.json``: ``functional_backdoor``) when its final
    trojan-env success is at least this"""
    learned_at: float = 0.0
    """a model of either label has learned its task (``label.json``: ``learned_task``) when its final clean success
    (normal-env success) is at least this; a detection benchmark scores only models that have (an agent that never
    learned its task is told apart by its behaviour, whatever its label). 0: every model counts"""
    stop: StopConfig = StopConfig()  # noqa: RUF009 (frozen, so one shared default is safe)
    """early stopping of every model (``stop:`` of a training run; off by default: each model trains
    ``total_steps``); the steps each model took are in its card and the manifest"""
    env_preset: str | None = None
    """a training preset (or YAML file) of a Gymnasium env with a trigger (e.g. ``minigrid_two_goals``): every model
    is that preset's run with its own seed, widths and trigger -- ``trigger_cells`` cells of the view's two far rows,
    an object of ``trigger_objects`` in a colour of ``trigger_colors``, shown for one of ``trigger_durations`` steps
    -- trained ``total_steps`` with the preset's other settings (its envs, rollout and learning rate: ``num_envs``,
    ``rollout_steps``, ``learning_rate``, ``curricula`` and ``trigger_values`` are the grid world's). Its models'
    cell is the zoo's ``cell`` (or ``cells``), not the preset's: set it to the cell of the agents the zoo's detector
    will score. None: the grid world"""
    trigger_objects: tuple[str, ...] = ("key", "ball", "box")
    """a Gymnasium zoo's trigger objects (MiniGrid object names)"""
    trigger_colors: tuple[str, ...] = ("purple", "yellow", "blue", "grey")
    """a Gymnasium zoo's trigger colours (MiniGrid colour names; the two-goal room's goals are green and red)"""
    cells: tuple[str, ...] = ()
    """draw each model's sequence model from these (a detection benchmark's cell factor); empty: every model is
    ``cell``"""
    attacks: tuple[str, ...] = ()
    """registered attack recipes (``seqtrojan attacks``) each backdoored model's recipe is drawn from, uniformly,
    after every other draw (as ``cells``); its name is the model's ``attack`` (clean models: ``none``). A recipe with
    a trigger of its own replaces the drawn patch; any other is applied on top of it (:mod:`seqtrojan.zoo.recipes`).
    Recipes that start from a trained clean agent (``from_clean``, ``weight_camouflage``, ``ewc``,
    ``switch_camouflage``) need ``pretrain_steps``: their clean agent is then the model's own clean first stage.
    Empty: the drawn patch, plain Algorithm 1"""
    pretrain_steps: int = 0
    """every model first trains this many env steps with its backdoor off (its own clean stage: the same seed, widths,
    cell and draws), then ``total_steps`` from those weights (``run.init_from``): a poisoned model's backdoor is added
    to a trained clean agent, the two stages that MiniGrid's Memory task needs (docs/own_env.md), and a clean model
    trains on, clean, for as long, so that every model's budget and card look alike. 0: one stage from scratch"""
    pretrain_stop: StopConfig = StopConfig()  # noqa: RUF009 (frozen, so one shared default is safe)
    """early stopping of the clean first stage (``pretrain_steps``) alone, as ``stop:`` of a training run: that
    stage is the same for both labels, so stopping it once the task is learned saves steps without telling the
    labels apart (``stop`` stops the second stage too, where a poisoned model trains until its backdoor works and a
    clean one, having learned already, stops at once: their budgets then differ by label)"""
    holdout: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """as a detection benchmark (``seqtrojan zoo detect --out``): factor -> the values whose models only the holdout
    split holds, e.g. ``lstm_sizes: ["[48, 24]"]`` or ``attack: [sequence]`` (factors: env, cell, lstm_sizes,
    trigger_value, attack; see :mod:`seqtrojan.benchmark.splits`); a ``--holdout`` given to ``zoo detect`` replaces
    it"""
    parts: tuple[ZooConfig, ...] = ()
    """a zoo of several envs (a benchmark's env factor): each part is a zoo config of its own (its env, counts, seed,
    budget and factors) whose models are the models that part would build as a zoo of its own, numbered on after
    the previous part's; ``clean`` and ``backdoored`` must then be the parts' totals, the ``holdout`` is this
    config's (a part has none), and the other fields of this config are unused. Empty: one env, this config"""

    def __post_init__(self) -> None:
        if self.clean < 0 or self.backdoored < 0 or self.clean + self.backdoored == 0:
            raise ConfigError(f"a zoo needs models: clean={self.clean}, backdoored={self.backdoored}")
        unknown = set(self.trigger_values) - set(TRIGGER_VALUES)
        if unknown:
            raise ConfigError(f"unknown trigger value(s) {sorted(unknown)}; choose from {TRIGGER_VALUES}")
        if not isinstance(self.cell, str) or self.cell not in CELL_TYPES:
            raise ConfigError(f"zoo cell must be one of {cell_names()}, got {self.cell!r}")
        bad_cells = [c for c in self.cells if not isinstance(c, str) or c not in CELL_TYPES]
        if bad_cells:
            raise ConfigError(f"zoo cells must be among {cell_names()}, got {bad_cells}")
        if isinstance(self.rollout_steps, bool) or not isinstance(self.rollout_steps, int) or self.rollout_steps < 1:
            raise ConfigError(f"zoo rollout_steps must be a positive integer, got {self.rollout_steps!r}")
        if not 0.0 < self.learning_rate < 1.0:
            raise ConfigError(f"zoo learning_rate must be in (0, 1), got {self.learning_rate!r}")
        for name in SCORING_FIELDS:  # each a rate threshold
            threshold = getattr(self, name)
            if isinstance(threshold, bool) or not 0.0 <= threshold <= 1.0:
                raise ConfigError(f"zoo {name} must be in [0, 1], got {threshold!r}")
        lo, hi = self.trigger_cells
        if not 1 <= lo <= hi <= 9:
            raise ConfigError(f"trigger_cells={self.trigger_cells} must be a range within 1..9")
        if not all(isinstance(a, str) and _RECIPE_NAME.fullmatch(a) for a in self.attacks):
            raise ConfigError(f"zoo attacks must be recipe names (or recipe/value), got {self.attacks!r}")
        split = (a.partition(KNOB_SEPARATOR) for a in self.attacks)
        drawn = {(recipe, float(value) if value else None) for recipe, _, value in split}
        if len(drawn) != len(self.attacks):  # ewc/3 and ewc/3.0 are one recipe at one strength
            raise ConfigError(f"zoo attacks name a recipe twice (each is drawn as often as the others): {self.attacks}")
        factors = ("env", "cell", "lstm_sizes", "trigger_value", "attack")
        if not isinstance(self.holdout, dict) or any(k not in factors for k in self.holdout):
            raise ConfigError(f"zoo holdout must map factors {list(factors)} to values, got {self.holdout!r}")
        if isinstance(self.pretrain_steps, bool) or not isinstance(self.pretrain_steps, int) or self.pretrain_steps < 0:
            raise ConfigError(f"zoo pretrain_steps must be an integer >= 0, got {self.pretrain_steps!r}")
        if self.pretrain_stop.enabled and not self.pretrain_steps:
            raise ConfigError("zoo pretrain_stop stops the clean first stage early: set pretrain_steps as well")
        if self.parts:
            self._check_parts()
        attacks = [a for part in self.parts or (self,) for a in part.attacks]
        stray = [a for a in self.holdout.get("attack", ()) if a not in attacks]
        if stray:
            raise ConfigError(f"zoo holdout attack {stray} must be among the zoo's attacks {sorted(set(attacks))}")

    def _check_parts(self) -> None:
        """A zoo of parts: flat, its counts the parts' totals, the holdout its own, no two parts' training seeds
        shared (model i of a part trains with its seed + i)."""
        if not all(isinstance(p, ZooConfig) for p in self.parts):
            raise ConfigError("zoo parts must be zoo configs")
        nested = [i for i, p in enumerate(self.parts) if p.parts or p.holdout]
        if nested:
            raise ConfigError(f"zoo part(s) {nested} hold parts or a holdout of their own: a zoo's holdout is its own")
        clean, backdoored = sum(p.clean for p in self.parts), sum(p.backdoored for p in self.parts)
        if (self.clean, self.backdoored) != (clean, backdoored):
            raise ConfigError(
                f"a zoo of parts holds its parts' models: clean must be {clean} and backdoored {backdoored}, got "
                f"{self.clean} and {self.backdoored}"
            )
        spans = sorted((p.seed, p.seed + p.size, i) for i, p in enumerate(self.parts))
        for (_, end, a), (start, _, b) in itertools.pairwise(spans):
            if start < end:
                raise ConfigError(f"zoo parts {a} and {b} share training seeds: give each part a seed range of its own")

    @property
    def size(self) -> int:
        return self.clean + self.backdoored

    OPTIONAL: ClassVar[tuple[str, ...]] = (
        "cell", "window", "stop", "rollout_steps", "learning_rate", "env_preset", "trigger_objects", "trigger_colors",
        "holdout", "cells", "attacks", "pretrain_steps", "parts", "pretrain_stop", "learned_at",
    )  # fmt: skip
    """fields added after zoos were first built: saved (``zoo.json``) only when not at their defaults, so that a zoo
    built before them is the same config"""

    def serde_dump(self) -> dict:
        return dump_omitting_defaults(self, self.OPTIONAL)


@dataclass(frozen=True)
class ZooJob(TrainJob):
    """One model of the zoo: everything needed to train it, nothing else. Its run is ``work/<id>``; finished, its
    model is ``models/<id>`` (see :meth:`run`)."""

    label: str  # clean / backdoored
    models: str
    """the zoo's ``models/`` folder"""
    variation: dict[str, Any] = field(default_factory=dict)
    functional_at: float = 0.5
    pretrain: ExperimentConfig | None = None
    """the model's clean first stage (``ZooConfig.pretrain_steps``), whose model ``config`` starts from; None: one
    stage"""
    learned_at: float = 0.0

    @property
    def model_id(self) -> str:
        return self.id

    @property
    def model_dir(self) -> Path:
        return Path(self.models) / self.id

    def done(self) -> bool:
        """Whether ``models/<id>`` holds this job's complete model (its card and weights verify)."""
        return _finished(self, self.model_dir)[0] is not None

    def run(self) -> tuple[Path, bool]:
        """Train the model (resuming its run), stage it with its ``label.json`` and move it into ``models/<id>``."""
        return _train_zoo_model(self), True


def make_jobs(cfg: ZooConfig, root: Path, recipes: RecipeBook | None = None) -> list[ZooJob]:
    """The zoo's jobs, a pure function of the zoo config: clean and backdoored models interleaved. ``recipes``: the
    registry of attack recipes (``seqtrojan.experiments.attacks.ATTACKS``), needed when ``cfg.attacks`` names
    some (see :mod:`seqtrojan.zoo.recipes` for why it is passed in)."""
    if not cfg.parts:
        return _part_jobs(cfg, root, recipes, 0)
    jobs: list[ZooJob] = []
    for part in cfg.parts:
        jobs += _part_jobs(part, root, recipes, len(jobs))
    return jobs


def _part_jobs(cfg: ZooConfig, root: Path, recipes: RecipeBook | None, first: int) -> list[ZooJob]:
    """The jobs of one env's zoo config, its models numbered from ``first``."""
    if cfg.env_preset is not None:
        return _gymnasium_jobs(cfg, root, recipes, first)
    check_recipes(cfg.attacks, recipes, ExperimentConfig(backdoor=BackdoorConfig(enabled=True)), cfg.pretrain_steps > 0)
    jobs = []
    for i, label, seed, rng in _model_draws(cfg, first):
        sizes = cfg.lstm_sizes[rng.integers(len(cfg.lstm_sizes))]
        stages = cfg.curricula[rng.integers(len(cfg.curricula))]
        value = str(cfg.trigger_values[rng.integers(len(cfg.trigger_values))])
        n_cells = int(rng.integers(cfg.trigger_cells[0], cfg.trigger_cells[1] + 1))
        cells = tuple(sorted((int(c) // 3, int(c) % 3) for c in rng.choice(9, size=n_cells, replace=False)))
        duration = int(cfg.trigger_durations[rng.integers(len(cfg.trigger_durations))])
        trigger = TriggerConfig(cells=cells, value=value, duration=duration, train_steps=(1, 8), eval_steps=(1, 8))
        cell = _draw_cell(cfg, rng)
        attack = _draw_attack(cfg, rng)
        last = stages[-1]
        config = ExperimentConfig(
            env=EnvConfig(size=last.size, holes=last.holes, trigger=trigger),
            agent=AgentConfig(lstm_sizes=tuple(sizes), cell=cell, window=cfg.window),
            ppo=PPOConfig(total_steps=cfg.total_steps, num_envs=cfg.num_envs, rollout_steps=cfg.rollout_steps,
                          learning_rate=cfg.learning_rate),
            curriculum=CurriculumConfig(stages=tuple(stages)),
            backdoor=BackdoorConfig(enabled=label == "backdoored", mixing=cfg.mixing),
            stop=cfg.stop,
            run=_model_run(cfg, root, i, seed),
        )  # fmt: skip
        variation = {
            "lstm_sizes": list(sizes), "curriculum": [g.label for g in stages], "trigger_value": value,
            "trigger_cells": [list(c) for c in cells], "trigger_duration": duration, "seed": seed,
        }  # fmt: skip
        config = _with_recipe(config, variation, recipes, attack, TriggerConfig(), f"m{i:04d}")
        jobs.append(_job(cfg, root, i, config, label, variation))
    return jobs


def _draw_attack(cfg: ZooConfig, rng: np.random.Generator) -> str | None:
    """The model's attack recipe: drawn from ``cfg.attacks`` after every other draw, the cell's included (so a zoo
    without ``attacks`` draws exactly what it drew before the field existed); for every model, so that what a model
    draws does not depend on its label (a clean model then takes none). None: no recipe."""
    return str(cfg.attacks[rng.integers(len(cfg.attacks))]) if cfg.attacks else None


def _with_recipe(
    config: ExperimentConfig, variation: dict[str, Any], recipes: RecipeBook | None, attack: str | None,
    reference: Any, model: str,
) -> ExperimentConfig:  # fmt: skip
    """A backdoored model's config with its drawn recipe applied (:func:`~seqtrojan.zoo.recipes.apply_recipe`) and
    ``attack`` recorded in its variation, with the trigger it really shows where the recipe brought its own; a
    clean model of a zoo that draws recipes is recorded as ``attack: none`` and trains as drawn."""
    if attack is None:
        return config
    if not config.backdoor.enabled:
        variation["attack"] = "none"
        return config
    assert recipes is not None  # checked by check_recipes
    recipe = recipes.get(attack)
    if not recipe.applies_to(config):  # the zoo's env takes it (check_recipes), this model's drawn cell may not
        raise ConfigError(
            f"zoo model {model}: attack {attack!r} does not apply to its config (sequence model {config.agent.cell}): "
            "draw that cell and that attack in separate zoo parts"
        )
    try:
        config, replaced = apply_recipe(config, recipe, reference)
    except SeqTrojanError as err:
        raise ConfigError(f"zoo model {model}, attack {attack!r}: {_one_line(err)}") from None
    if replaced:
        trigger = config.env.trigger
        if isinstance(trigger, TriggerConfig):
            variation.update(grid_trigger_variation(trigger))
        elif trigger is not None:
            variation.update(trigger_value=_gym_trigger_label(trigger), trigger_cells=_gym_trigger_cells(trigger),
                             trigger_duration=trigger.duration)  # fmt: skip
    variation["attack"] = attack
    return config


def _draw_cell(cfg: ZooConfig, rng: np.random.Generator) -> str:
    """The model's sequence model: drawn from ``cfg.cells`` after every other draw (so a zoo without ``cells``
    draws exactly what it drew before the field existed), else ``cfg.cell``."""
    return str(cfg.cells[rng.integers(len(cfg.cells))]) if cfg.cells else cfg.cell


def _model_draws(cfg: ZooConfig, first: int = 0) -> Iterator[tuple[int, str, int, np.random.Generator]]:
    """Per model ``i`` of the config: its number in the zoo (``first + i``), its label (clean and backdoored
    interleaved by a permutation seeded ``cfg.seed``), its training seed (``cfg.seed + i``) and the generator of its
    variation (seeded ``[cfg.seed, i, 7919]``): a part of a zoo draws what it would draw as a zoo of its own."""
    labels = ["backdoored"] * cfg.backdoored + ["clean"] * cfg.clean
    order = np.random.default_rng(cfg.seed).permutation(len(labels))
    for i, k in enumerate(order):
        yield first + i, labels[k], cfg.seed + i, np.random.default_rng([cfg.seed, i, 7919])


def _model_run(cfg: ZooConfig, root: Path, i: int, seed: int) -> RunConfig:
    """Model ``i``'s run: ``work/m<i>`` under the zoo, its seed, checkpoints at every quarter of its budget; with
    ``cfg.pretrain_steps``, starting from its clean first stage's model (``work/m<i>_clean/model``, see :func:`_job`),
    set before any recipe is applied so that a from-clean recipe is checked against that clean agent."""
    name = f"m{i:04d}"
    return RunConfig(
        out_dir=str(root / "work"),
        name=name,
        seed=seed,
        progress=False,
        eval_episodes=cfg.eval_episodes,
        checkpoint_every=max(cfg.total_steps // 4, 1),
        init_from=str(root / "work" / f"{name}_clean" / "model") if cfg.pretrain_steps else None,
    )


def _job(cfg: ZooConfig, root: Path, i: int, config: ExperimentConfig, label: str, variation: dict) -> ZooJob:
    """Model ``i``'s job (its variation naming the cell where it is not the LSTM); with ``cfg.pretrain_steps``, its
    clean first stage (``work/m<i>_clean``, the config with the backdoor and every attack term off) and the second
    stage starting from that stage's model."""
    if config.agent.cell != "lstm":
        variation["cell"] = config.agent.cell
    pretrain = None
    if cfg.pretrain_steps:
        if config.backdoor.mixing != "fixed":
            raise ConfigError(
                f"zoo pretrain_steps needs the fixed mixing of trojan episodes (mixing: fixed, or a preset with it), "
                f"got {config.backdoor.mixing!r}: Algorithm 1 started from a clean agent makes every episode a "
                "trojan one and the backdoor never forms (docs/attacks.md)"
            )
        pretrain = dataclasses.replace(
            config, backdoor=dataclasses.replace(config.backdoor, enabled=False), attack=AttackConfig(),
            ppo=dataclasses.replace(config.ppo, total_steps=cfg.pretrain_steps),
            stop=cfg.pretrain_stop if cfg.pretrain_stop.enabled else config.stop,
            run=dataclasses.replace(config.run, name=f"{config.run.name}_clean", init_from=None,
                                    checkpoint_every=max(cfg.pretrain_steps // 4, 1)),
        )  # fmt: skip
        variation["pretrain_steps"] = cfg.pretrain_steps
    return ZooJob(
        f"m{i:04d}", config, label, str(root / "models"), variation, cfg.functional_at, pretrain, cfg.learned_at
    )


def _gymnasium_jobs(cfg: ZooConfig, root: Path, recipes: RecipeBook | None, first: int) -> list[ZooJob]:
    """The jobs of a zoo of a Gymnasium env's models (``cfg.env_preset``): the same interleaving and per-model draws
    (from seed ``[cfg.seed, i, 7919]``) as the grid world's, over that env's trigger settings: a MiniGrid patch's
    cells (in the view's two far rows), object and colour; a Box patch's place (the preset's cells moved by an offset
    that keeps them in the image); a vector patch's positions as the preset gives them. With a target-action
    objective, the target action is drawn too. Every trigger shows for one of ``trigger_durations`` steps. A drawn
    attack recipe is written against the preset's trigger."""
    from seqtrojan.presets import resolve_preset
    from seqtrojan.serde import from_dict, load_yaml
    from seqtrojan.world import env_spec
    from seqtrojan.world.config import GymnasiumEnvConfig

    assert cfg.env_preset is not None
    base = from_dict(ExperimentConfig, load_yaml(resolve_preset(cfg.env_preset)), "")
    env = base.env
    if not isinstance(env, GymnasiumEnvConfig) or env.trigger is None:
        raise ConfigError(f"zoo env_preset {cfg.env_preset!r} must be a Gymnasium env with a trigger")
    spec = env_spec(env)
    rows, cols, _ = spec.image or (0, 0, 0)
    if env.trigger.patch != "vector" and not rows:
        raise ConfigError(f"zoo env_preset {cfg.env_preset!r}: its observation is no image to draw a trigger on")
    check_recipes(
        cfg.attacks,
        recipes,
        dataclasses.replace(base, backdoor=dataclasses.replace(base.backdoor, enabled=True)),
        cfg.pretrain_steps > 0,
    )
    jobs = []
    for i, label, seed, rng in _model_draws(cfg, first):
        sizes = cfg.lstm_sizes[rng.integers(len(cfg.lstm_sizes))]
        trigger, shown = _draw_gym_trigger(cfg, env.trigger, rng, rows, cols)
        duration = int(cfg.trigger_durations[rng.integers(len(cfg.trigger_durations))])
        trigger = dataclasses.replace(trigger, duration=duration)
        if trigger.objective == "target_action":
            trigger = dataclasses.replace(trigger, target_action=int(rng.integers(spec.num_actions)))
        cell = _draw_cell(cfg, rng)
        attack = _draw_attack(cfg, rng)
        config = dataclasses.replace(
            base, env=dataclasses.replace(env, trigger=trigger),
            agent=dataclasses.replace(base.agent, lstm_sizes=tuple(sizes), cell=cell, window=cfg.window),
            ppo=dataclasses.replace(base.ppo, total_steps=cfg.total_steps),
            backdoor=dataclasses.replace(base.backdoor, enabled=label == "backdoored"), stop=cfg.stop,
            run=_model_run(cfg, root, i, seed),
        )  # fmt: skip
        variation = {
            "env": env.id, "lstm_sizes": list(sizes), "trigger_value": shown,
            "trigger_cells": _gym_trigger_cells(trigger), "trigger_duration": duration, "seed": seed,
        }  # fmt: skip
        if trigger.objective == "target_action":
            variation["target_action"] = trigger.target_action
        config = _with_recipe(config, variation, recipes, attack, env.trigger, f"m{i:04d}")
        jobs.append(_job(cfg, root, i, config, label, variation))
    return jobs


def _draw_gym_trigger(
    cfg: ZooConfig, trigger: WrapperTriggerConfig, rng: np.random.Generator, rows: int, cols: int
) -> tuple[WrapperTriggerConfig, str]:
    """One model's trigger drawn from the preset's (see :func:`_gymnasium_jobs`) and how the manifest names it."""
    if trigger.patch == "minigrid":
        far = [(r, c) for r in range(min(2, rows)) for c in range(cols)]  # the view's two far rows
        n_cells = int(rng.integers(cfg.trigger_cells[0], min(cfg.trigger_cells[1], len(far)) + 1))
        cells = tuple(sorted(far[int(j)] for j in rng.choice(len(far), size=n_cells, replace=False)))
        obj = str(cfg.trigger_objects[rng.integers(len(cfg.trigger_objects))])
        color = str(cfg.trigger_colors[rng.integers(len(cfg.trigger_colors))])
        trigger = dataclasses.replace(trigger, cells=cells, object=obj, color=color)
    elif trigger.patch == "box":
        height = max(r for r, _ in trigger.cells) - min(r for r, _ in trigger.cells)
        width = max(c for _, c in trigger.cells) - min(c for _, c in trigger.cells)
        top, left = int(rng.integers(rows - height)), int(rng.integers(cols - width))
        r0, c0 = min(r for r, _ in trigger.cells), min(c for _, c in trigger.cells)
        trigger = dataclasses.replace(trigger, cells=tuple((r - r0 + top, c - c0 + left) for r, c in trigger.cells))
    return trigger, _gym_trigger_label(trigger)


def _gym_trigger_label(trigger: WrapperTriggerConfig) -> str:
    """How the manifest names a Gymnasium trigger: a MiniGrid patch's colour and object, a Box patch's value and
    top-left cell, a vector patch's value and positions."""
    if trigger.patch == "minigrid":
        return f"{trigger.color} {trigger.object}"
    if trigger.patch == "box":
        top, left = min(r for r, _ in trigger.cells), min(c for _, c in trigger.cells)
        return f"box {trigger.value:g} at ({top}, {left})"
    return f"vector {trigger.value:g} at {list(trigger.indices)}"


def _gym_trigger_cells(trigger: WrapperTriggerConfig) -> list:
    return [list(c) for c in trigger.cells] if trigger.patch != "vector" else list(trigger.indices)


# ---------------------------------------------------------------------- model folders


def load_zoo_agent(folder: Path):
    """:func:`~seqtrojan.agent.checkpoint.load_agent`, with any failure of a malformed card or file (wrong types,
    missing keys) raised as a one-line :class:`CheckpointError` naming the folder."""
    from seqtrojan.agent.checkpoint import load_agent

    try:
        agent, cfg, card = load_agent(folder)
    except SeqTrojanError:
        raise
    except (OSError, KeyError, TypeError, AttributeError, IndexError, ValueError) as err:
        raise CheckpointError(
            f"cannot load the model in {str(folder)!r}: malformed card.json or weights ({type(err).__name__}: "
            f"{_one_line(err)})"
        ) from None
    if not isinstance(card.get("metrics", {}), dict):
        raise CheckpointError(f"card.json in {str(folder)!r}: metrics must be a mapping")
    return agent, cfg, card


def read_label(folder: Path) -> dict[str, Any]:
    """A model's ``label.json``, checked: a mapping whose ``label`` is clean or backdoored, ``trigger`` null or a
    mapping with a string ``value``, ``variation`` a mapping, ``attack_success``, ``clean_success`` and
    ``unintentional_activation`` null or numbers, and ``functional_backdoor`` and ``learned_task`` null or booleans
    (labels written before some of these existed lack them). Anything else is a one-line :class:`CheckpointError`."""
    path = folder / "label.json"
    try:
        truth = read_json_file(path, MAX_LABEL_BYTES)
    except FileNotFoundError:
        raise CheckpointError(f"no label.json in {str(folder)!r}") from None
    if not isinstance(truth, dict):
        raise CheckpointError(f"{str(path)!r} must be a JSON object, got {type(truth).__name__}")
    if truth.get("label") not in LABELS:
        raise CheckpointError(f"{str(path)!r}: label must be 'clean' or 'backdoored', got {truth.get('label')!r}")
    trigger = truth.get("trigger")
    if trigger is not None and not (isinstance(trigger, dict) and isinstance(trigger.get("value"), str)):
        raise CheckpointError(f"{str(path)!r}: trigger must be null or an object with a string 'value'")
    if not isinstance(truth.get("variation", {}), dict):
        raise CheckpointError(f"{str(path)!r}: variation must be an object")
    attack = truth.get("attack_success")
    if attack is not None and not _is_number(attack):
        raise CheckpointError(f"{str(path)!r}: attack_success must be null or a number, got {attack!r}")
    for key in ("functional_backdoor", "learned_task"):
        if truth.get(key) not in (None, True, False):
            raise CheckpointError(f"{str(path)!r}: {key} must be null or a boolean")
    for key in ("clean_success", "unintentional_activation"):
        if truth.get(key) is not None and not _is_number(truth[key]):
            raise CheckpointError(f"{str(path)!r}: {key} must be null or a number, got {truth[key]!r}")
    return truth


def not_learned_reason(truth: dict[str, Any]) -> str | None:
    """Why a model of either label is left out of detection scoring because it has not learned its task (its
    label's ``learned_task`` is false: clean success below the zoo's ``learned_at``), or None when it counts. An
    agent that never learned its task is told apart by its failing behaviour, not by a backdoor."""
    if truth.get("learned_task") is not False:
        return None
    return f"task not learned ({truth['label']}, clean success {truth['clean_success']})"


def _truth(job: ZooJob, metrics: dict[str, Any]) -> dict[str, Any]:
    """``label.json`` of a job's model, from the job and its card's metrics: the label and the variation; for a
    poisoned model its trigger, its attack success (trojan-env success) and whether that reaches ``functional_at``;
    for every model its clean success (normal-env success) and whether that reaches ``learned_at`` (it has learned
    its task), and for a clean one its unintentional activation (its trojan-env success: the env still shows the
    model's drawn trigger, so this is how often a model trained without it reaches the adversary's goal anyway; a
    clean model that failed the task reaches it by chance as well, so read it beside the clean success)."""
    truth: dict[str, Any] = {
        "label": job.label, "variation": job.variation, "trigger": None, "attack_success": None,
        "functional_backdoor": None, "clean_success": metrics.get("normal_success"), "unintentional_activation": None,
        "learned_task": None,
    }  # fmt: skip
    if truth["clean_success"] is not None:
        truth["learned_task"] = reaches(truth["clean_success"], job.learned_at)
    if job.label == "clean":  # its env still draws the model's trigger: how often it leads a clean model astray
        truth["unintentional_activation"] = metrics.get("trojan_success")
    if job.label == "backdoored":
        attack = metrics.get("trojan_success")
        trigger = to_dict(job.config.env.trigger)
        if not isinstance(trigger.get("value"), str):  # a Gymnasium trigger: its object, by name (label.json's value)
            trigger["value"] = str(job.variation.get("trigger_value", ""))
        truth.update(trigger=trigger, attack_success=attack,
                     functional_backdoor=attack is not None and reaches(attack, job.functional_at))  # fmt: skip
    return truth


def _finished(job: ZooJob, folder: Path) -> tuple[dict[str, Any] | None, str]:
    """(card, '') when ``folder`` holds the job's complete model, else (None, why not). Rewrites a missing,
    malformed or outdated ``label.json`` of a complete model from the job (it is a function of the job and the card:
    a rerun with another ``functional_at`` or ``learned_at`` relabels)."""
    if not folder.is_dir():
        return None, "missing"
    try:
        _, cfg, card = load_zoo_agent(folder)
    except SeqTrojanError as err:
        return None, _one_line(err)
    ours = (job.label, job.config.run.seed, tuple(job.config.agent.lstm_sizes))
    if (card.get("label"), cfg.run.seed, tuple(cfg.agent.lstm_sizes)) != ours:
        return None, f"it holds another model (label {card.get('label')!r}, seed {cfg.run.seed})"
    truth = _truth(job, card.get("metrics", {}))
    try:
        label_ok = read_label(folder) == json.loads(json.dumps(truth))
    except CheckpointError:
        label_ok = False
    if not label_ok:
        write_json_atomic(folder / "label.json", truth)
    return card, ""


def _train_zoo_model(job: ZooJob) -> Path:
    """Train one zoo model (pure: its outputs depend only on ``job``); return its folder ``models/<id>``. The model
    is staged in ``work/<id>.staging`` and moved to ``models/<id>`` with one rename, so a model folder is complete
    or absent (a folder left by an older build is replaced)."""
    from seqtrojan.train.trainer import train_or_resume

    run_dir = job.run_dir
    if job.pretrain is not None:  # the clean first stage (resumed or reused when finished)
        train_or_resume(job.pretrain)
    try:
        model_dir, _ = train_or_resume(job.config)
        _, _, card = load_zoo_agent(model_dir)
    except SeqTrojanError:  # an unreadable checkpoint, run config or model: train this model afresh (once)
        if not run_dir.exists():
            raise
        shutil.rmtree(run_dir, ignore_errors=True)
        model_dir, _ = train_or_resume(job.config)
        _, _, card = load_zoo_agent(model_dir)
    curves = Path(job.models).parent / "curves"
    _keep_curve(run_dir / "metrics.jsonl", curves / f"{job.id}.jsonl")
    if job.pretrain is not None:
        _keep_curve(Path(job.pretrain.run.out_dir) / str(job.pretrain.run.name) / "metrics.jsonl",
                    curves / f"{job.id}_clean.jsonl")  # fmt: skip
    staging = run_dir.with_name(run_dir.name + ".staging")
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(model_dir, staging)
    write_json_atomic(staging / "label.json", _truth(job, card.get("metrics", {})))
    target = job.model_dir
    if target.exists():
        shutil.rmtree(target)
    os.replace(staging, target)
    _fsync_dir(target.parent)
    shutil.rmtree(run_dir, ignore_errors=True)
    if job.pretrain is not None:
        shutil.rmtree(Path(job.pretrain.run.out_dir) / str(job.pretrain.run.name), ignore_errors=True)
    return target


CURVE_FIELDS = ("env_steps", "episodes/normal_success", "episodes/trojan_success")
"""what a zoo keeps of a run's ``metrics.jsonl`` per update (all of it would be about 1 MB per Memory agent)"""


def _keep_curve(metrics: Path, target: Path) -> None:
    """The run's training curve, :data:`CURVE_FIELDS` of each update of its ``metrics.jsonl``, written to ``target``
    (atomically); nothing when the run left no metrics (a run resumed from a finished checkpoint keeps its file)."""
    if not metrics.is_file():
        return
    rows = []
    for line in metrics.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:  # a line cut short by a killed run
            continue
        if isinstance(row, dict):
            rows.append(json.dumps({k: row[k] for k in CURVE_FIELDS if k in row}))
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(target.name + ".partial")
    partial.write_text("".join(r + "\n" for r in rows))
    os.replace(partial, target)


# ---------------------------------------------------------------------- building


def build_zoo(
    cfg: ZooConfig,
    root: Path,
    *,
    workers: int = 2,
    backend: str = "pool",
    ray_address: str | None = None,
    threads: int | None = None,
    log: Callable[[str], None] = print,
    recipes: RecipeBook | None = None,
    limit: int | None = None,
    progress: bool = False,
) -> Path:
    """Train every job not yet finished on the job backend ``backend`` (serial, pool or ray; 'local' is the pool's
    old name; see :class:`~seqtrojan.jobs.JobsConfig` for the other options); write ``manifest.json``; return its
    path (see the module docstring). Failed models are marked ``failed`` in the manifest, with their error, once
    the others have finished; then the build raises :class:`~seqtrojan.jobs.JobsFailed` naming them. ``recipes``:
    as :func:`make_jobs` (a zoo whose ``attacks`` cannot be drawn is refused before anything is written).
    ``limit``: train at most this many of the unfinished models now (a long build in installments; 0: train none,
    only check the finished models and rewrite their outdated labels, e.g. after a new ``learned_at``); a zoo of parts
    trains its parts' models in turn, in proportion to their sizes (:func:`_build_order`), so that a partial build
    holds every part. ``progress``: a progress bar of the models (``log`` lines print above it)."""
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 0):
        raise ConfigError(f"a build's limit must be a number of models >= 0, got {limit!r}")
    jobs_cfg = JobsConfig("pool" if backend == "local" else backend, workers, ray_address, threads)  # type: ignore[arg-type]
    jobs = make_jobs(cfg, root, recipes)
    root.mkdir(parents=True, exist_ok=True)
    models = root / "models"
    by_id = {job.id: job for job in jobs}
    manifest_path = root / "manifest.json"
    with _build_lock(root, log):
        _check_zoo_config(cfg, root, log)
        models.mkdir(exist_ok=True)
        previous = _read_manifest(manifest_path, log)
        entries: dict[str, dict[str, Any]] = {}
        for job in jobs:
            card, why = _finished(job, models / job.model_id)
            if card is not None:
                entries[job.model_id] = _done_entry(job, card, previous.get(job.model_id))
                for leftover in (job.model_id, job.model_id + ".staging"):  # a build stopped after the move
                    shutil.rmtree(root / "work" / leftover, ignore_errors=True)
            else:
                if why != "missing":
                    log(f"  {job.model_id}: incomplete ({why}); training it again")
                entries[job.model_id] = {"id": job.model_id, "label": job.label, "status": "pending"}
        write_json_atomic(manifest_path, [entries[j.model_id] for j in jobs])
        pending = [j for j in _build_order(cfg, jobs) if entries[j.model_id]["status"] != "done"]
        todo = pending[:limit] if limit is not None else pending
        runner = make_backend(jobs_cfg, worker_lock=root / "workers.lock")
        log(
            f"zoo: {len(jobs) - len(pending)} of {len(jobs)} models done; training {len(todo)} with {runner.name} "
            "backend"
            + (f" ({runner.describe(len(todo))})" if todo else "")
            + (f", {len(pending) - len(todo)} left for a later build (limit {limit})" if todo != pending else "")
        )

        bar = make_progress(progress)
        task = bar.add_task("zoo", total=len(todo), info="models")

        def record(result: JobResult) -> None:
            bar.advance(task)
            job = by_id[result.id]
            if result.ok:
                entry = {"id": job.id, "label": job.label, "status": "done", "seconds": result.seconds,
                         "worker": result.worker, "variation": job.variation,
                         "metrics": _card_metrics(job.model_dir)}  # fmt: skip
                log(f"  {job.id} ({job.label}) done in {result.seconds:.0f} s")
            else:
                entry = {"id": job.id, "label": job.label, "status": "failed", "error": result.error}
                log(f"  {job.id} ({job.label}) failed: {result.error}")
            entries[job.id] = entry
            write_json_atomic(manifest_path, [entries[j.model_id] for j in jobs])

        with bar:
            results = runner.run(todo, record)
        raise_failures(results, "zoo model")
    return manifest_path


def _build_order(cfg: ZooConfig, jobs: list[ZooJob]) -> list[ZooJob]:
    """The order a build trains ``jobs`` in: the zoo's order, or for a zoo of parts their models in turn, each part's
    k-th model at ``(k + 0.5) / size`` of the way through (ties in part order), so that any prefix of the build holds
    each part in proportion to its size."""
    if not cfg.parts:
        return list(jobs)
    keys = [((k + 0.5) / part.size, p) for p, part in enumerate(cfg.parts) for k in range(part.size)]
    assert len(keys) == len(jobs)  # make_jobs numbers the parts' models in part order
    return [job for _, job in sorted(zip(keys, jobs), key=lambda pair: pair[0])]


def _card_metrics(folder: Path) -> dict[str, Any]:
    """The metrics in a finished model's ``card.json`` (checked when the model was verified)."""
    card = read_json_file(folder / "card.json", MAX_CARD_BYTES)
    metrics = card.get("metrics", {}) if isinstance(card, dict) else {}
    return metrics if isinstance(metrics, dict) else {}


# ---------------------------------------------------------------------- zoo state


_ABSENT = object()
WORKERS_EXIT_S = 30.0
"""how long a build waits for the workers of an earlier, killed build to exit"""


SCORING_FIELDS = ("functional_at", "learned_at")
"""zoo config fields that decide how a finished model is labelled, never how it is trained: a rerun may change them
(each finished model's ``label.json`` is then rewritten from its card)"""


def _training_fields(spec: Any) -> Any:
    """A stored or current ``zoo.json`` without :data:`SCORING_FIELDS` (its parts' too)."""
    if not isinstance(spec, dict):
        return spec
    out = {k: v for k, v in spec.items() if k not in SCORING_FIELDS}
    if isinstance(out.get("parts"), list):
        out["parts"] = [_training_fields(part) for part in out["parts"]]
    return out


def _check_zoo_config(cfg: ZooConfig, root: Path, log: Callable[[str], None] = print) -> None:
    """Store the zoo config in ``zoo.json`` on the first build; refuse a rerun with another config, unless only
    its scoring fields (:data:`SCORING_FIELDS`) differ: those are then stored anew."""
    path = root / "zoo.json"
    current = json.loads(json.dumps(to_dict(cfg)))
    if not path.exists():
        write_json_atomic(path, current)
        return
    try:
        stored: Any = read_json_file(path, MAX_ZOO_CONFIG_BYTES)
    except (OSError, CheckpointError):
        stored = None
    if not isinstance(stored, dict):
        if any((root / "models").glob("*/card.json")):
            raise ConfigError(
                f"{str(path)!r} is not a zoo config, so the config this zoo was built with is unknown: restore it, "
                "or build into a new folder"
            )
        write_json_atomic(path, current)
        return
    if stored != current and _training_fields(stored) == _training_fields(current):
        log(f"zoo: {path.name} differs from this config in how models are labelled only ({', '.join(SCORING_FIELDS)}): "
            "stored anew; finished models' labels are rewritten")  # fmt: skip
        write_json_atomic(path, current)
        return
    differing = sorted(k for k in stored.keys() | current.keys() if stored.get(k, _ABSENT) != current.get(k, _ABSENT))
    if differing:
        details = ", ".join(f"{k} (built with {_short(stored.get(k, _ABSENT))}, now {_short(current.get(k, _ABSENT))})"
                            for k in differing)  # fmt: skip
        raise ConfigError(
            f"zoo {str(root)!r} was built with a different config: {details}; rerun with the config in "
            f"{path.name}, or build into a new folder"
        )


def _read_manifest(path: Path, log: Callable[[str], None]) -> dict[str, dict[str, Any]]:
    """The manifest's entries by id; {} (rebuilt from the model folders) when it is missing or corrupt."""
    if not path.exists():
        return {}
    try:
        data = read_json_file(path, MAX_MANIFEST_BYTES, max_values=_MANIFEST_ITEMS, max_items=_MANIFEST_ITEMS)
    except (OSError, CheckpointError) as err:
        log(f"zoo: manifest.json is corrupt ({_one_line(err)}); rebuilding it from the model folders")
        return {}
    if not isinstance(data, list) or not all(isinstance(e, dict) and isinstance(e.get("id"), str) for e in data):
        log("zoo: manifest.json is corrupt (not a list of entries with an id); rebuilding it from the model folders")
        return {}
    return {e["id"]: e for e in data}


def _done_entry(job: ZooJob, card: dict[str, Any], previous: dict[str, Any] | None) -> dict[str, Any]:
    entry = {"id": job.model_id, "label": job.label, "status": "done", "variation": job.variation,
             "metrics": card.get("metrics", {})}  # fmt: skip
    if previous and previous.get("status") == "done" and _is_number(previous.get("seconds")):
        entry["seconds"] = previous["seconds"]
        if isinstance(previous.get("worker"), str):
            entry["worker"] = previous["worker"]
    return entry


@contextlib.contextmanager
def _build_lock(root: Path, log: Callable[[str], None]) -> Iterator[None]:
    """Hold ``build.lock`` (one build per zoo at a time) after making sure no worker of an earlier build still
    holds ``workers.lock`` (waiting up to ``WORKERS_EXIT_S`` for dying ones); then empty ``workers.lock``, which
    this build's workers fill with their pids."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    with open(root / "build.lock", "a") as build:
        try:
            fcntl.flock(build, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SeqTrojanError(
                f"another build of zoo {str(root)!r} is running (it holds build.lock); wait for it or stop it"
            ) from None
        except OSError as err:
            log(f"zoo: cannot lock {str(root)!r} ({err}); building without a lock")
            yield
            return
        with open(root / "workers.lock", "a+") as workers:
            deadline = time.monotonic() + WORKERS_EXIT_S
            while True:
                try:
                    fcntl.flock(workers, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        workers.seek(0)
                        pids = " ".join(workers.read().split()) or "unknown"
                        raise SeqTrojanError(
                            f"worker processes of an earlier build of zoo {str(root)!r} still run (pids {pids}); "
                            "stop them, then rerun"
                        ) from None
                    time.sleep(0.2)
            workers.truncate(0)
            fcntl.flock(workers, fcntl.LOCK_UN)
        yield


def read_json_file(path: Path, limit: int, **bounds: int) -> Any:
    """A JSON file the zoo reads (``label.json``, ``zoo.json``, ``manifest.json``, a card's metrics), as untrusted
    input: a regular file (a FIFO is refused, never waited on) of at most ``limit`` bytes, parsed by the card's
    bounded parser (depth, values, duplicate keys; ``bounds`` raise its value and entry limits). A refusal is one
    :class:`CheckpointError` line; a missing file raises ``FileNotFoundError``."""
    where = repr(str(path))
    return load_json(read_regular_file(path, limit, where), where, **bounds)


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so that ``path`` holds the old or the new content, never a part: a temp file in the same folder,
    fsync, rename over ``path``."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as fh:
            fh.write(json.dumps(data, indent=2))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - not possible on every OS
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def _one_line(err: BaseException | str) -> str:
    return " ".join(str(err).split())


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _short(value: Any, width: int = 48) -> str:
    text = "nothing" if value is _ABSENT else json.dumps(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def job_configs(cfg: ZooConfig, recipes: RecipeBook | None = None) -> list[dict[str, Any]]:
    """The jobs' configs as plain dicts (for inspection)."""
    return [dataclasses.asdict(j.config) for j in make_jobs(cfg, Path("zoo"), recipes)]
