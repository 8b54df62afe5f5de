"""The end-to-end reproduction on a tiny scale: every stage's outputs, the report, and resuming."""

from __future__ import annotations

import csv
import itertools
import json
import re
import statistics
from html.parser import HTMLParser

import pytest

from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.seeds import find_summary, summarise_over_seeds
from seqtrojan.evaluation.sweep import load_sweep
from seqtrojan.experiment_results import CurvesResult, TradeoffResult
from seqtrojan.experiments.curves import aggregate_curves
from seqtrojan.experiments.reproduce import ReproduceConfig, load_reproduce_config, reproduce
from seqtrojan.experiments.specs import deep_merge
from seqtrojan.report.sections.tables import seed_cell
from seqtrojan.serde import from_dict, load_json

TINY_STAGES = [{"size": 5, "holes": 0}, {"size": 5, "holes": 1}]
TINY_SET = {
    "env": {"size": 5, "holes": 1},
    "ppo": {"total_steps": 8192, "num_envs": 64, "rollout_steps": 32, "num_minibatches": 2, "update_epochs": 2},
    "curriculum": {"stages": TINY_STAGES},
    "run": {"eval_episodes": 32, "checkpoint_every": 4096, "progress": False},
}
TINY = {
    "clean": {"preset": "clean_s17_h30", "set": TINY_SET},
    "backdoor": {"preset": "trojan_s17_h30", "set": deep_merge(TINY_SET, {"backdoor": {"eval_episodes": 16}})},
    "evaluation": {"configs": "7x7/0,7x7/7", "episodes": 32},
    "curves": {"configs": [[5, 0], [5, 1]], "seeds": 2, "total_steps": 4096, "num_envs": 32, "points": 5},
    "trajectory": {"size": 5, "holes": 1, "trigger_step": 2},
    "analysis": {
        "size": 7,
        "holes": [2, 3],
        "episodes": 40,
        "trigger_step": 2,
        "rule": {"min_episodes": 5, "response_window": 2, "late_start": 3, "late_end": 6},
        "intervention_episodes": 32,
        "unintentional_configs": "7x7/0,7x7/3",
        "unintentional_episodes": 32,
        "layout_search": {
            "size": 7,
            "holes": 3,
            "population": 4,
            "rollouts": 4,
            "generations": 2,
            "elite": 2,
            "restarts": 1,
        },
        "sequence_search": {"length": 6, "restarts": 4, "steps": 10},
        "walk_search": {"size": 7, "holes": 3, "length": 6, "restarts": 4, "steps": 10},
    },
    "defense": {
        "monitor": {"calibration_episodes": 40, "eval_episodes": 32, "false_alarm_target": 0.05},
        "mitigation": {"finetune_steps": 2048, "calibration_episodes": 32, "eval_episodes": 32},
        "oracle_episodes": 40,
    },
    "tradeoff": {"penalties": [-1.0, -4.0], "configs": "7x7/0,7x7/3", "episodes": 16, "seeds": 2},
    "zoo": {
        "clean": 2,
        "backdoored": 2,
        "total_steps": 2048,
        "num_envs": 32,
        "eval_episodes": 16,
        "lstm_sizes": [[8]],
        "curricula": [[{"size": 5, "holes": 0}]],
    },
    "zoo_workers": 1,
}


class _Tables(HTMLParser):
    """Every <table> of a page as {"heading", "summary", "rows"}: the last <h2>/<h3> and <summary> text before it,
    and its rows as lists of cell texts (tags dropped, entities decoded, white space collapsed)."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: list[dict] = []
        self.heading = self.summary = ""
        self._text: list[str] | None = None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        if tag in ("h2", "h3", "summary", "td", "th"):
            self._text = []
        elif tag == "table":
            self.tables.append({"heading": self.heading, "summary": self.summary, "rows": []})
        elif tag == "tr":
            self.tables[-1]["rows"].append([])

    def handle_endtag(self, tag):
        if tag not in ("h2", "h3", "summary", "td", "th") or self._text is None:
            return
        text = " ".join("".join(self._text).split())
        self._text = None
        if tag in ("h2", "h3"):
            self.heading, self.summary = text, ""
        elif tag == "summary":
            self.summary = text
        else:
            self.tables[-1]["rows"][-1].append(text)

    def handle_data(self, data):
        if self._text is not None:
            self._text.append(data)


def _table(tables: list[dict], heading: str, summary: str = "", first_column: str | None = None) -> list[list[str]]:
    """The rows (header first) of the one table under a heading starting with ``heading``, after a <summary>
    starting with ``summary`` (none when empty), whose header starts with ``first_column`` if given."""
    (found,) = [
        t for t in tables
        if t["heading"].startswith(heading) and (t["summary"].startswith(summary) if summary else not t["summary"])
        and (first_column is None or t["rows"][0][0] == first_column)
    ]  # fmt: skip
    return found["rows"]


def _td_text(td: str) -> str:
    """The text of one table cell as produced by report.html's formatting functions."""
    return _Tables(f"<table><tr>{td}</tr></table>").tables[0]["rows"][0][0]


def _rate(entry: dict) -> str:
    """A rate with its 95% interval, as the report shows it: '0.125 [0.050, 0.281]' (``entry``: a rate as the JSON
    files hold it, {"k", "n", "rate", "ci95"})."""
    return f"{entry['rate']:.3f} [{entry['ci95'][0]:.3f}, {entry['ci95'][1]:.3f}]"


# The evaluation tables: which (agent role, env) each column title shows.
EVALUATION_TABLES = {
    "Headline": {
        "clean agent, normal env": ("clean", "normal"),
        "backdoored agent, normal env": ("backdoor", "normal"),
        "backdoored agent, trojan env": ("backdoor", "trojan"),
    },
    "Table 1": {"clean agent": ("clean", "normal"), "backdoored agent": ("backdoor", "normal")},
    "Table 2": {"backdoored agent": ("backdoor", "trojan")},
}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro")
    report = reproduce(from_dict(ReproduceConfig, TINY), out, scale="tiny", log=lambda *_: None)
    return out, report


def test_every_stage_writes_its_outputs(tiny_run):
    out, _ = tiny_run
    for path in (
        "runs/clean/model/card.json", "runs/backdoor/model/card.json", "evaluation/evaluation.json",
        "evaluation/evaluation.csv", "curves/curves.csv", "curves/curves.json", "curves/curves.png",
        "trajectory.png", "trajectory_normal.txt", "trajectory_trojan.txt", "timings.json", "reproduce.yaml",
        "analysis/analysis.json", "analysis/responses.json", "analysis/interventions.json", "analysis/search.json",
        "analysis/findings.json", "analysis/traces/backdoor_trojan.safetensors", "analysis/figures/responses_clean.png",
        "defense/defense.json", "zoo/manifest.json", "zoo/detection.json", "tradeoff/tradeoff.json",
        "runs/backdoor_penalty-4/model/card.json",
    ):  # fmt: skip
        assert (out / path).exists(), path
    rows = json.loads((out / "evaluation" / "evaluation.json").read_text())
    cells = {(r["agent"], r["env"], r["config"]) for r in rows}
    assert ("backdoor", "trojan", "7x7/7") in cells and ("clean", "normal", "5x5/1") in cells  # + training grid
    assert next(r for r in rows if r["config"] == "7x7/7" and r["agent"] == "clean")["paper"] == 0.928
    assert set(json.loads((out / "timings.json").read_text())) >= {"train_clean", "train_backdoor", "curves"}
    tradeoff = load_json(TradeoffResult, out / "tradeoff" / "tradeoff.json")
    agents = [(a.penalty, a.seed, a.model) for a in tradeoff.agents]
    assert agents == [
        (-1.0, 0, "runs/backdoor/model"),
        (-1.0, 1, "runs/backdoor_penalty-1_seed1/model"),
        (-4.0, 0, "runs/backdoor_penalty-4/model"),
        (-4.0, 1, "runs/backdoor_penalty-4_seed1/model"),
    ]
    summary = tradeoff.penalties  # the backdoored agent itself is the -1 baseline's first seed
    assert [(p.penalty, p.seeds) for p in summary] == [(-1.0, 2), (-4.0, 2)]
    rates = [a.trojan_success.value for a in tradeoff.agents[:2]]
    assert summary[0].trojan_success.mean == pytest.approx(sum(rates) / 2)
    assert summary[0].trojan_success.sd == pytest.approx(statistics.stdev(rates))
    assert all(a.activation.n == 2 * 16 and len(a.per_config) == 2 for a in tradeoff.agents)
    card = json.loads((out / "runs/backdoor_penalty-4/model/card.json").read_text())
    assert card["config"]["env"]["rewards"]["false_activation"] == -4.0 and card["label"] == "backdoored"
    analysis = json.loads((out / "analysis" / "analysis.json").read_text())
    assert [d["grid"] for d in analysis["unintentional"]["trigger_detection"]] == ["7x7/0", "7x7/3", "all"]
    walks = analysis["search"]["walks"]
    assert [w["config"]["density_weight"] for w in walks] == [2.0, 0.0] and all(w["walkable"] == 4 for w in walks)


def test_report_is_self_contained_with_tables_figures_and_configs(tiny_run):
    _, report = tiny_run
    text = report.read_text()
    for heading in ("Headline", "Table 1", "Table 2", "Learning curves", "with and without the trigger",
                    "response types", "editing the goal units", "Unintentional triggers", "on purpose",
                    "Online state monitor", "Mitigation", "Offline detection",
                    "as a trigger detector", "adversary's trade-off", "walks of 6 views",
                    "Training", "Machine and timings"):  # fmt: skip
        assert heading in text, heading
    assert len(re.findall(r"src='data:image/png;base64,", text)) >= 4 + 8  # curves, trajectory, 2 responses, heatmaps
    assert "0.928" in text and "0.549" in text  # the paper's numbers beside ours
    assert "backdoor agent config" in text and not re.findall(r"src='(?!data:)", text)  # nothing external


def test_report_numbers_are_those_of_the_json_it_was_built_from(tiny_run):
    """Every number of the evaluation tables, and key rates of the curves, analysis, defense, zoo detection and
    trade-off sections, equal the JSON files the report was built from, in the row and column that name them."""
    out, report = tiny_run
    tables = _Tables(report.read_text()).tables

    # Evaluation: each (agent, env, grid) cell of evaluation.json, over its training seeds, in its row and column.
    raw = json.loads((out / "evaluation" / "evaluation.json").read_text())
    seeds: dict[tuple[str, str, str], list[dict]] = {}
    for r in raw:
        seeds.setdefault((r["agent"], r["env"], r["config"]), []).append(r)
    summaries = summarise_over_seeds(load_sweep(out / "evaluation" / "evaluation.json"))
    shown = set()
    for heading, columns in EVALUATION_TABLES.items():
        header, *rows = _table(tables, heading)
        if heading == "Headline":  # one row: the backdoored agent's training grid
            expected = [json.loads((out / "runs/backdoor/model/card.json").read_text())["metrics"]["grid"]]
        else:
            expected = list(dict.fromkeys(r["config"] for r in raw))
        assert [row[0] for row in rows] == expected, heading
        for row in rows:
            for i, title in enumerate(header):
                if title not in columns:
                    continue
                agent, env = columns[title]
                cell = seeds[(agent, env, row[0])]
                paper = cell[0]["paper"]
                assert header[i + 1] == "paper" and row[i + 1] == ("" if paper is None else f"{paper:.3f}")
                mean = statistics.fmean(r["success"]["rate"] for r in cell)
                assert row[i].split()[0] == f"{mean:.3f}", (heading, title, row[0])
                summary = find_summary(summaries, agent, env, row[0])
                assert row[i] == _td_text(seed_cell(summary)), (heading, title, row[0])
                shown.add((agent, env, row[0]))
    assert shown == set(seeds)  # every evaluated cell is in a table
    header, *rows = _table(tables, "Table 2", summary="Every seed's cell")
    col = {name: header.index(name) for name in ("agent", "seed", "env", "grid", "success", "95% interval", "trials")}
    got = sorted(tuple(row[col[name]] for name in col) for row in rows)
    want = sorted(
        (r["agent"], str(r["seed"]), r["env"], r["config"], f"{r['success']['rate']:.3f}",
         f"[{r['success']['ci95'][0]:.3f}, {r['success']['ci95'][1]:.3f}]", str(r["success"]["n"]))
        for r in raw
    )  # fmt: skip
    assert got == want

    # Learning curves: each grid's final mean and sd over seeds.
    curves = json.loads((out / "curves" / "curves.json").read_text())
    _, *rows = _table(tables, "Learning curves")
    assert {row[0]: row[1] for row in rows} == {
        c["grid"]: f"{c['mean'][-1]:.3f} ± {c['std'][-1]:.3f}" for c in curves["curves"]
    }

    # Analysis: the goal-unit edits, unintentional triggers and the agent as a trigger detector.
    analysis = json.loads((out / "analysis" / "analysis.json").read_text())
    _, *rows = _table(tables, "Looking inside: editing the goal units")
    results = analysis["interventions"]["results"]
    assert [row[1] for row in rows] == [r["units"] for r in results]
    assert [row[2] for row in rows] == [_rate(r["switch"]) for r in results]
    assert [row[3] for row in rows] == [_rate(r["hole"]) for r in results]
    _, *rows = _table(tables, "Unintentional triggers")
    assert [row[:3] for row in rows] == [
        [s["grid"], _rate(s["activation"]), _rate(s["deactivation"])] for s in analysis["unintentional"]["summaries"]
    ]
    _, *rows = _table(tables, "The agent as a trigger detector")
    assert [row[:3] for row in rows] == [
        [d["grid"], _rate(d["recall"]), _rate(d["false_positive_rate"])]
        for d in analysis["unintentional"]["trigger_detection"]
    ]

    # Defenses: the monitor's rates, the mitigation rows, the zoo detector's scores.
    defense = json.loads((out / "defense" / "defense.json").read_text())
    m = defense["monitor"]
    _, *rows = _table(tables, "Online state monitor")
    monitor = dict(rows)
    assert monitor["false-alarm rate (normal env)"] == _rate(m["normal_alarm"]["false_alarm"])
    assert monitor["detection rate (trojan env, alarm at or after the trigger)"] == _rate(m["trojan_alarm"]["detected"])
    assert monitor["attack success without the monitor"] == _rate(m["attack_success_undefended"])
    assert monitor["attack success with alarm-and-reset"] == _rate(m["trojan_reset"]["attack_success"])
    assert monitor["clean success with alarm-and-reset"] == _rate(m["normal_reset"]["success"])
    _, *rows = _table(tables, "Mitigation")
    mit = defense["mitigation"]
    assert rows[0] == ["no mitigation", _rate(mit["before"]["clean_success"]), _rate(mit["before"]["attack_success"])]
    assert rows[1][1:] == [_rate(mit["pruned"]["clean_success"]), _rate(mit["pruned"]["attack_success"])]
    detection = json.loads((out / "zoo" / "detection.json").read_text())
    header, *rows = _table(tables, "Offline detection", first_column="features")
    cols = [next(i for i, h in enumerate(header) if h.startswith(n)) for n in ("ROC-AUC", "cross-entropy", "Brier")]
    assert [[row[0], *(row[i].split()[0] for i in cols)] for row in rows] == [
        [s["group"], f"{s['roc_auc']:.3f}", f"{s['cross_entropy']:.3f}", f"{s['brier']:.3f}"]
        for s in detection["scores"]
    ]  # each score's leading number (a cell may add an interval)

    # The adversary's trade-off: each penalty's trojan success over its seeds.
    tradeoff = json.loads((out / "tradeoff" / "tradeoff.json").read_text())
    header, *rows = _table(tables, "The adversary's trade-off")
    i = header.index("trojan success")
    assert [row[i] for row in rows] == [
        f"{p['trojan_success']['mean']:.3f}"
        + (f" ± {p['trojan_success']['sd']:.3f}" if len(p["trojan_success"]["values"]) > 1 else "")
        for p in tradeoff["penalties"]
    ]


def test_a_second_call_reuses_finished_stages(tiny_run):
    out, _ = tiny_run
    before = (out / "runs" / "clean" / "model" / "card.json").stat().st_mtime
    reproduce(from_dict(ReproduceConfig, TINY), out, scale="tiny", log=lambda *_: None)
    assert (out / "runs" / "clean" / "model" / "card.json").stat().st_mtime == before


def test_curves_are_aggregated_over_seeds(tiny_run):
    out, _ = tiny_run
    curves = aggregate_curves(out / "curves" / "curves.csv", points=5)
    assert [c.grid for c in curves.curves] == ["5x5/0", "5x5/1"]
    assert load_json(CurvesResult, out / "curves" / "curves.json") == curves  # the stage saved the same
    data = curves.curves[0]
    assert data.seeds == 2 and len(data.mean) == 5
    runs: dict[int, list[tuple[int, float]]] = {}  # seed -> (env steps, score) from the CSV, recomputed by hand
    with (out / "curves" / "curves.csv").open() as fh:
        for r in csv.DictReader(fh):
            assert float(r["score"]) == pytest.approx(float(r["normal_success"]) + float(r["trojan_success"]))
            if r["config"] == "5x5/0":
                runs.setdefault(int(r["seed"]), []).append((int(r["env_steps"]), float(r["score"])))
    assert sorted(runs) == [0, 1]
    start, end = min(run[0][0] for run in runs.values()), min(run[-1][0] for run in runs.values())
    assert data.env_steps == pytest.approx([start + (end - start) * i / 4 for i in range(5)])

    def at(run, x):  # the seed's curve, linear between its logged points (flat before its first)
        if x <= run[0][0]:
            return run[0][1]
        (x0, y0), (x1, y1) = next((a, b) for a, b in itertools.pairwise(run) if a[0] <= x <= b[0])
        return y0 + (y1 - y0) * (x - x0) / (x1 - x0)

    for x, mean, std in zip(data.env_steps, data.mean, data.std, strict=True):
        values = [at(run, x) for run in runs.values()]
        assert mean == pytest.approx(statistics.fmean(values)) and std == pytest.approx(statistics.pstdev(values))


def test_scale_files_load_and_bad_presets_are_named(tmp_path):
    assert load_reproduce_config("smoke").evaluation.episodes == 200
    assert load_reproduce_config("paper").curves.seeds == 10
    with pytest.raises(ConfigError, match="preset 'nope' not found"):
        reproduce(from_dict(ReproduceConfig, {"clean": {"preset": "nope"}}), tmp_path)


def test_the_training_queue_holds_every_known_agent_longest_first(tmp_path):
    from seqtrojan.artifacts import RunLayout
    from seqtrojan.experiments.reproduce import queued_jobs

    config = load_reproduce_config("paper")
    jobs = queued_jobs(config, RunLayout(tmp_path))
    ids = [job.id for job in jobs]
    assert len(ids) == len(set(ids)) == 2 * 5 + 3 * 10 + 2  # headline, curves, trade-off (-1 seed 1 is reused)
    steps = [job.config.ppo.total_steps for job in jobs]
    assert steps == sorted(steps, reverse=True)
    assert "backdoor_seed1" in ids and "backdoor_penalty-1_seed1" not in ids
    curve_steps = {job.id.split("_")[0]: job.config.ppo.total_steps for job in jobs if job.id[0].isdigit()}
    assert curve_steps == {"5x5h0": 200_000, "5x5h1": 300_000, "7x7h3": 900_000}


@pytest.mark.parametrize("steps", [[100, 200], [100, 0, 300]])
def test_curve_steps_per_config_are_checked(steps):
    with pytest.raises(ConfigError, match=r"curves\.config_steps"):
        from_dict(ReproduceConfig, {"curves": {"configs": [[5, 0], [5, 1], [7, 3]], "config_steps": steps}})
