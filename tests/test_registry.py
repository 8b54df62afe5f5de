"""The registries of attacks and defenses: lookup, refusal of duplicates, a new mitigation reaching the results
and the report without other edits, and the two listing commands."""

from __future__ import annotations

import pytest
import torch

from seqtrojan import registry as registry_module
from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.benchmark.detectors import DETECTORS as BENCHMARK_DETECTORS
from seqtrojan.cli import main
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig
from seqtrojan.defense.mitigation import MITIGATIONS, MitigationConfig, MitigationContext, run_mitigation
from seqtrojan.defense.monitor import MONITORS
from seqtrojan.defense.offline import DETECTORS
from seqtrojan.defense.results import DefenseResult, MitigationArm, MonitorResult, NormalEnvArm, TrojanEnvArm
from seqtrojan.env import EnvConfig, GridSpec
from seqtrojan.env.config import REWARDS, TRIGGERS, OffTriggerConfig, TriggerConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS
from seqtrojan.registry import Registry, registries
from seqtrojan.report.markup import rate
from seqtrojan.report.sections.defense import defense_section
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import Rate
from seqtrojan.train.mixing import MIXING_RULES, MixingRule, TrojanMixer
from seqtrojan.train.penalties import PENALTIES


@pytest.fixture
def scratch(monkeypatch):
    """A fresh registry of a made-up kind, removed from the list of all registries afterwards."""
    monkeypatch.setattr(registry_module, "_ALL", list(registry_module._ALL))
    return Registry[int]("attack", "colour")


def test_lookup_by_name_and_an_unknown_name_lists_the_known_ones(scratch):
    scratch.register("red", "the first one", 1)

    @scratch.register("blue", "the second one")
    def _blue() -> int:
        return 2

    assert scratch.get("red") == 1 and scratch.get("blue") is _blue
    assert scratch.names() == ("red", "blue") and scratch.items() == (("red", 1), ("blue", _blue))
    assert scratch.entry("blue").kind == "colour" and scratch.entry("blue").description == "the second one"
    with pytest.raises(ConfigError, match=r"unknown colour 'green'; known: red, blue"):
        scratch.get("green")
    assert scratch in registries("attack") and scratch not in registries("defense")


def test_a_duplicate_name_and_a_bad_entry_are_refused(scratch):
    scratch.register("red", "the first one", 1)
    with pytest.raises(ConfigError, match=r"colour 'red' is already registered \(the first one\)"):
        scratch.register("red", "another", 3)
    assert scratch.get("red") == 1
    with pytest.raises(ConfigError, match="needs a one-line description"):
        scratch.register("pink", "two\nlines", 4)
    with pytest.raises(ConfigError, match="must be an identifier"):
        scratch.register("dark red", "a space in its name", 5)
    with pytest.raises(ConfigError, match="family must be one of"):
        Registry("offence", "x")  # type: ignore[arg-type]
    assert scratch.names() == ("red",)


def test_what_exists_is_registered():
    assert ATTACKS.names() == (
        "dedicated_code", "delayed", "in_distribution_patch", "partial_patch", "sequence", "search_decoys",
        "state_camouflage", "mahalanobis_camouflage", "from_clean", "weight_camouflage", "ewc", "switch_camouflage",
        "response_mimicry", "combined", "combined_all", "combined_all_margin", "finetune_resistant", "trained_longer",
        "probe_camouflage", "probe_mimicry",
    )  # fmt: skip
    assert PENALTIES.names() == (
        "state_camouflage", "mahalanobis_camouflage", "switch_camouflage", "weight_camouflage", "ewc",
        "finetune_resistance", "probe_camouflage", "response_mimicry",
    )  # fmt: skip
    assert MIXING_RULES.names() == ("exact", "running", "fixed")
    assert TRIGGERS.get("patch") is TriggerConfig and TRIGGERS.get("on_off") is OffTriggerConfig
    assert TRIGGERS.names() == (
        "patch", "on_off", "delayed", "in_distribution_patch", "partial_patch", "sequence", "decoys",
    )  # fmt: skip
    assert REWARDS.names() == ("env_rewards", "false_activation")
    assert MITIGATIONS.names() == ("fine_pruning", "fine_tuning", "state_bounds", "unit_reset")
    assert MONITORS.names() == ("state_monitor", "multivariate_monitor", "goal_switch", "input_novelty")
    assert DETECTORS.names() == ("weight_detector", "behaviour_detector")


def test_the_mixer_takes_its_rule_from_the_registry(monkeypatch):
    fixed = TrojanMixer(BackdoorConfig(enabled=True, mixing="fixed", fixed_probability=0.3), 2)
    fixed.observe(0, 0.9, 0.1)
    assert fixed.probabilities() == [0.3, 0.3]
    running = TrojanMixer(BackdoorConfig(enabled=True, mixing="running", probability_bounds=(0.1, 0.9)), 2)
    running.observe(0, 0.9, 0.1)  # the trojan env lags: 0.5 - (0.1 - 0.9) = 1.3, clipped to the bounds
    running.observe(1, 0.2, 0.6)
    assert running.probabilities() == pytest.approx([0.9, 0.1])
    monkeypatch.setattr(MIXING_RULES, "_entries", dict(MIXING_RULES._entries))
    MIXING_RULES.register("halves", "a made-up rule for the test", MixingRule(lambda c, t, config: 0.5 * c))
    halves = TrojanMixer(BackdoorConfig(enabled=True, mixing="halves"), 1)
    halves.observe(0, 0.8, 0.0)
    assert halves.probabilities() == [0.4]
    with pytest.raises(ConfigError, match=r"unknown mixing 'nope'; known: exact, running, fixed, halves"):
        TrojanMixer(BackdoorConfig(enabled=True, mixing="nope"), 1)
    with pytest.raises(ConfigError, match=r"backdoor\.mixing must be a rule name"):
        BackdoorConfig(mixing="not a name")


def test_a_registered_mitigation_reaches_the_results_the_json_and_the_report(tmp_path, monkeypatch):
    monkeypatch.setattr(MITIGATIONS, "_entries", dict(MITIGATIONS._entries))  # restored after the test
    seen: list[MitigationContext] = []

    @MITIGATIONS.register("identity", "leaves the agent as it is")
    def identity(ctx: MitigationContext) -> dict[str, MitigationArm]:
        seen.append(ctx)
        return {"identity": ctx.measure(ctx.agent, "the agent left as it is (identity)")}

    cfg = ExperimentConfig(env=EnvConfig(size=5, holes=1), agent=AgentConfig(lstm_sizes=(8, 4)))
    torch.manual_seed(0)
    agent = build_agent(cfg).eval()
    mcfg = MitigationConfig(finetune_steps=0, calibration_episodes=16, eval_episodes=16)
    rows = run_mitigation(agent, cfg, GridSpec(5, 1), mcfg, tmp_path)

    # no fine-tuning (0 steps), no oracle (no goal units)
    assert list(rows) == ["before", "pruned", "state_bounds", "identity"]
    assert len(seen) == 1 and seen[0].agent is agent
    # measured exactly as the untouched agent is: the same episodes and seed
    assert (rows["identity"].clean_success, rows["identity"].attack_success) == (
        rows["before"].clean_success,
        rows["before"].attack_success,
    )
    half = Rate(8, 16)
    normal, trojan = NormalEnvArm(half, half), TrojanEnvArm(half, half, half, half, None)
    monitor = MonitorResult("5x5/1", 16, 3.0, (8, 4), normal, normal, trojan, trojan, half, half)
    result = DefenseResult("model", "backdoored", "5x5/1", "trigger", monitor, None, rows)
    loaded = load_json(DefenseResult, save_json(result, tmp_path / "defense.json"))
    assert loaded == result and list(loaded.mitigation) == ["before", "pruned", "state_bounds", "identity"]
    table = "".join(defense_section(loaded, None))
    table = table[table.index("<h3>Mitigation") :]
    assert table.count("<tr>") == 5  # header, then one row per result, in order
    pruned = f"pruned {len(rows['pruned'].units)} least-active units"
    order = [table.index(title) for title in ("no mitigation", pruned, rows["state_bounds"].title, "(identity)")]
    assert order == sorted(order)
    clean, attack = (rate(r) for r in (rows["identity"].clean_success, rows["identity"].attack_success))
    assert f"<td class='l'>the agent left as it is (identity)</td><td>{clean}</td><td>{attack}</td>" in table


def test_a_mitigation_that_returns_a_taken_row_name_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(MITIGATIONS, "_entries", {})
    MITIGATIONS.register("clash", "returns the row name 'before'", lambda ctx: {"before": ctx.measure(ctx.agent, "x")})
    cfg = ExperimentConfig(env=EnvConfig(size=5, holes=1), agent=AgentConfig(lstm_sizes=(4,)))
    mcfg = MitigationConfig(finetune_steps=0, eval_episodes=4)
    with pytest.raises(ConfigError, match=r"mitigation 'clash' returned row 'before'"):
        run_mitigation(build_agent(cfg).eval(), cfg, GridSpec(5, 1), mcfg, tmp_path)


@pytest.mark.parametrize(
    ("command", "registered"),
    [
        ("attacks", (ATTACKS, TRIGGERS, MIXING_RULES, REWARDS, PENALTIES)),
        ("defenses", (MONITORS, DETECTORS, BENCHMARK_DETECTORS, MITIGATIONS)),
    ],
)
def test_the_listing_commands_print_every_registered_name(capsys, command, registered):
    assert main([command]) == 0
    lines = capsys.readouterr().out.splitlines()
    entries = [e for r in registered for e in r.entries()]
    assert len(lines) == len(entries)
    for line, e in zip(lines, entries):
        assert line.split()[:2] == [e.name, e.kind] and line.endswith(e.description)
    assert main(["--help"]) == 0 and command in capsys.readouterr().out


def test_a_listing_command_takes_no_options(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["attacks", "--verbose"])
    assert exit_.value.code == 2 and "takes no options" in capsys.readouterr().err


def test_each_adaptive_attack_names_a_registered_defense_it_targets():
    """``seqtrojan attacks`` says which defense each adaptive attacker is built against."""
    defenses = (
        set(MONITORS.names()) | set(DETECTORS.names()) | set(BENCHMARK_DETECTORS.names()) | set(MITIGATIONS.names())
    )
    targeted = {name: attack.targets for name, attack in ATTACKS.items() if attack.targets is not None}
    assert targeted == {
        "state_camouflage": "state_monitor", "mahalanobis_camouflage": "multivariate_monitor",
        "switch_camouflage": "goal_switch", "search_decoys": "behaviour_detector",
        "weight_camouflage": "weight_detector", "ewc": "fine_tuning", "finetune_resistant": "fine_tuning",
        "trained_longer": "fine_tuning", "combined": "state_monitor+multivariate_monitor+behaviour_detector",
        "probe_camouflage": "state_probe", "probe_mimicry": "state_probe_deviation",
        "response_mimicry": "query_response",
        "combined_all": "all_features+behaviour_search+multivariate_monitor",
        "combined_all_margin": "all_features+behaviour_search+multivariate_monitor",
    }  # fmt: skip
    assert {d for attack in ATTACKS.items() for d in attack[1].target_defenses} <= defenses
    for name in ("state_camouflage", "mahalanobis_camouflage", "switch_camouflage", "search_decoys",
                 "finetune_resistant", "trained_longer", "probe_camouflage", "probe_mimicry",
                 "response_mimicry"):  # fmt: skip
        assert f"against {targeted[name]}" in ATTACKS.entry(name).description
    assert "against state_monitor, multivariate_monitor and behaviour_detector" in ATTACKS.entry("combined").description
    every = "against all_features, behaviour_search and multivariate_monitor"
    assert (
        every in ATTACKS.entry("combined_all").description and every in ATTACKS.entry("combined_all_margin").description
    )


def test_each_adaptive_attack_has_a_knob_that_changes_its_config():
    """A sweep varies an adaptive attacker's strength through its registered knob."""
    from seqtrojan.config import ExperimentConfig

    for name, attack in ATTACKS.items():
        if attack.targets is None:
            assert attack.knob is None, name
            continue
        assert attack.knob is not None, f"{name} has no knob"
        cfg = attack.configure(ExperimentConfig())
        assert attack.knob.apply(cfg, attack.knob.default) == cfg, f"{name}'s knob default is not its own value"
        assert attack.knob.apply(cfg, attack.knob.default * 2 + 0.1) != cfg, f"{name}'s knob changes nothing"
