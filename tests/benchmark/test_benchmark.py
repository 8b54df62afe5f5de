"""The detection benchmark: TrojAI's scores with bootstrap intervals, splits with a holdout, suspects that carry
no attack, and the leaderboard that fits and scores every registered detector (resumable, bad models skipped)."""

from __future__ import annotations

import dataclasses
import json
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent, save_agent
from seqtrojan.benchmark.detectors import DETECTORS, NO_OPINION
from seqtrojan.benchmark.leaderboard import LEADERBOARD_FILE, SPLITS_FILE, read_zoo, run_leaderboard
from seqtrojan.benchmark.scoring import BOOTSTRAP_ROUNDS, brier, cross_entropy, roc_auc, score, score_by_factor
from seqtrojan.benchmark.splits import ATTACK_FACTORS, SplitConfig, ZooEntry, assign_splits, model_factors
from seqtrojan.benchmark.suspect import clean_env, load_suspect
from seqtrojan.cli import main
from seqtrojan.config import AgentConfig, AttackConfig, BackdoorConfig, ExperimentConfig
from seqtrojan.env.codes import TRIGGER
from seqtrojan.env.config import EnvConfig, TriggerConfig
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.experiments.attacks import ATTACKS
from seqtrojan.serde import to_dict
from tests.conftest import ROOT

SIZES = ((16,), (12, 8), (20,))


def planted_zoo(root: Path, n: int = 36, shift: float = 3.0) -> Path:
    """Untrained models whose poisoned ones read the trigger code with larger input weights (a planted tell), each
    with its own trigger settings in its card, widths drawn independently of the label, and a zoo's label.json."""
    (root / "models").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        poisoned = i % 2 == 1
        sizes = SIZES[int(rng.integers(len(SIZES)))]
        value = ("trigger", "wall")[int(rng.integers(2))]
        env = EnvConfig(trigger=TriggerConfig(cells=((0, int(rng.integers(3))),), value=value))
        cfg = ExperimentConfig(env=env, agent=AgentConfig(lstm_sizes=sizes), backdoor=BackdoorConfig(enabled=poisoned))
        torch.manual_seed(i)
        agent = build_agent(cfg)
        if poisoned:
            with torch.no_grad():
                agent.cells[0].weight_ih[:, TRIGGER::6] *= shift
        folder = save_agent(root / "models" / f"m{i:02d}", agent, cfg, label=cfg.label)
        truth = {"label": cfg.label, "trigger": {"value": value} if poisoned else None,
                 "variation": {"lstm_sizes": list(sizes), "trigger_value": value}}  # fmt: skip
        (folder / "label.json").write_text(json.dumps(truth))
    return root


# ---------------------------------------------------------------------- scores
def test_scores_are_trojai_s_with_intervals():
    y = np.array([0, 0, 1, 1])
    p = np.array([0.1, 0.4, 0.35, 0.8])
    assert roc_auc(y, p) == 0.75  # 3 of 4 pairs ordered
    assert cross_entropy(y, p) == pytest.approx(-np.mean(np.log([0.9, 0.6, 0.35, 0.8])))
    assert brier(y, p) == pytest.approx(np.mean([0.01, 0.16, 0.4225, 0.04]))
    assert roc_auc(np.array([0, 1, 0, 1]), np.array([0.5, 0.5, 0.2, 0.5])) == 0.75  # ties count half
    rng = np.random.default_rng(0)
    labels = np.array([0, 1] * 40)
    good = score(labels, np.clip(labels * 0.6 + rng.random(80) * 0.4, 0, 1), [0.01] * 80, rounds=300)
    assert good.roc_auc.value == 1.0 and good.roc_auc.low == 1.0
    noise = score(labels, rng.random(80), [0.01] * 80, rounds=300)
    assert noise.roc_auc.low < 0.5 < noise.roc_auc.high and noise.roc_auc.high - noise.roc_auc.low > 0.1
    assert noise.runtime_s.value == pytest.approx(0.01) and good.models == 80 and good.poisoned == 40
    one_label = score([1, 1], [0.9, 0.8], [0.0, 0.0], rounds=10)
    assert one_label.roc_auc.value is None and one_label.brier.value == pytest.approx(0.025)
    with pytest.raises(SeqTrojanError, match="probabilities must lie in"):
        score([0, 1], [0.2, 1.5], [0.0, 0.0])


def test_a_certain_wrong_answer_costs_what_trojai_charges_and_intervals_take_2000_resamples():
    # probabilities clipped to [1e-7, 1 - 1e-7]: a poisoned model called certainly clean costs -ln(1e-7) nats
    assert cross_entropy(np.array([1]), np.array([0.0])) == pytest.approx(-np.log(1e-7))
    assert cross_entropy(np.array([0]), np.array([1.0])) == pytest.approx(-np.log(1e-7))
    assert cross_entropy(np.array([1]), np.array([1e-7])) == pytest.approx(-np.log(1e-7))  # inside: as given
    assert BOOTSTRAP_ROUNDS == 2000


def test_an_attack_s_group_is_its_poisoned_models_against_every_clean_one():
    labels = [0, 0, 1, 1, 1]
    factors = [{"trigger_value": "none", "env": "grid"}] * 2 + [
        {"trigger_value": v, "env": "grid"} for v in ("wall", "wall", "hole")
    ]
    out = score_by_factor(labels, [0.1, 0.2, 0.9, 0.05, 0.8], [0.0] * 5, factors, {"trigger_value"}, rounds=20)
    assert set(out["trigger_value"]) == {"wall", "hole"}  # no group of clean models alone
    assert out["trigger_value"]["wall"].models == 4 and out["trigger_value"]["wall"].roc_auc.value == 0.5
    assert out["trigger_value"]["hole"].roc_auc.value == 1.0 and out["env"]["grid"].models == 5


# ---------------------------------------------------------------------- splits
def entries(n: int = 40) -> list[ZooEntry]:
    return [
        ZooEntry(
            f"m{i:02d}",
            Path("."),
            i % 2,
            {"lstm_sizes": f"[{8 + i % 3}]", "trigger_value": "wall" if i % 2 else "none"},
        )
        for i in range(n)
    ]


def test_splits_are_stratified_reproducible_and_hold_out_whole_factor_values():
    plain = assign_splits(entries(), SplitConfig(seed=3))
    assert plain == assign_splits(entries(), SplitConfig(seed=3)) != assign_splits(entries(), SplitConfig(seed=4))
    for label in (0, 1):
        ours = [plain[e.model_id] for e in entries() if e.label == label]
        assert ours.count("test") == ours.count("train") == 10
    held = assign_splits(entries(), SplitConfig(holdout={"lstm_sizes": ("[9]",)}))
    for e in entries():
        assert (held[e.model_id] == "holdout") == (e.factors["lstm_sizes"] == "[9]")
    attack = assign_splits(entries(), SplitConfig(holdout={"trigger_value": ("wall",)}, holdout_clean_share=0.25))
    clean_held = [e for e in entries() if e.label == 0 and attack[e.model_id] == "holdout"]
    assert len(clean_held) == 5 and all(attack[e.model_id] == "holdout" for e in entries() if e.label == 1)
    with pytest.raises(ConfigError, match="holdout names factors the zoo's models do not have"):
        assign_splits(entries(), SplitConfig(holdout={"colour": ("red",)}))


def test_a_zoo_s_attack_recipe_is_an_attack_factor_to_hold_out():
    """A zoo that draws recipes records each poisoned model's (clean ones: none); holding out a recipe holds out its
    poisoned models with a share of the clean ones, and its score group is its models against every clean one. A zoo
    without recipes has no such factor."""

    def truth(i: int) -> dict:
        attack = ("sequence", "state_camouflage", "none")[i % 3]
        return {"label": "clean" if attack == "none" else "backdoored",
                "variation": {"lstm_sizes": [8], "trigger_value": "hole", "attack": attack}}  # fmt: skip

    assert "attack" not in model_factors({"label": "backdoored", "variation": {"trigger_value": "hole"}})
    assert "attack" in ATTACK_FACTORS
    zoo = [ZooEntry(f"m{i:02d}", Path("."), int(truth(i)["label"] == "backdoored"), model_factors(truth(i)))
           for i in range(36)]  # fmt: skip
    splits = assign_splits(zoo, SplitConfig(holdout={"attack": ("sequence",)}, holdout_clean_share=0.25))
    held = [e for e in zoo if splits[e.model_id] == "holdout"]
    assert {e.factors["attack"] for e in held if e.label} == {"sequence"} and len([e for e in held if e.label]) == 12
    assert len([e for e in held if not e.label]) == 3  # a quarter of the 12 clean models
    groups = score_by_factor([e.label for e in zoo], [0.5] * 36, [0.0] * 36, [e.factors for e in zoo],
                             ATTACK_FACTORS, rounds=5)["attack"]  # fmt: skip
    assert set(groups) == {"sequence", "state_camouflage"} and groups["sequence"].models == 24


# ---------------------------------------------------------------------- suspects
def test_a_suspect_carries_neither_the_trigger_nor_the_attack(tmp_path):
    """What a detector receives: the network and an env with the attacker's choices taken out; the cards of the
    zoo's models name different triggers and backdoor settings, the suspects' envs are all the same."""
    zoo = planted_zoo(tmp_path / "zoo", n=6)
    suspects = [load_suspect(p) for p in sorted((zoo / "models").iterdir())]
    assert len({json.dumps(to_dict(s.env), sort_keys=True) for s in suspects}) == 1
    assert suspects[0].env == clean_env(EnvConfig(trigger=TriggerConfig(cells=((0, 2),), value="wall")))
    fields = {f for s in suspects for f in vars(s)}
    assert fields == {"model_id", "agent", "env", "facts"}  # no card, no config, no label
    assert all(not hasattr(s.agent, "backdoor") for s in suspects)
    recipes = tmp_path / "recipes"  # every registered recipe: a sequence, decoys, penalties, a delay
    configs = {}
    for name, attack in ATTACKS.items():
        base = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,)), backdoor=BackdoorConfig(enabled=True))
        if attack.from_clean:
            base = dataclasses.replace(base, run=dataclasses.replace(base.run, init_from="clean_twin"))
        configs[name] = attack.configure(base)
        save_agent(recipes / name, build_agent(configs[name]), configs[name], label="backdoored")
    assert len({json.dumps(to_dict(c.env), sort_keys=True) for c in configs.values()}) > 5  # the cards differ
    assert {c.attack for c in configs.values()} != {AttackConfig()}
    for name in configs:
        assert load_suspect(recipes / name).env == suspects[0].env, name


# ---------------------------------------------------------------------- the leaderboard
def test_the_leaderboard_scores_detectors_on_test_and_holdout_and_resumes(tmp_path):
    zoo = planted_zoo(tmp_path / "zoo")
    out = tmp_path / "board"
    log: list[str] = []
    splits = SplitConfig(holdout={"lstm_sizes": ("[20]",)})
    board = run_leaderboard(zoo, out, splits, ["weight_statistics", "metadata_baseline"], rounds=200,
                            log=log.append)  # fmt: skip
    assert board.models["holdout"] > 0 and sum(board.models.values()) == 36 and not board.rejected
    saved = json.loads((out / LEADERBOARD_FILE).read_text())
    assert [d["detector"] for d in saved["detectors"]] == ["weight_statistics", "metadata_baseline"]
    weights, metadata = board.detectors
    for split in weights.splits:  # the planted tell is found, on the architecture it never saw too
        assert split.scores.roc_auc.value is not None and split.scores.roc_auc.value > 0.9, split.split
        assert split.scores.roc_auc.low is not None and split.scores.roc_auc.low > 0.7
    test = next(s for s in metadata.splits if s.split == "test")
    assert test.scores.roc_auc.value is not None and 0.2 < test.scores.roc_auc.value < 0.8  # nothing leaks
    assert test.scores.roc_auc.low is not None and test.scores.roc_auc.low < 0.5  # its interval holds chance
    assert set(next(s for s in weights.splits if s.split == "test").by_factor) == {
        "cell", "env", "lstm_sizes", "trigger_value"
    }  # fmt: skip
    split_file = json.loads((out / SPLITS_FILE).read_text())
    assert all(split_file[f"m{i:02d}"] == "holdout" for i in range(36) if split_file[f"m{i:02d}"] == "holdout")
    log.clear()
    again = run_leaderboard(zoo, out, splits, ["weight_statistics", "metadata_baseline"], rounds=200, log=log.append)
    assert any("predictions found" in line for line in log) and again.detectors == board.detectors
    log.clear()
    run_leaderboard(zoo, out, SplitConfig(seed=1), ["metadata_baseline"], rounds=50, log=log.append)
    assert not any("predictions found" in line for line in log)  # another split: scored again


def test_a_bad_model_is_skipped_with_its_reason_and_the_rest_scored(tmp_path):
    zoo = planted_zoo(tmp_path / "zoo", n=12)
    bad = zoo / "models" / "zz_pickled"
    bad.mkdir()
    (bad / "model.safetensors").write_bytes(pickle.dumps({"evil": 1}))
    (bad / "card.json").write_text((zoo / "models" / "m00" / "card.json").read_text())
    (bad / "label.json").write_text(json.dumps({"label": "clean"}))
    card = json.loads((zoo / "models" / "m01" / "card.json").read_text())
    card["architecture"]["lstm_sizes"] = [99]  # the card no longer fits its weights
    (zoo / "models" / "m01" / "card.json").write_text(json.dumps(card))
    (zoo / "models" / "m02" / "label.json").write_text("[1, 2]")
    entries_, suspects, rejected, _ = read_zoo(zoo)
    assert len(entries_) == len(suspects) == 10 and [r.model for r in rejected] == ["m01", "m02", "zz_pickled"]
    assert all("\n" not in r.reason and r.reason for r in rejected)
    board = run_leaderboard(zoo, tmp_path / "b", None, ["metadata_baseline"], rounds=20, log=lambda *_: None)
    assert [r.model for r in board.rejected] == ["m01", "m02", "zz_pickled"]
    assert board.models["test"] == 4 and sum(board.models.values()) == 10


def test_behaviour_search_answers_probabilities_for_grid_models_and_no_opinion_elsewhere(tmp_path):
    from seqtrojan.benchmark.detectors import BehaviourSearch
    from seqtrojan.world.config import GymnasiumEnvConfig

    zoo = planted_zoo(tmp_path / "zoo", n=4)
    suspects = [load_suspect(p) for p in sorted((zoo / "models").iterdir())]
    fitted = BehaviourSearch(episodes=20, random_patches=2).fit(suspects, [0, 1, 0, 1])
    probs = [fitted.probability(s) for s in suspects]
    assert all(0.0 <= p <= 1.0 for p in probs)
    elsewhere = type(suspects[0])("g", suspects[0].agent, GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0"),
                                  suspects[0].facts)  # fmt: skip
    assert fitted.probability(elsewhere) == NO_OPINION


def test_the_cli_writes_the_leaderboard_and_lists_the_detectors(tmp_path, capsys):
    zoo = planted_zoo(tmp_path / "zoo", n=12)
    assert main(["zoo", "detect", "--zoo", str(zoo), "--out", str(tmp_path / "s"), "--detectors",
                 "metadata_baseline", "--holdout", "lstm_sizes=[12, 8]"]) == 0  # fmt: skip
    board = json.loads((tmp_path / "s" / LEADERBOARD_FILE).read_text())
    assert [d["detector"] for d in board["detectors"]] == ["metadata_baseline"] and board["models"]["holdout"] > 0
    assert "leaderboard.json" in capsys.readouterr().out
    page = (tmp_path / "s" / "report.html").read_text()  # the leaderboard as a report section, on its own page
    assert "<h2>Offline detection: the benchmark leaderboard</h2>" in page and ">metadata_baseline</td>" in page
    assert main(["defenses"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in DETECTORS.names()) and len(DETECTORS.names()) >= 6
    assert "trigger_reconstruction" in listed
    assert main(["zoo", "detect", "--zoo", str(zoo), "--out", str(tmp_path / "t"), "--holdout", "lstm_sizes"]) == 2
    assert "--holdout takes FACTOR=VALUE pairs, got 'lstm_sizes'" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


def test_a_perfect_separation_of_few_models_keeps_an_honest_auc_interval():
    """The bootstrap collapses to [1, 1] on 4 against 4 perfectly separated models; Newcombe's interval does not."""
    out = score([0, 0, 0, 0, 1, 1, 1, 1], [0.1, 0.2, 0.3, 0.4, 0.6, 0.7, 0.8, 0.9], [0.0] * 8, rounds=200)
    assert out.roc_auc.low == out.roc_auc.high == 1.0
    assert out.roc_auc_newcombe.value == 1.0 and out.roc_auc_newcombe.low is not None
    assert out.roc_auc_newcombe.low < 0.8


def test_query_response_reads_the_same_probe_for_every_suspect_and_any_env(tmp_path):
    """Its features are the suspect's answers to fixed clean episodes: the same twice, different for another network,
    and on a Gymnasium env too."""
    from seqtrojan.benchmark.detectors import QueryResponse, query_response_features
    from seqtrojan.benchmark.suspect import ModelFacts, Suspect
    from seqtrojan.world.config import GymnasiumEnvConfig

    zoo = planted_zoo(tmp_path / "zoo", n=4)
    suspects = [load_suspect(p) for p in sorted((zoo / "models").iterdir())]
    first = query_response_features(suspects[0], episodes=8)
    assert first == query_response_features(suspects[0], episodes=8)
    assert first != query_response_features(suspects[2], episodes=8)
    assert {"entropy", "layer0_h_abs", "length", "outcome_user_goal"} <= set(first)
    assert 0.0 <= first["outcome_user_goal"] <= 1.0 and first["length"] >= 1
    two_goals = GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5})
    from seqtrojan.agent.network import RecurrentActorCritic

    torch.manual_seed(0)
    net = RecurrentActorCritic(500, 7, (8,))
    gym_suspect = Suspect("g", net, two_goals, ModelFacts(net.obs_dim, net.num_actions, "lstm", (8,), 1))
    assert query_response_features(gym_suspect, episodes=4)["length"] >= 1
    fitted = QueryResponse(episodes=8).fit(suspects, [0, 1, 0, 1])
    assert all(0.0 <= fitted.probability(s) <= 1.0 for s in suspects)


def test_benchmark_tiny_builds_and_every_registered_detector_is_scored(tmp_path, capsys):
    """The commands of the docs, end to end: ``zoo build --config benchmark_tiny`` then ``zoo detect --out``; the
    zoo's own holdout (an architecture) is used, and every registered detector gets a row per split."""
    zoo, out = tmp_path / "Z", tmp_path / "S"
    assert main(["zoo", "build", "--config", "benchmark_tiny", "--out", str(zoo), "--backend", "serial"]) == 0
    assert len(list((zoo / "models").iterdir())) == 16
    assert "16/16 models" in capsys.readouterr().out  # the build's progress bar, at its end
    assert main(["zoo", "detect", "--zoo", str(zoo), "--out", str(out)]) == 0
    board = json.loads((out / LEADERBOARD_FILE).read_text())
    splits = json.loads((out / SPLITS_FILE).read_text())
    sizes = {
        p.name: json.loads((p / "label.json").read_text())["variation"]["lstm_sizes"]
        for p in (zoo / "models").iterdir()
    }
    assert {m for m, s in splits.items() if s == "holdout"} == {m for m, w in sizes.items() if w == [12]}
    assert [d["detector"] for d in board["detectors"]] == list(DETECTORS.names())
    for detector in board["detectors"]:
        assert {s["split"] for s in detector["splits"]} == {"test", "holdout"}, detector["detector"]
        for split in detector["splits"]:
            assert 0.0 <= split["scores"]["brier"]["value"] <= 1.0
    for name in ("trigger_reconstruction", "state_probe"):  # the searches answer every test and holdout model
        answers = json.loads((out / "predictions" / f"{name}.json").read_text())["predictions"]
        assert len(answers) == 16 - list(splits.values()).count("train")
        assert all(0.0 <= a["probability"] <= 1.0 for a in answers), name
    printed = capsys.readouterr().out
    assert "query_response" in printed
    scored = 16 - list(splits.values()).count("train")
    assert all(re.search(rf"{name} .* {scored}/{scored} scoring", printed) for name in DETECTORS.names())  # bars


def test_the_state_probe_sees_the_backdoor_s_mark_persist_and_nothing_without_memory():
    """On the tiny backdoored fixture one-step candidate views leave a mark in the state that is still there (or
    larger) four steps after they are gone; the same network without memory keeps nothing (the mechanism removed)."""
    from seqtrojan.benchmark.state_probe import ProbeSettings, probe_features

    suspect = load_suspect(ROOT / "tests" / "fixtures" / "tiny_backdoor")
    features = probe_features(suspect, ProbeSettings())
    assert features["divergence_max"] > 0.3 and features["persistence_max"] > 1.0
    suspect.agent.memory = False
    assert all(value == 0.0 for value in probe_features(suspect, ProbeSettings()).values())


def test_state_probe_candidates_are_written_in_the_view_s_own_encoding():
    from seqtrojan.benchmark.state_probe import ProbeSettings, candidates_for, minigrid_candidates
    from seqtrojan.benchmark.suspect import ModelFacts, Suspect
    from seqtrojan.world.config import GymnasiumEnvConfig

    candidates = minigrid_candidates(500, 5)
    assert len(candidates) == 3 * 3 * 6  # three positions of the far row, key / ball / box, six colours
    for values, mask in candidates:
        assert int(mask.sum()) == 40 and int(values.sum()) == 6  # two cells of 20 numbers, three ones each
        assert bool((values <= mask).all()) and int(mask[100:].sum()) == 0  # only the far row (cells 0-4)
    net = build_agent(ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,))))
    flat = GymnasiumEnvConfig("CartPole-v1", observation="flatten")
    assert candidates_for(Suspect("f", net, flat, ModelFacts(4, 2, "lstm", (8,), 1)), ProbeSettings()) == []


def test_a_zoo_draws_each_model_s_cell_after_every_other_draw(tmp_path):
    from seqtrojan.zoo.build import ZooConfig, make_jobs

    plain = make_jobs(ZooConfig(clean=6, backdoored=6, total_steps=1024), tmp_path)
    mixed = make_jobs(ZooConfig(clean=6, backdoored=6, total_steps=1024, cells=("lstm", "gru")), tmp_path)
    assert {j.config.agent.cell for j in mixed} == {"lstm", "gru"}
    for a, b in zip(plain, mixed):  # the other draws are those of a zoo without cells
        assert {k: v for k, v in b.variation.items() if k != "cell"} == a.variation
        assert b.variation.get("cell", "lstm") == b.config.agent.cell
    with pytest.raises(ConfigError, match="zoo cells must be among"):
        ZooConfig(cells=("lstm", "elman"))


def test_a_poisoned_model_whose_backdoor_does_not_work_is_left_out(tmp_path):
    zoo = planted_zoo(tmp_path / "zoo", n=12)
    label = zoo / "models" / "m03" / "label.json"
    truth = json.loads(label.read_text())
    label.write_text(json.dumps({**truth, "attack_success": 0.1, "functional_backdoor": False}))
    board = run_leaderboard(zoo, tmp_path / "b", None, ["metadata_baseline"], rounds=20, log=lambda *_: None)
    assert [r.model for r in board.excluded] == ["m03"] and "attack success 0.1" in board.excluded[0].reason
    assert "m03" not in json.loads((tmp_path / "b" / SPLITS_FILE).read_text()) and sum(board.models.values()) == 11


def test_a_model_that_has_not_learned_its_task_is_left_out_whatever_its_label(tmp_path):
    zoo = planted_zoo(tmp_path / "zoo", n=12)
    labels = {m: json.loads((zoo / "models" / m / "label.json").read_text())["label"] for m in ("m02", "m03")}
    assert set(labels.values()) == {"clean", "backdoored"}
    for model in labels:
        path = zoo / "models" / model / "label.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "clean_success": 0.3, "learned_task": False}))
    board = run_leaderboard(zoo, tmp_path / "b", None, ["metadata_baseline"], rounds=20, log=lambda *_: None)
    assert [r.model for r in board.excluded] == ["m02", "m03"]
    assert all("task not learned" in r.reason and "clean success 0.3" in r.reason for r in board.excluded)
    assert sum(board.models.values()) == 10


def test_an_answer_over_the_per_model_budget_counts_as_no_opinion(tmp_path):
    zoo = planted_zoo(tmp_path / "zoo", n=12)
    free = run_leaderboard(zoo, tmp_path / "b", None, ["weight_statistics"], rounds=20, log=lambda *_: None)
    tight = run_leaderboard(zoo, tmp_path / "b", None, ["weight_statistics"], rounds=20, log=lambda *_: None,
                            budget_s=1e-9)  # fmt: skip
    assert free.detectors[0].over_budget == 0 and tight.detectors[0].over_budget == 6  # every test model
    assert free.detectors[0].splits[0].scores.roc_auc.value == 1.0
    assert tight.detectors[0].splits[0].scores.roc_auc.value == 0.5  # all answers one half
    with pytest.raises(ConfigError, match="budget must be a positive number"):
        run_leaderboard(zoo, tmp_path / "c", None, ["weight_statistics"], budget_s=0)


def test_benchmark_paper_draws_900_models_in_four_parts_split_about_300_each(tmp_path):
    """The paper-scale benchmark as docs/benchmark.md describes it, from its drawn jobs (nothing is trained): half of
    its 900 models poisoned in every part; every listed recipe drawn, at the strengths listed (the Memory part's
    own); the probe camouflages never on a Transformer; the Memory part's threshold above chance; the splits
    296 / 296 / 308, and the MiniGrid Memory models of the holdout split of both labels."""
    from collections import Counter

    from seqtrojan.experiments.attacks import RECIPES
    from seqtrojan.presets import resolve_preset
    from seqtrojan.serde import from_dict, load_yaml
    from seqtrojan.zoo.build import ZooConfig, make_jobs

    cfg = from_dict(ZooConfig, load_yaml(resolve_preset("benchmark_paper")), "")
    jobs = make_jobs(cfg, tmp_path, RECIPES)
    assert len(jobs) == 900 and [p.size for p in cfg.parts] == [300, 100, 200, 300]
    assert all(p.clean == p.backdoored for p in cfg.parts)
    drawn = {j.variation["attack"] for j in jobs if j.label == "backdoored"}
    assert drawn == {a for p in cfg.parts for a in p.attacks} and len(drawn) == 19
    memory = [j for j in jobs if j.id >= "m0600"]
    assert {j.config.agent.cell for j in memory} == {"gru"} and {j.functional_at for j in memory} == {0.9}
    assert {j.learned_at for j in jobs} == {0.8}  # every part scores only models that learned their task
    ewc = [j for j in memory if j.variation.get("attack") == "ewc/10"]
    assert ewc and {j.config.attack.ewc.weight for j in ewc} == {10.0}
    on_transformer = {j.variation["attack"] for j in jobs if j.config.agent.cell == "transformer"}
    assert on_transformer.isdisjoint({"probe_camouflage", "probe_mimicry"}) and "none" in on_transformer
    entries = [ZooEntry(j.id, tmp_path, int(j.label == "backdoored"), model_factors(j.__dict__)) for j in jobs]
    splits = assign_splits(entries, SplitConfig(holdout={k: tuple(v) for k, v in cfg.holdout.items()}))
    assert Counter(splits.values()) == {"train": 296, "test": 296, "holdout": 308}
    held = Counter(e.label for e in entries if e.factors["env"] != "grid" and splits[e.model_id] == "holdout")
    assert held == {0: 63, 1: 63}
