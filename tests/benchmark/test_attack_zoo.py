"""A benchmark zoo that draws attack recipes, end to end through the commands of the docs: ``seqtrojan zoo build``
trains each poisoned model with its recipe, ``seqtrojan zoo detect --out`` holds the zoo's held-out recipe back."""

from __future__ import annotations

import json

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.benchmark.leaderboard import LEADERBOARD_FILE, SPLITS_FILE
from seqtrojan.cli import main

RECIPES = ("sequence", "partial_patch", "state_camouflage", "search_decoys")
TINY_ATTACKS = f"""\
# 8 grid-world models trained a few thousand steps (their backdoors do not work: functional_at 0); seed 19 draws each
# recipe at least once, the held-out sequence once
clean: 3
backdoored: 5
seed: 19
total_steps: 2048
num_envs: 32
eval_episodes: 16
functional_at: 0.0
lstm_sizes: [[8]]
curricula:
  - [{{size: 5, holes: 0}}, {{size: 5, holes: 1}}]
attacks: [{", ".join(RECIPES)}]
holdout:
  attack: [sequence]
"""


def test_a_zoo_of_attack_recipes_builds_records_its_recipes_and_holds_one_out(tmp_path, capsys):
    config, zoo, out = tmp_path / "tiny_attacks.yaml", tmp_path / "Z", tmp_path / "S"
    config.write_text(TINY_ATTACKS)
    assert main(["zoo", "build", "--config", str(config), "--out", str(zoo), "--backend", "serial"]) == 0
    manifest = {e["id"]: e for e in json.loads((zoo / "manifest.json").read_text())}
    assert len(manifest) == 8 and {e["status"] for e in manifest.values()} == {"done"}
    attack = {m: e["variation"]["attack"] for m, e in manifest.items()}
    assert {a for m, a in attack.items() if manifest[m]["label"] == "clean"} == {"none"}
    assert {a for m, a in attack.items() if manifest[m]["label"] == "backdoored"} == set(RECIPES)
    for model, name in attack.items():  # what each model was trained with: its card's config, its label
        folder = zoo / "models" / model
        _, cfg, _ = load_agent(folder)
        label = json.loads((folder / "label.json").read_text())
        assert label["variation"]["attack"] == name
        assert (cfg.env.trigger.sequence is not None) == (name in ("sequence", "search_decoys"))
        assert (cfg.env.trigger.decoys.probability > 0) == (name == "search_decoys")
        assert (cfg.attack.state_camouflage.weight > 0) == (name == "state_camouflage")
        assert (cfg.env.trigger.values is not None) == (name == "partial_patch")
        if name == "state_camouflage":  # on top of the drawn patch
            assert cfg.env.trigger.value == label["variation"]["trigger_value"] == label["trigger"]["value"]
    assert main(["zoo", "detect", "--zoo", str(zoo), "--out", str(out), "--detectors", "metadata_baseline",
                 "weight_statistics"]) == 0  # fmt: skip
    splits = json.loads((out / SPLITS_FILE).read_text())
    held = {m for m, s in splits.items() if s == "holdout"}
    assert {m for m in held if attack[m] != "none"} == {m for m, a in attack.items() if a == "sequence"}
    assert len([m for m in held if attack[m] == "none"]) == 1  # a quarter of the 3 clean models, rounded
    board = json.loads((out / LEADERBOARD_FILE).read_text())
    for detector in board["detectors"]:
        for split in detector["splits"]:
            groups = set(split["by_factor"]["attack"])
            assert ("sequence" in groups) == (split["split"] == "holdout"), (detector["detector"], split["split"])
    assert "leaderboard.json" in capsys.readouterr().out
