"""Typed stage results: Rate, serde's nested types, round trips of every result type, and loads that fail with the
dotted path of a misspelt, missing or ill-typed key."""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field

import pytest
from hypothesis import given
from hypothesis import strategies as st

from seqtrojan.analysis.config import AnalysisConfig, LayoutSearchConfig, ResponseRule, WalkSearchConfig
from seqtrojan.analysis.results import (
    AnalysisResult,
    GoalUnitsRecord,
    InterventionsResult,
    LayoutSearch,
    LayoutSearchResult,
    ResponseCounts,
    ResponsesResult,
    SearchResult,
    SequenceSearchResult,
    SwitchResult,
    TriggerDetectionRow,
    UnintentionalResult,
    UnintentionalRow,
    UnitResponses,
    WalkSearchResult,
)
from seqtrojan.artifacts import RunLayout, TrajectoryResult
from seqtrojan.defense.results import (
    DefenseResult,
    DetectionResult,
    FunctionalSplit,
    GroupScores,
    HeldOutGroup,
    HeldOutScores,
    MitigationArm,
    MonitorResult,
    NormalEnvArm,
    Prediction,
    Rejected,
    TrojanEnvArm,
)
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.results import SweepRow, load_sweep, write_sweep
from seqtrojan.serde import from_dict, load_json, save_json, to_dict
from seqtrojan.stats import Rate, wilson_interval

# --- Rate


@given(st.integers(0, 5000).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_a_rate_is_its_counts_with_their_wilson_interval(counts):
    k, n = counts
    rate = Rate(k, n)
    assert rate.value == (k / n if n else 0.0)
    assert rate.interval == wilson_interval(k, n)
    assert rate.serde_dump() == {"k": k, "n": n, "rate": rate.value, "ci95": list(wilson_interval(k, n))}
    assert from_dict(_Holder, json.loads(json.dumps({"rate": to_dict(rate)}))).rate == rate


def test_a_rate_prints_with_its_interval_and_refuses_impossible_counts():
    assert Rate(1, 8).text() == "0.125 [0.022, 0.471]" == str(Rate(1, 8))
    assert Rate(0, 0).text(2) == "0.00 [0.00, 1.00]"  # nothing measured: the whole range
    for k, n in ((3, 2), (-1, 5), (True, 5), (1.0, 5)):
        with pytest.raises(ConfigError, match="rate"):
            Rate(k, n)


@dataclass(frozen=True)
class _Holder:
    rate: Rate
    rates: dict[str, Rate] = field(default_factory=dict)
    maybe: Rate | None = None
    pair: tuple[Rate, ...] = ()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["rate"].pop("n"), r"rate: missing key\(s\) \['n'\]"),
        (lambda d: d["rate"].update(kk=1), r"rate: unknown key\(s\) \['kk'\]"),
        (lambda d: d["rate"].update(k=1.0), r"rate\.k must be an integer"),
        (lambda d: d["rate"].update(k=9), r"rate: .*0 <= k <= n"),
        (lambda d: d["rate"].update(rate=0.5), r"rate\.rate=0\.5 is not k/n = 1/8"),
        (lambda d: d["rate"].update(ci95=[0.0, 1.0]), r"rate\.ci95=\[0\.0, 1\.0\] is not the Wilson interval of 1/8"),
        (lambda d: d["rates"]["hole"].pop("ci95"), r"rates\.hole: missing key\(s\) \['ci95'\]"),
        (lambda d: d["pair"][1].update(n="8"), r"pair\[1\]\.n must be an integer"),
        (lambda d: d.update(maybe=[1, 8]), r"maybe must be a mapping"),
    ],
)
def test_a_rate_that_its_counts_do_not_give_fails_at_load_with_its_path(change, message):
    data = to_dict(_Holder(Rate(1, 8), {"hole": Rate(2, 8)}, Rate(3, 8), (Rate(4, 8), Rate(5, 8))))
    assert from_dict(_Holder, copy.deepcopy(data)) == _Holder(
        Rate(1, 8), {"hole": Rate(2, 8)}, Rate(3, 8), (Rate(4, 8), Rate(5, 8))
    )
    change(data)
    with pytest.raises(ConfigError, match=message):
        from_dict(_Holder, data)


# --- serde: nested dataclasses, tuples, Optional, dicts of dataclasses, missing keys


@dataclass(frozen=True)
class _Leaf:
    x: int
    y: float = 0.0


@dataclass(frozen=True)
class _Tree:
    leaves: dict[str, _Leaf]
    nested: dict[str, dict[str, _Leaf]]
    chain: tuple[_Leaf, ...]
    optional: _Leaf | None
    counts: dict[str, int] = field(default_factory=dict)


def test_serde_reads_dicts_of_dataclasses_tuples_and_optionals():
    tree = _Tree({"a": _Leaf(1, 0.5)}, {"p": {"q": _Leaf(2)}}, (_Leaf(3), _Leaf(4, 1.5)), None, {"n": 5})
    data = json.loads(json.dumps(to_dict(tree)))
    assert data["nested"] == {"p": {"q": {"x": 2, "y": 0.0}}} and data["optional"] is None
    back = from_dict(_Tree, data)
    assert back == tree and isinstance(back.chain, tuple) and isinstance(back.leaves["a"], _Leaf)
    assert from_dict(_Tree, {**data, "optional": {"x": 7}}).optional == _Leaf(7)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["nested"]["p"]["q"].update(xx=1), r"unknown config key\(s\) \['xx'\] in nested\.p\.q"),
        (lambda d: d["nested"]["p"]["q"].pop("x"), r"missing key\(s\) \['x'\] in nested\.p\.q \(_Leaf\)"),
        (lambda d: d["chain"][1].update(x="4"), r"chain\[1\]\.x must be an integer"),
        (lambda d: d.pop("chain"), r"missing key\(s\) \['chain'\] \(_Tree\)"),
        (lambda d: d["leaves"].update(b=3), r"leaves\.b must be a mapping"),
        (lambda d: d["counts"].update(m=1.5), r"counts\.m must be an integer"),
        (lambda d: d.update(nested=[]), r"nested must be a mapping"),
    ],
)
def test_serde_names_the_dotted_path_of_a_wrong_or_missing_key(change, message):
    data = to_dict(_Tree({"a": _Leaf(1)}, {"p": {"q": _Leaf(2)}}, (_Leaf(3), _Leaf(4)), _Leaf(5), {"n": 1}))
    change(data)
    with pytest.raises(ConfigError, match=message):
        from_dict(_Tree, data)


# --- every stage's result type round trips, and a wrong key fails at load with its path


def analysis_result() -> AnalysisResult:
    goal = GoalUnitsRecord(0, "c", (3, 5), (0.1, -0.2), (0.9, 0.7), "the 2 most persistent step-type c units")
    units = UnitResponses(ResponseCounts(impulse=2, none=10, step=4), (1, 2, 3, 4), (5, 6))
    responses = ResponsesResult(
        ResponseRule(min_episodes=5),
        {"clean": {"layer0.h": units, "layer0.c": units}, "backdoor": {"layer0.h": units}},
        {"clean": 8, "backdoor": 4},
        "step responses in both agents",
    )
    switch = SwitchResult("activate", "step-units", Rate(20, 32), Rate(3, 32), Rate(1, 32))
    interventions = InterventionsResult("7x7/2", goal, (switch, SwitchResult("deactivate", "none", *[Rate(0, 32)] * 3)))
    row = UnintentionalRow("7x7/0", Rate(2, 32), Rate(5, 32), {"user_goal": 30, "adversary_goal": 2}, {"hole": 1})
    detection = TriggerDetectionRow("all", Rate(27, 30), Rate(2, 32), 0.93, 0.91, 0.5, 2)
    unintentional = UnintentionalResult((row,), (detection,), 7, {"activation": Rate(1, 2)}, ("finding.png",))
    layouts = LayoutSearch(
        LayoutSearchConfig(size=7, holes=3), (LayoutSearchResult(True, 2, Rate(3, 4), [[0, 1]], 32, 1.5),)
    )
    sequences = SequenceSearchResult(
        config=AnalysisConfig().sequence_search, found=1, relaxed_activation=[0.2, 0.9], rounded_activation=[0.1, 0.8],
        seconds=0.5, forward_steps=400, flip_rate=Rate(9, 30), baseline_rate=Rate(1, 30), walkable=0,
    )  # fmt: skip
    walk = WalkSearchResult(WalkSearchConfig(size=7, holes=3), 0, [0.1], 1, 0, [0.05], 0.25)
    return AnalysisResult(
        AnalysisConfig(size=7, holes=(2, 3)), responses, goal, interventions, unintentional,
        SearchResult(layouts, sequences, (walk,)), {"interventions": 1.25},
    )  # fmt: skip


def defense_result() -> DefenseResult:
    normal = NormalEnvArm(Rate(30, 32), Rate(1, 32))
    trojan = TrojanEnvArm(Rate(28, 32), Rate(3, 32), Rate(31, 32), Rate(0, 32), 1.0)
    monitor = MonitorResult("5x5/1", 32, 4.5, (32, 16), normal, normal, trojan,
                            TrojanEnvArm(Rate(2, 32), Rate(29, 32), Rate(30, 32), Rate(1, 32), None),
                            Rate(31, 32), Rate(30, 32))  # fmt: skip
    arm = MitigationArm("no mitigation", Rate(30, 32), Rate(25, 32), ())
    mitigation = {
        "before": arm,
        "pruned": MitigationArm("pruned 2 least-active units", Rate(30, 32), Rate(25, 32), (0, 7)),
        "fine_pruned": MitigationArm("fine-pruning", Rate(30, 32), Rate(25, 32), (0, 7)),
        "reset_goal_units_oracle": MitigationArm("holding the step units", Rate(29, 32), Rate(2, 32), (0,)),
    }
    goal = GoalUnitsRecord(1, "h", (0,), (0.0,), (1.0,), "oracle: ...")
    return DefenseResult("runs/backdoor/model", "backdoored", "5x5/1", "hole", monitor, goal, mitigation)


def detection_result() -> DetectionResult:
    predictions = (Prediction("m0", 0, 0.2), Prediction("m1", 1, 0.7))
    held = HeldOutScores(
        "lstm_sizes", 2, 0.75, 0.6, 0.2,
        (HeldOutGroup([8], 2, 1, 1.0, 0.3, 0.1), HeldOutGroup({"stages": [1]}, 1, 0, None, None, None)), (None,),
    )  # fmt: skip
    return DetectionResult(
        (Rejected("zz", "pickled"),), (GroupScores("all", 12, 2, 2, 1.0, 0.3, 0.1, predictions),), (held,),
        FunctionalSplit(0.5, 1, 0, 1.0, None), {"trigger": 1.0},
    )  # fmt: skip


@pytest.mark.parametrize(
    "result",
    [analysis_result(), defense_result(), detection_result(), TrajectoryResult(2, {"normal": "user_goal"})],
    ids=lambda r: type(r).__name__,
)
def test_every_result_type_round_trips_through_json(tmp_path, result):
    path = save_json(result, tmp_path / "result.json")
    assert load_json(type(result), path) == result


def test_derived_values_are_read_from_the_counts():
    a = analysis_result()
    assert a.interventions.results[0].episodes == 32 and a.unintentional.summaries[0].episodes == 32
    assert (a.unintentional.trigger_detection[0].positives, a.unintentional.trigger_detection[0].negatives) == (30, 32)
    layouts = a.search.layouts
    assert (layouts.restarts, layouts.found, layouts.episodes, layouts.seconds_per_found) == (1, 1, 32, 1.5)
    assert a.search.sequences.restarts == 32 and a.search.walks[0].seconds_per_found is None
    assert a.search.walks[0].target_density == pytest.approx(3 / 46)
    d = defense_result().mitigation
    assert list(d) == ["before", "pruned", "fine_pruned", "reset_goal_units_oracle"]
    assert (detection_result().clean_models, detection_result().backdoored_models) == (1, 1)


@pytest.mark.parametrize(
    ("result", "change", "message"),
    [
        (analysis_result(), lambda d: d["interventions"]["results"][1]["switch"].update(kk=0),
         r"interventions\.results\[1\]\.switch: unknown key\(s\) \['kk'\]"),
        (analysis_result(), lambda d: d["unintentional"]["summaries"][0].pop("activation"),
         r"missing key\(s\) \['activation'\] in unintentional\.summaries\[0\]"),
        (analysis_result(), lambda d: d["responses"]["agents"]["clean"]["layer0.c"]["counts"].update(stepp=1),
         r"\['stepp'\] in responses\.agents\.clean\.layer0\.c\.counts"),
        (analysis_result(), lambda d: d["config"]["layout_search"].update(sise=7),
         r"\['sise'\] in config\.layout_search"),
        (analysis_result(), lambda d: d["search"]["sequences"]["flip_rate"].update(rate=0.5),
         r"search\.sequences\.flip_rate\.rate=0\.5 is not k/n"),
        (defense_result(), lambda d: d["monitor"]["trojan_alarm"].pop("median_steps_to_detect"),
         r"missing key\(s\) \['median_steps_to_detect'\] in monitor\.trojan_alarm"),
        (defense_result(), lambda d: d["mitigation"]["pruned"].update(x=1),
         r"unknown config key\(s\) \['x'\] in mitigation\.pruned"),
        (detection_result(), lambda d: d["scores"][0]["predictions"][1].update(label="1"),
         r"scores\[0\]\.predictions\[1\]\.label must be an integer"),
        (detection_result(), lambda d: d["held_out"][0]["groups"][0].pop("backdoored"),
         r"\['backdoored'\] in held_out\[0\]\.groups\[0\]"),
    ],
)  # fmt: skip
def test_a_result_file_with_a_wrong_or_missing_key_fails_at_load_with_its_path(tmp_path, result, change, message):
    data = to_dict(result)
    change(data)
    path = tmp_path / "result.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=message) as err:
        load_json(type(result), path)
    assert str(path) in str(err.value)


def test_the_run_layout_reads_each_stage_typed_and_names_a_bad_file(tmp_path):
    layout = RunLayout(tmp_path)
    assert layout.analysis() is None and layout.defense() is None and layout.evaluation() == []
    for folder in (layout.analysis_dir, layout.defense_dir, layout.zoo_dir):
        folder.mkdir()
    save_json(analysis_result(), layout.analysis_file)
    save_json(defense_result(), layout.defense_file)
    save_json(detection_result(), layout.detection_file)
    assert (layout.analysis(), layout.defense(), layout.detection()) == (
        analysis_result(), defense_result(), detection_result())  # fmt: skip
    data = json.loads(layout.defense_file.read_text())
    data["monitor"]["normal_alarm"]["false_alarms"] = data["monitor"]["normal_alarm"].pop("false_alarm")
    layout.defense_file.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=r"defense\.json' is not a valid DefenseResult: .*monitor\.normal_alarm"):
        layout.defense()


def test_sweep_rows_round_trip_and_a_wrong_key_is_named(tmp_path):
    rows = [
        SweepRow("clean", "clean", "normal", 7, 0, Rate(30, 32), Rate(1, 32), Rate(1, 32), Rate(0, 32), 12.5, 0.98),
        SweepRow("backdoor", "backdoored", "trojan", 7, 7, Rate(20, 32), Rate(2, 32), Rate(0, 32), Rate(10, 32), 9.0,
                 None, seed=1),
    ]  # fmt: skip
    json_path, csv_path = write_sweep(rows, tmp_path)
    assert load_sweep(json_path) == rows
    assert [r["config"] for r in json.loads(json_path.read_text())] == ["7x7/0", "7x7/7"]
    header, first = csv_path.read_text().splitlines()[:2]  # the flat CSV: one column per number
    assert header.split(",")[6:9] == ["success", "ci_low", "ci_high"]
    assert first.split(",")[6:9] == [str(30 / 32), *map(str, wilson_interval(30, 32))]
    data = json.loads(json_path.read_text())
    data[1]["success"]["n"] = 33
    json_path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=r"\[1\]\.success\.rate=0\.625 is not k/n = 20/33"):
        load_sweep(json_path)
    data[1]["success"]["n"], data[1]["config"] = 32, "7x7/0"
    json_path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=r"\[1\]\.config='7x7/0' but size and holes give '7x7/7'"):
        load_sweep(json_path)
