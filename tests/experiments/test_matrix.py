"""The attack x defense matrix end to end on a tiny budget: trainings on the job backend, every measurement, the
typed matrix.json, the heat map page, resuming, and bad input."""

from __future__ import annotations

import json

import pytest

from seqtrojan.errors import ConfigError
from seqtrojan.experiment_results import AgentMeasurement, MatrixResult
from seqtrojan.experiments.matrix import MatrixConfig, load_matrix_config, matrix_jobs, run_matrix
from seqtrojan.serde import from_dict, load_json, to_dict

TRAINING = {
    "env": {"size": 5, "holes": 1},
    "agent": {"lstm_sizes": [16]},
    "ppo": {"total_steps": 4096, "num_envs": 32, "rollout_steps": 32, "num_minibatches": 2, "update_epochs": 1},
    "curriculum": {"stages": [{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]},
    "run": {"eval_episodes": 0, "checkpoint_every": 4096, "progress": False},
}
TINY = {
    "backdoor": {"preset": "trojan_s17_h30", "set": {**TRAINING, "backdoor": {"mixing": "running"}}},
    "clean": {"preset": "clean_s17_h30", "set": TRAINING},
    "attacks": ["dedicated_code", "partial_patch", "ewc/3"],  # ewc at another knob value
    "seeds": 2,
    "episodes": 24,
    "monitor": {"calibration_episodes": 40, "eval_episodes": 24, "false_alarm_target": 0.05},
    "mitigation": {"finetune_steps": 1024, "calibration_episodes": 16, "eval_episodes": 24},
    "zoo": {"clean": 2, "backdoored": 2, "total_steps": 2048, "num_envs": 32, "eval_episodes": 8,
            "lstm_sizes": [[16]], "curricula": [[{"size": 5, "holes": 0}]]},
    "jobs": {"backend": "serial"},
}  # fmt: skip


@pytest.fixture(scope="module")
def tiny_matrix(tmp_path_factory):
    out = tmp_path_factory.mktemp("matrix")
    cfg = from_dict(MatrixConfig, TINY)
    return out, cfg, run_matrix(cfg, out, scale="tiny", log=lambda *_: None)


def test_every_attack_and_seed_is_trained_measured_and_saved_typed(tiny_matrix):
    out, cfg, result = tiny_matrix
    assert load_json(MatrixResult, out / "matrix.json") == result
    assert [a.attack for a in result.attacks] == ["dedicated_code", "partial_patch", "ewc/3"]
    assert sorted(a.agent for a in result.agents) == sorted(
        f"{name}_s{s}" for name in ("clean", "dedicated_code", "partial_patch", "ewc_w3") for s in (0, 1)
    )
    assert result.attacks[2].description.endswith("[attack.ewc.weight = 3]")
    for a in result.agents:
        assert a.attack_success.n == 24 and a.clean_success.n == 24
        assert set(a.online) == set(cfg.online_names) and set(a.mitigation) == {
            "fine_pruned",
            "fine_tuned",
            "state_bounds",
        }
        assert set(a.offline_scores) == set(cfg.offline_names)
        card = json.loads((out / "runs" / a.agent / "model" / "card.json").read_text())
        assert card["seed"] == a.seed and card["label"] == ("clean" if a.attack == "clean" else "backdoored")
    partial = json.loads((out / "runs" / "partial_patch_s1" / "model" / "card.json").read_text())
    assert partial["config"]["env"]["trigger"]["values"] == ["hole", "hole"]
    ewc = json.loads((out / "runs" / "ewc_w3_s1" / "model" / "card.json").read_text())["config"]
    assert ewc["run"]["init_from"] == str(out / "runs" / "clean_s1" / "model") and ewc["attack"]["ewc"]["weight"] == 3
    kinds = {(c.attack, c.kind) for c in result.cells}
    assert kinds == {(a, k) for a in TINY["attacks"] for k in ("online", "mitigation", "offline")}
    for summary in result.attacks:
        mine = [a for a in result.agents if a.attack == summary.attack]
        assert summary.attack_success_pooled.k == sum(a.attack_success.k for a in mine)
        by_seed = sorted(mine, key=lambda a: a.seed)
        assert summary.attack_success.values == tuple(a.attack_success.value for a in by_seed)
    page = (out / "report.html").read_text()
    assert "Attacks against defenses" in page and "data:image/png;base64," in page and "partial_patch" in page


def test_a_second_call_reuses_trainings_and_measurements(tiny_matrix):
    out, cfg, result = tiny_matrix
    measured = out / "measured" / "dedicated_code_s0.json"
    before = measured.stat().st_mtime, (out / "runs" / "clean_s0" / "model" / "card.json").stat().st_mtime
    assert run_matrix(cfg, out, scale="tiny", log=lambda *_: None) == result
    assert (measured.stat().st_mtime, (out / "runs" / "clean_s0" / "model" / "card.json").stat().st_mtime) == before
    assert load_json(AgentMeasurement, measured).agent == "dedicated_code_s0"
    measured.write_text(measured.read_text()[:100])  # cut short, as by a kill mid-write: measured again
    assert run_matrix(cfg, out, scale="tiny", log=lambda *_: None) == result
    assert load_json(AgentMeasurement, measured).agent == "dedicated_code_s0"


def test_from_clean_attacks_start_from_their_seeds_clean_agent(tmp_path):
    cfg = load_matrix_config("smoke")
    first, second = matrix_jobs(cfg, tmp_path)
    assert first[0].id == "clean_s0" and len(first) + len(second) == cfg.seeds * (1 + len(cfg.attack_names))
    for job in second:
        seed = job.id.rsplit("_s", 1)[1]
        assert job.config.run.init_from == str(tmp_path / f"clean_s{seed}" / "model")


def test_bad_presets_are_named(tmp_path):
    with pytest.raises(ConfigError, match="does not enable backdoor training"):
        matrix_jobs(from_dict(MatrixConfig, {**TINY, "backdoor": TINY["clean"]}), tmp_path)
    with pytest.raises(ConfigError, match="unknown attack 'nope'"):
        from_dict(MatrixConfig, {**TINY, "attacks": ["nope"]})
    with pytest.raises(ConfigError, match=r"names one attack twice: 'ewc/3' and 'ewc/3\.0'"):
        from_dict(MatrixConfig, {**TINY, "attacks": ["ewc/3", "ewc/3.0"]})
    with pytest.raises(ConfigError, match="dedicated_code has no knob to set"):
        from_dict(MatrixConfig, {**TINY, "attacks": ["dedicated_code/2"]})


MINIGRID_TRAINING = {
    "agent": {"lstm_sizes": [16]},
    "ppo": {"total_steps": 1024, "num_envs": 8, "rollout_steps": 32, "bptt_length": 16, "num_minibatches": 2,
            "update_epochs": 1},
    "run": {"eval_episodes": 0, "checkpoint_every": 1024, "progress": False},
}  # fmt: skip


def test_the_matrix_runs_on_a_minigrid_env_with_the_defenses_that_apply(tmp_path):
    """The MiniGrid preset keeps the attacks and defenses that apply to a Gymnasium env (none drawn with grid-world
    codes), names a grid-only one in one line, and a tiny run measures every applicable defense."""
    shipped = load_matrix_config("matrix_minigrid_smoke")
    assert shipped.attack_names == ("dedicated_code", "delayed", "state_camouflage", "mahalanobis_camouflage",
                                    "from_clean", "weight_camouflage", "ewc", "switch_camouflage")  # fmt: skip
    assert shipped.online_names == ("state_monitor", "multivariate_monitor", "goal_switch")
    assert shipped.offline_names == ("weight_detector",) and shipped.zoo is not None  # on a zoo of its env
    assert shipped.zoo.env_preset == "minigrid_two_goals"
    assert load_matrix_config("smoke").online_names[-1] == "input_novelty"  # the grid world keeps all
    for field, name, message in (("attacks", "partial_patch", "grid-world cells"),
                                 ("online", "input_novelty", "reads grid-world views"),
                                 ("offline", "behaviour_detector", "reads grid-world views")):  # fmt: skip
        with pytest.raises(ConfigError, match=message):
            from_dict(MatrixConfig, {"backdoor": {"preset": "minigrid_two_goals"}, field: [name], "zoo": None})
    tiny = {
        "backdoor": {"preset": "minigrid_two_goals", "set": MINIGRID_TRAINING},
        "clean": {"preset": "minigrid_two_goals", "set": {**MINIGRID_TRAINING, "backdoor": {"enabled": False}}},
        "attacks": ["dedicated_code", "from_clean"], "seeds": 1, "episodes": 12,
        "monitor": {"calibration_episodes": 40, "eval_episodes": 12, "false_alarm_target": 0.05},
        "mitigation": {"finetune_steps": 256, "calibration_episodes": 8, "eval_episodes": 12},
        "zoo": None, "jobs": {"backend": "serial"},
    }  # fmt: skip
    result = run_matrix(from_dict(MatrixConfig, tiny), tmp_path, scale="minigrid", log=lambda *_: None)
    assert result.grid == "seqtrojan/MiniGridTwoGoals-v0" and [a.attack for a in result.attacks] == list(
        tiny["attacks"]
    )
    for a in result.agents:
        assert set(a.online) == {"state_monitor", "multivariate_monitor", "goal_switch"} and a.natural_trigger is None
        assert set(a.mitigation) == {"fine_pruned", "fine_tuned", "state_bounds"} and a.attack_success.n == 12
    assert {(c.defense, c.kind) for c in result.cells} == {
        ("state_monitor", "online"), ("multivariate_monitor", "online"), ("goal_switch", "online"),
        ("fine_pruned", "mitigation"),
        ("fine_tuned", "mitigation"), ("state_bounds", "mitigation"),
    }  # fmt: skip
    assert (tmp_path / "report.html").read_text().count("MiniGridTwoGoals") >= 1


POPGYM_TRAINING = {
    "ppo": {"total_steps": 2048, "num_envs": 8, "rollout_steps": 32, "bptt_length": 16, "num_minibatches": 2,
            "update_epochs": 1},
    "run": {"eval_episodes": 0, "checkpoint_every": 2048, "progress": False},
}  # fmt: skip


@pytest.mark.parametrize("preset", ["matrix_popgym_smoke", "matrix_minatar_smoke"])
def test_the_family_matrix_presets_keep_the_gymnasium_attacks_and_defenses(preset):
    shipped = load_matrix_config(preset)
    assert "from_clean" in shipped.attack_names and "partial_patch" not in shipped.attack_names
    assert shipped.online_names == ("state_monitor", "multivariate_monitor", "goal_switch")
    assert shipped.zoo is not None and shipped.zoo.env_preset == shipped.backdoor.preset
    assert shipped.zoo.cell == shipped.base_config.agent.cell  # the weight detector scores the matrix's cell


def test_a_zoo_of_another_cell_than_the_matrix_agents_is_refused_before_training():
    """A weight detector fitted on LSTM models cannot score GRU agents: found at scoring, after every agent and the
    zoo had trained, until the config was checked up front."""
    shipped = to_dict(load_matrix_config("matrix_popgym_smoke"))
    shipped["zoo"]["cell"] = "lstm"
    with pytest.raises(ConfigError, match=r"has lstm models, but the matrix trains gru agents: set zoo.cell: gru"):
        from_dict(MatrixConfig, shipped)
    shipped["zoo"]["cells"] = ["gru", "lstm"]
    with pytest.raises(ConfigError, match=r"has gru, lstm models"):
        from_dict(MatrixConfig, shipped)
    shipped["offline"] = []  # no detector fitted on the zoo: nothing to refuse
    assert from_dict(MatrixConfig, shipped).zoo is not None


def test_the_matrix_runs_on_a_popgym_task(tmp_path):
    """A tiny matrix on POPGym's RepeatPrevious: the attacks train, every applicable defense is measured, and the
    target-action switch is what the defenses read (an attack success over the episodes)."""
    tiny = {
        "backdoor": {"preset": "popgym_repeat_previous", "set": POPGYM_TRAINING},
        "clean": {"preset": "popgym_repeat_previous", "set": {**POPGYM_TRAINING, "backdoor": {"enabled": False}}},
        "attacks": ["delayed"], "seeds": 1, "episodes": 12,
        "monitor": {"calibration_episodes": 40, "eval_episodes": 12, "false_alarm_target": 0.05},
        "mitigation": {"finetune_steps": 256, "calibration_episodes": 8, "eval_episodes": 12},
        "zoo": None, "jobs": {"backend": "serial"},
    }  # fmt: skip
    result = run_matrix(from_dict(MatrixConfig, tiny), tmp_path, scale="popgym", log=lambda *_: None)
    assert result.grid == "popgym-RepeatPreviousEasy-v0" and [a.attack for a in result.attacks] == ["delayed"]
    for a in result.agents:
        assert set(a.online) == {"state_monitor", "multivariate_monitor", "goal_switch"}
        assert a.attack_success.n == 12
    assert (tmp_path / "report.html").read_text().count("RepeatPrevious") >= 1
