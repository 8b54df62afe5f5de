"""A zoo model's attack recipe: checked against the zoo, and applied to the model's drawn config.

The recipes are registered in :mod:`seqtrojan.experiments.attacks` (``ATTACKS``), a package above this one (its
studies build zoos), so the zoo cannot import them: whoever builds a zoo that draws recipes passes the registry in
(``seqtrojan zoo build`` passes ``RECIPES``, which also reads ``recipe/value``: a recipe at another strength), and
this module reads it only through :class:`RecipeBook`. Reading a zoo back (``zoo.json``, the labels, the
leaderboard) needs no registry, so a zoo stays readable after a recipe is renamed.

How a recipe meets the model's drawn trigger patch (:func:`apply_recipe`): a recipe that draws a trigger of its own
-- applied to a config with a reference trigger (the grid world's default; a Gymnasium zoo's preset trigger), it
changes where or what that trigger draws (:data:`GRID_PATTERN`, :data:`GYM_PATTERN`) -- replaces the drawn patch,
and the drawn model keeps its other trigger settings (the step ranges the trigger shows in, unless the recipe sets
them); any other recipe (training penalties, a delay) is applied on top of the drawn patch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Protocol

from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import TriggerConfig
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.world.config import GymnasiumEnvConfig

KNOB_SEPARATOR = "/"
"""``recipe/value``: a registered recipe with its strength (its knob) at ``value``, as the matrix writes it"""
GRID_PATTERN = ("cells", "value", "values", "sequence")
"""the grid-world trigger fields that say where and what it draws (a recipe that changes one brings its own)"""
GYM_PATTERN = ("patch", "cells", "object", "color", "value", "key", "indices")
"""the same for a Gymnasium env's trigger wrapper"""
SHOWN_FOR = "duration"
"""taken with a recipe's own pattern (a sequence shows each frame once), never drawn beside it"""


class Recipe(Protocol):
    """What the zoo reads of a registered attack (:class:`seqtrojan.experiments.attacks.Attack`)."""

    @property
    def configure(self) -> Callable[[ExperimentConfig], ExperimentConfig]: ...

    @property
    def from_clean(self) -> bool: ...

    def applies_to(self, cfg: ExperimentConfig) -> bool: ...


class RecipeBook(Protocol):
    """The registry of recipes (``RECIPES``): the registered names in order, and the recipe of a name, registered
    or at another strength (``recipe/value``)."""

    def names(self) -> tuple[str, ...]: ...

    def get(self, name: str) -> Recipe: ...


def check_recipes(
    names: tuple[str, ...], recipes: RecipeBook | None, reference: ExperimentConfig, pretrained: bool = False
) -> None:
    """Refuse, in one line, a zoo's ``attacks`` that cannot be drawn: no registry given, an unregistered name, a
    recipe that does not apply to the zoo's env (``reference``: a backdoored config of it), or one that starts from
    a trained clean agent (``from_clean``) in a zoo whose models have no clean first stage (``pretrained``: the
    zoo's ``pretrain_steps``). With that stage, a from-clean recipe's clean twin is the model's own first stage (its
    ``run.init_from``, which the second stage starts from in any case); without it the twin would be another job's
    model, which a zoo's independent jobs never wait for."""
    if not names:
        return
    if recipes is None:
        raise ConfigError(
            f"zoo attacks {list(names)} are registered recipes (seqtrojan.experiments.attacks.RECIPES), which this "
            "build was not given: build it with `seqtrojan zoo build`, or pass recipes=RECIPES"
        )
    registered = recipes.names()
    unknown = [n for n in names if n.partition(KNOB_SEPARATOR)[0] not in registered]
    if unknown:
        raise ConfigError(f"zoo attacks: unknown recipe(s) {unknown}; registered: {', '.join(registered)}")
    for name in names:  # a recipe at another strength (recipe/value): its knob and value checked here
        try:
            recipes.get(name)
        except SeqTrojanError as err:
            raise ConfigError(f"zoo attacks: {err}") from None
    from_clean = [n for n in names if recipes.get(n).from_clean]
    if from_clean and not pretrained:
        raise ConfigError(
            f"zoo attacks: {from_clean} add a backdoor to a trained clean agent (run.init_from), and a zoo's models "
            "are independent jobs that never wait for one; set pretrain_steps (each model's clean first stage is "
            "then its clean agent) or choose recipes trained from scratch"
        )
    elsewhere = [n for n in names if not recipes.get(n).applies_to(reference)]
    if elsewhere:
        env = reference.env.id if isinstance(reference.env, GymnasiumEnvConfig) else "the grid world"
        raise ConfigError(f"zoo attacks: {elsewhere} do not apply to this zoo's env, {env}")


def apply_recipe(config: ExperimentConfig, recipe: Recipe, reference: Any) -> tuple[ExperimentConfig, bool]:
    """The model's config with ``recipe`` applied, and whether the recipe's own trigger replaced the drawn one
    (``reference``: the trigger the recipes are written against; see the module docstring). A combination the
    config refuses raises its :class:`~seqtrojan.errors.ConfigError`."""
    drawn = config.env.trigger
    assert drawn is not None  # a backdoored config's trigger
    pattern = GYM_PATTERN if isinstance(config.env, GymnasiumEnvConfig) else GRID_PATTERN
    probe = recipe.configure(_with_trigger(config, reference)).env.trigger
    if all(getattr(probe, f) == getattr(reference, f) for f in pattern):
        return recipe.configure(config), False
    start = dataclasses.replace(drawn, **{f: getattr(probe, f) for f in (*pattern, SHOWN_FOR)})
    return recipe.configure(_with_trigger(config, start)), True


def grid_trigger_variation(trigger: TriggerConfig) -> dict[str, Any]:
    """How the manifest records a grid-world trigger: what it draws (its code, a per-cell patch's codes, a
    sequence's length and codes: :attr:`TriggerConfig.drawn_codes`), its cells (a sequence's, all frames together;
    None: the whole view) and the steps it shows."""
    if trigger.sequence is not None:
        cells: Any = sorted({tuple(c) for frame in trigger.sequence for c in frame.cells})
    else:
        cells = trigger.cells
    return {
        "trigger_value": trigger.drawn_codes,
        "trigger_cells": None if cells is None else [list(c) for c in cells],
        "trigger_duration": trigger.shown_steps,
    }


def _with_trigger(config: ExperimentConfig, trigger: Any) -> ExperimentConfig:
    return dataclasses.replace(config, env=dataclasses.replace(config.env, trigger=trigger))
