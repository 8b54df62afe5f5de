"""A zoo that draws attack recipes: each backdoored model's recipe drawn after every other draw, combined with its
drawn patch by the rule of :mod:`seqtrojan.zoo.recipes`, recorded as its ``attack``; the recipes a zoo cannot draw
refused in one line; a zoo without ``attacks`` exactly as before."""

from __future__ import annotations

import dataclasses
import json

import pytest

from seqtrojan.config import ExperimentConfig
from seqtrojan.env import GridSpec
from seqtrojan.env.config import TriggerConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS, RECIPES
from seqtrojan.zoo.build import ZooConfig, build_zoo, make_jobs
from seqtrojan.zoo.recipes import GRID_PATTERN

SCRATCH = tuple(name for name, attack in ATTACKS.items() if not attack.from_clean)
"""every registered recipe trained from scratch (all of them apply to the grid world)"""
PLAIN = ZooConfig(clean=8, backdoored=120, total_steps=1024, cells=("lstm", "gru"))
"""enough poisoned models that every registered recipe is drawn (11 recipes miss one with probability about 1e-4)"""


def own_pattern(name: str) -> bool:
    """Whether the recipe draws a trigger of its own: it changes where or what the default trigger draws."""
    probe = ATTACKS.get(name).configure(ExperimentConfig()).env.trigger
    return any(getattr(probe, f) != getattr(TriggerConfig(), f) for f in GRID_PATTERN)


def test_the_recipe_is_drawn_after_every_other_draw_and_combined_with_the_drawn_patch(tmp_path):
    plain = make_jobs(PLAIN, tmp_path)
    drawn = make_jobs(dataclasses.replace(PLAIN, attacks=SCRATCH), tmp_path, ATTACKS)
    assert {j.variation["attack"] for j in drawn if j.label == "backdoored"} == set(SCRATCH)
    assert {own_pattern(n) for n in SCRATCH} == {True, False}  # both kinds of recipe are exercised
    for a, b in zip(plain, drawn):
        same = ("lstm_sizes", "curriculum", "seed", "cell")
        assert {k: b.variation.get(k) for k in same} == {k: a.variation.get(k) for k in same}
        assert (b.config.agent, b.config.curriculum) == (a.config.agent, a.config.curriculum)
        assert b.config.run == a.config.run
        if b.label == "clean":  # no recipe, the same training settings
            assert b.config == a.config and b.variation == {**a.variation, "attack": "none"}
            continue
        name = b.variation["attack"]
        default = dataclasses.replace(a.config, env=dataclasses.replace(a.config.env, trigger=TriggerConfig()))
        recipe = ATTACKS.get(name).configure(default)  # the recipe on the plain model, for its other sections
        assert (b.config.attack, b.config.backdoor, b.config.ppo) == (recipe.attack, recipe.backdoor, recipe.ppo)
        mine, theirs = b.config.env.trigger, a.config.env.trigger
        assert (mine.train_steps, mine.eval_steps) == (theirs.train_steps, theirs.eval_steps)  # the drawn ranges
        if own_pattern(name):  # the recipe's trigger replaces the drawn patch; the manifest says what it shows
            default_probe = ATTACKS.get(name).configure(ExperimentConfig()).env.trigger
            assert all(getattr(mine, f) == getattr(default_probe, f) for f in (*GRID_PATTERN, "duration", "decoys"))
            assert b.variation["trigger_value"] == mine.drawn_codes != a.variation["trigger_value"]
        else:  # on top of the drawn patch
            assert all(getattr(mine, f) == getattr(theirs, f) for f in (*GRID_PATTERN, "duration"))
            assert {k: v for k, v in b.variation.items() if k != "attack"} == a.variation
    delayed = [j for j in drawn if j.variation.get("attack") == "delayed"]
    assert delayed and all(j.config.env.trigger.delay == 3 for j in delayed)  # a setting layered on the patch


def test_a_zoo_without_attacks_is_the_zoo_it_was(tmp_path):
    """Nothing of the field reaches a zoo that does not use it: its jobs, its variations, its zoo.json."""
    plain = make_jobs(PLAIN, tmp_path)
    assert plain == make_jobs(PLAIN, tmp_path, ATTACKS)  # the registry changes nothing without attacks
    assert all("attack" not in j.variation for j in plain)
    assert "attacks" not in PLAIN.serde_dump()
    assert dataclasses.replace(PLAIN, attacks=("sequence",)).serde_dump()["attacks"] == ["sequence"]


def test_recipes_a_zoo_cannot_draw_are_refused_in_one_line(tmp_path):
    cases = [
        (ZooConfig(attacks=("sequenc",)), ATTACKS, r"unknown recipe\(s\) \['sequenc'\]; registered: dedicated_code"),
        (ZooConfig(attacks=("sequence", "ewc")), ATTACKS, r"\['ewc'\] add a backdoor to a trained clean agent"),
        (ZooConfig(attacks=("sequence",), env_preset="minigrid_two_goals"), ATTACKS,
         r"\['sequence'\] do not apply to this zoo's env, seqtrojan/MiniGridTwoGoals-v0"),
        (ZooConfig(attacks=("sequence",)), None, "which this build was not given"),
    ]  # fmt: skip
    for cfg, recipes, message in cases:
        with pytest.raises(ConfigError, match=message) as err:
            make_jobs(cfg, tmp_path, recipes)
        assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="not given"):  # refused before anything is written
        build_zoo(ZooConfig(attacks=("sequence",)), tmp_path / "zoo", log=lambda *_: None)
    assert not (tmp_path / "zoo").exists()
    twice, wrong = "name a recipe twice", "must be recipe names"
    for bad, message in ((("sequence", "sequence"), twice), (("ewc/3", "ewc/3.0"), twice), (("two words",), wrong)):
        with pytest.raises(ConfigError, match=message):
            ZooConfig(attacks=bad)
    with pytest.raises(ConfigError, match=r"holdout attack \['combined'\] must be among the zoo's attacks"):
        ZooConfig(attacks=("sequence",), holdout={"attack": ("combined",)})


def test_a_zoo_draws_recipes_at_other_strengths(tmp_path):
    """``recipe/value`` (the matrix's notation): the recipe with its knob at that value, recorded under that name;
    a value the knob cannot take, or a recipe without a knob, refused in one line."""
    attacks = ("state_camouflage/1.5", "mahalanobis_camouflage")
    cfg = ZooConfig(clean=2, backdoored=10, total_steps=1024, attacks=attacks)
    jobs = make_jobs(cfg, tmp_path, RECIPES)
    drawn = {j.variation["attack"]: j.config.attack for j in jobs if j.label == "backdoored"}
    assert set(drawn) == {"state_camouflage/1.5", "mahalanobis_camouflage"}
    assert drawn["state_camouflage/1.5"].state_camouflage.margin == 1.5
    assert drawn["state_camouflage/1.5"].state_camouflage.weight == 5.0  # the recipe's other settings kept
    assert drawn["mahalanobis_camouflage"].mahalanobis_camouflage.weight == 5.0
    assert make_jobs(dataclasses.replace(cfg, attacks=("state_camouflage",)), tmp_path, RECIPES) == make_jobs(
        dataclasses.replace(cfg, attacks=("state_camouflage",)), tmp_path, ATTACKS
    )  # a plain name draws what the registry draws
    for attacks, message in (
        (("sequence/2",), r"zoo attacks: attack 'sequence/2': sequence has no knob to set"),
        (("sequenc/2",), r"unknown recipe\(s\) \['sequenc/2'\]"),
        (("state_camouflage/1.5",), r"unknown attack 'state_camouflage/1.5'"),  # ATTACKS reads no strengths
    ):
        recipes = ATTACKS if attacks == ("state_camouflage/1.5",) else RECIPES
        with pytest.raises(ConfigError, match=message) as err:
            make_jobs(dataclasses.replace(cfg, attacks=attacks), tmp_path, recipes)
        assert "\n" not in str(err.value)
    for bad in ("state_camouflage/", "state_camouflage/-1", "state_camouflage/x", "../state_camouflage/1"):
        with pytest.raises(ConfigError, match="must be recipe names"):
            ZooConfig(attacks=(bad,))


def test_a_gymnasium_zoo_draws_the_recipes_that_apply_to_it(tmp_path):
    cfg = ZooConfig(clean=2, backdoored=6, env_preset="minigrid_two_goals", attacks=("delayed", "state_camouflage"))
    plain = make_jobs(dataclasses.replace(cfg, attacks=()), tmp_path)
    for a, b in zip(plain, make_jobs(cfg, tmp_path, ATTACKS)):
        assert {k: v for k, v in b.variation.items() if k != "attack"} == a.variation  # on top of the drawn patch
        if b.variation["attack"] == "delayed":
            assert b.config.env.trigger == dataclasses.replace(a.config.env.trigger, delay=3)
        elif b.variation["attack"] == "state_camouflage":
            assert b.config.attack.state_camouflage.weight > 0 and b.config.env == a.config.env


def test_a_recipe_that_does_not_combine_with_a_drawn_model_is_named_in_one_line(tmp_path):
    """A recipe (here a test's own, as a user could register) whose config the drawn model refuses: the error names
    the model and the recipe."""

    def decoys_alone(cfg: ExperimentConfig) -> ExperimentConfig:  # decoys need a trigger longer than one step
        trigger = cfg.grid_env.trigger
        return dataclasses.replace(
            cfg, env=dataclasses.replace(cfg.grid_env, trigger=dataclasses.replace(
                trigger, decoys=dataclasses.replace(trigger.decoys, probability=0.5))))  # fmt: skip

    book = {"decoys_alone": dataclasses.replace(ATTACKS.get("delayed"), configure=decoys_alone)}
    recipes = type("Book", (), {"names": lambda self: tuple(book), "get": lambda self, name: book[name]})()
    with pytest.raises(ConfigError, match=r"zoo model m0000, attack 'decoys_alone': .*decoys") as err:
        make_jobs(ZooConfig(clean=0, backdoored=1, attacks=("decoys_alone",)), tmp_path, recipes)
    assert "\n" not in str(err.value)


def test_the_attack_benchmark_preset_validates(tmp_path):
    from seqtrojan.presets import resolve_preset
    from seqtrojan.serde import from_dict, load_yaml

    cfg = from_dict(ZooConfig, load_yaml(resolve_preset("benchmark_attacks")), "")
    jobs = make_jobs(cfg, tmp_path, ATTACKS)
    held = [j for j in jobs if j.variation.get("attack") in cfg.holdout["attack"]]
    assert held and set(cfg.attacks) <= set(SCRATCH) and {own_pattern(n) for n in cfg.attacks} == {True, False}
    assert len(jobs) == cfg.size and all(j.config.curriculum.stages[-1] == GridSpec(7, 3) for j in jobs)
    assert json.loads(json.dumps([j.variation for j in jobs]))  # the manifest's variations are plain JSON


FROM_CLEAN = tuple(name for name, attack in ATTACKS.items() if attack.from_clean)


def test_a_from_clean_recipe_starts_from_the_model_s_own_clean_stage(tmp_path):
    """With ``pretrain_steps`` a from-clean recipe is drawn: its clean agent (``run.init_from``, which its penalties
    compare against) is the model's own first stage, and that stage is clean, from scratch and penalty-free."""
    with pytest.raises(ConfigError, match="set pretrain_steps"):
        make_jobs(ZooConfig(clean=1, backdoored=8, attacks=FROM_CLEAN, mixing="fixed"), tmp_path, ATTACKS)
    cfg = ZooConfig(clean=2, backdoored=40, total_steps=4096, pretrain_steps=2048, mixing="fixed", attacks=FROM_CLEAN)
    jobs = make_jobs(cfg, tmp_path, ATTACKS)
    assert {j.variation["attack"] for j in jobs if j.label == "backdoored"} == set(FROM_CLEAN)
    for job in jobs:
        stage = tmp_path / "work" / f"{job.id}_clean" / "model"
        assert job.config.run.init_from == str(stage) and job.pretrain.run.init_from is None
        assert not job.pretrain.backdoor.enabled and job.pretrain.attack == type(job.config.attack)()
        assert job.pretrain.ppo.total_steps == 2048 and job.config.ppo.total_steps == 4096
        if job.variation["attack"] == "weight_camouflage":  # the recipe's warm-up is half of the second stage
            assert job.config.attack.weight_camouflage.warmup_steps == 2048
        if job.variation["attack"] == "ewc":
            assert job.config.attack.ewc.weight == 100.0
    gym = ZooConfig(clean=1, backdoored=12, env_preset="minigrid_memory_backdoor", total_steps=4096,
                    pretrain_steps=2048, attacks=("weight_camouflage", "switch_camouflage"))  # fmt: skip
    for job in make_jobs(gym, tmp_path, ATTACKS):
        assert job.config.run.init_from == str(tmp_path / "work" / f"{job.id}_clean" / "model")


def test_the_memory_attack_benchmark_preset_draws_every_attack_into_both_splits(tmp_path):
    """The preset's seed was chosen (docs/benchmark.md) so that every recipe is drawn at least twice and the split
    left for train/test and the holdout both hold clean and poisoned models: a changed draw breaks it."""
    from collections import Counter

    from seqtrojan.presets import resolve_preset
    from seqtrojan.serde import from_dict, load_yaml

    cfg = from_dict(ZooConfig, load_yaml(resolve_preset("benchmark_minigrid_memory_attacks")), "")
    jobs = make_jobs(cfg, tmp_path, ATTACKS)
    drawn = Counter(j.variation["attack"] for j in jobs if j.label == "backdoored")
    assert set(drawn) == set(cfg.attacks) and min(drawn.values()) >= 2
    held = [j.variation["lstm_sizes"] == [64, 32] or j.variation["attack"] == "weight_camouflage" for j in jobs]
    for in_holdout in (False, True):
        labels = Counter(j.label for j, h in zip(jobs, held) if h == in_holdout)
        assert min(labels["clean"], labels["backdoored"]) >= 6


def test_a_recipe_that_does_not_apply_to_a_model_s_drawn_cell_is_refused_before_anything_is_trained(tmp_path):
    """The probe camouflage replays a recurrent state, which a Transformer does not carry: a zoo that could draw the
    two together is refused when its jobs are made (it used to fail once that model began to train)."""
    cfg = ZooConfig(clean=2, backdoored=20, total_steps=1024, cells=("lstm", "transformer"), attacks=("probe_mimicry",))
    with pytest.raises(ConfigError, match=r"attack 'probe_mimicry' does not apply to its config \(sequence model "
                       r"transformer\)") as err:  # fmt: skip
        make_jobs(cfg, tmp_path, ATTACKS)
    assert "\n" not in str(err.value)
    assert make_jobs(dataclasses.replace(cfg, cells=("lstm", "gru")), tmp_path, ATTACKS)
