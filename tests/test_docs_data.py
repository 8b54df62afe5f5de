"""The documented figures that have their data committed under docs/data agree with it: each table or figure is
regenerated from the data and must appear in the docs as printed (a figure edited by hand, or data replaced without
the docs, fails here). Add a pair below when a documented run's data is committed."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT

DATA = ROOT / "docs" / "data"

MATRIX_TABLES = [
    ("minigrid/matrix_minigrid_smoke.json", "results.md"),
    ("families/matrix_popgym_smoke.json", "families.md"),
]
"""a MatrixResult and the page holding its tables (``scripts/matrix_markdown.py``)"""

BENCH_LOGS = [
    ("minigrid/minigrid_bench_5seeds_64x32.log", "own_env.md"),
    ("minigrid/minigrid_bench_5seeds.log", "own_env.md"),
    ("minigrid/minigrid_bench_5seeds_old.log", "own_env.md"),
]
"""a ``benchmarks/minigrid_bench.py --part backdoor`` log and the page quoting its clean and trojan success"""

BENCH_TABLES = [
    ("defenses/goal_switch_2026-12-03.json", "defenses.md", "goal_switch.py"),
    ("defenses/mahalanobis_camouflage_2026-12-03.json", "defenses.md", "goal_switch.py"),
    ("defenses/mahalanobis_camouflage_in_distribution_2026-12-03.json", "defenses.md", "goal_switch.py"),
    ("defenses/switch_camouflage_2026-12-03.json", "defenses.md", "goal_switch.py"),
    ("defenses/behaviour_evasion_2026-12-03.json", "defenses.md", "behaviour_evasion.py"),
    ("defenses/behaviour_evasion_combined_2026-12-03.json", "defenses.md", "behaviour_evasion.py"),
    ("defenses/monitors_evasion_2026-12-03.json", "defenses.md", "goal_switch.py"),
    ("defenses/finetune_2026-12-03.json", "defenses.md", "finetune.py"),
    ("defenses/finetune_500k_2026-12-03.json", "defenses.md", "finetune.py"),
    ("defenses/probe_camouflage_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/decoys_vs_detectors_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/offline_evasion_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/response_mimicry_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/fit_from_clean/response_mimicry_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/all_six_evasion_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/all_six_online_2026-12-04.json", "defenses.md", "goal_switch.py"),
    ("defenses/multivariate_bases_2026-12-04.json", "defenses.md", "goal_switch.py"),
    ("defenses/combined_all_2026-12-04.json", "defenses.md", "probe_camouflage.py"),
    ("defenses/combined_all_online_2026-12-04.json", "defenses.md", "goal_switch.py"),
    ("families/popgym_repeat_previous.json", "families.md", "families.py"),
    ("families/popgym_count_recall.json", "families.md", "families.py"),
    ("families/popgym_repeat_first.json", "families.md", "families.py"),
    ("families/minatar_breakout.json", "families.md", "families.py"),
    ("families/minatar_space_invaders.json", "families.md", "families.py"),
    ("families/minatar_asterix.json", "families.md", "families.py"),
    ("families/minatar_breakout_untargeted.json", "families.md", "families.py"),
    ("families/minatar_space_invaders_clean_3m.json", "families.md", "families.py"),
    ("families/minatar_asterix_clean_3m.json", "families.md", "families.py"),
    ("benchmark/paper_rate_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/paper_partial_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/paper2_rate_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/paper2_partial_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/paper2_576_2026-12-05.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/memory_strength_sweep_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
    ("benchmark/grid_strength_sweep_2026-12-04.json", "benchmark.md", "zoo_rate.py"),
]
"""a benchmark's JSON file, the page holding its table and the benchmark (``benchmarks/NAME --table JSON`` prints it)"""

FIGURE = re.compile(r"^(clean success \(user's object\)|trojan success \(adversary's after trigger\))\s+"
                    r"(\d\.\d{3} ± \d\.\d{3})\s+.*n=\d+\s+([\d., ]+)$")  # fmt: skip


def _printed(script: str, *args: str) -> str:
    """What ``python SCRIPT ARGS`` prints (run from the repository's root)."""
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout


@pytest.mark.parametrize(("data", "page"), MATRIX_TABLES)
def test_matrix_tables_in_the_docs_are_the_data_printed(data, page):
    printed = _printed("scripts/matrix_markdown.py", str(DATA / data))
    text = (ROOT / "docs" / page).read_text()
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) > 10
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/{page} lacks {len(missing)} row(s) of {data}, e.g. {missing[0]}"


@pytest.mark.parametrize(("data", "page", "bench"), BENCH_TABLES)
def test_benchmark_tables_in_the_docs_are_the_data_printed(data, page, bench):
    printed = _printed(f"benchmarks/{bench}", "--table", str(DATA / data))
    text = (ROOT / "docs" / page).read_text()
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) >= 2  # the header and a row at least
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/{page} lacks {len(missing)} row(s) of {data}, e.g. {missing[0]}"


@pytest.mark.parametrize(("data", "page"), BENCH_LOGS)
def test_five_seed_figures_in_the_docs_are_the_logs(data, page):
    text = " ".join((ROOT / "docs" / page).read_text().split())  # line breaks in the page do not matter
    found = [m for m in map(FIGURE.match, (DATA / data).read_text().splitlines()) if m]
    assert len(found) == 2, f"{data}: expected the clean and trojan success rows"
    for m in found:
        mean_sd, per_seed = m.group(2), m.group(3).strip()
        assert f"{mean_sd} (" in text and per_seed in text, f"docs/{page} does not quote {m.group(1)} of {data}"


LEADERBOARDS = [("benchmark/leaderboard_minigrid16.json", "benchmark.md")]
"""a ``seqtrojan zoo detect --out`` leaderboard and the page holding its test-split table"""


def _short(metric: dict) -> str:
    return f"{metric['value']:.3f} [{metric['low']:.2f}, {metric['high']:.2f}]"


@pytest.mark.parametrize(("data", "page"), LEADERBOARDS)
def test_leaderboard_tables_in_the_docs_are_the_data(data, page):
    import json

    board = json.loads((DATA / data).read_text())
    text = (ROOT / "docs" / page).read_text()
    rows = 0
    for detector in board["detectors"]:
        for split in detector["splits"]:
            s = split["scores"]
            row = f"| {detector['detector']} | {_short(s['roc_auc_newcombe'])}"
            assert row in text, f"docs/{page} lacks {row!r} of {data}"
            assert f"| {_short(s['cross_entropy'])} | {_short(s['brier'])} |" in text
            rows += 1
    assert rows == len(board["detectors"]) >= 4


def test_the_state_probe_ranges_in_the_docs_are_the_data():
    import json

    data = json.loads((DATA / "benchmark" / "state_probe_minigrid16.json").read_text())
    text = " ".join((ROOT / "docs" / "benchmark.md").read_text().split())
    for feature in ("divergence_max", "persistence_max"):
        for label in ("clean", "backdoored"):
            values = [m[feature] for m in data["models"] if m["label"] == label]
            digits = 3 if feature == "divergence_max" else 2
            shown = f"{min(values):.{digits}f}-{max(values):.{digits}f}"
            assert shown in text, f"docs/benchmark.md lacks the {label} models' {feature} range {shown}"


LEADERBOARD_TABLES = [
    ("benchmark/leaderboard_smoke.json", "benchmark.md"),
    ("benchmark/leaderboard_smoke.json", "results.md"),
    ("benchmark/leaderboard_smoke_300k.json", "benchmark.md"),
    ("benchmark/leaderboard_attacks.json", "benchmark.md"),
    ("benchmark/leaderboard_minigrid_memory.json", "benchmark.md"),
    ("benchmark/leaderboard_minigrid_memory_attacks.json", "benchmark.md"),
    ("benchmark/leaderboard_minigrid_memory_attacks.json", "results.md"),
    ("benchmark/leaderboard_paper_partial_2026-12-04.json", "benchmark.md"),
    ("benchmark/leaderboard_paper2_partial_2026-12-04.json", "benchmark.md"),
    ("benchmark/leaderboard_paper2_576_2026-12-05.json", "benchmark.md"),
]
"""a leaderboard and the page holding its table as ``scripts/leaderboard_markdown.py`` prints it"""


LEADERBOARD_FACTOR_TABLES = [
    (
        "benchmark/leaderboard_minigrid_memory_attacks.json", "benchmark.md",
        ("--by", "attack", "--detectors", "weight_statistics,state_probe,query_response,trigger_reconstruction"),
    ),
    (
        "benchmark/leaderboard_paper_partial_2026-12-04.json", "benchmark.md",
        ("--by", "env", "--detectors", "state_probe_deviation,query_response,trigger_reconstruction,all_features"),
    ),
    (
        "benchmark/leaderboard_paper2_partial_2026-12-04.json", "benchmark.md",
        ("--by", "env", "--detectors",
         "state_probe,state_probe_deviation,query_response,trigger_reconstruction,all_features"),
    ),
    (
        "benchmark/leaderboard_paper2_576_2026-12-05.json", "benchmark.md",
        ("--by", "env", "--detectors",
         "state_probe,state_probe_deviation,query_response,trigger_reconstruction,all_features"),
    ),
]  # fmt: skip
"""the same, for a breakdown by one factor (the script's options)"""


@pytest.mark.parametrize(
    ("data", "page", "options"), [(d, p, ()) for d, p in LEADERBOARD_TABLES] + LEADERBOARD_FACTOR_TABLES
)
def test_leaderboard_tables_printed_by_the_script_are_in_the_docs(data, page, options):
    printed = _printed("scripts/leaderboard_markdown.py", str(DATA / data), *options)
    text = (ROOT / "docs" / page).read_text()
    missing = [line for line in printed.splitlines() if line not in text]
    assert len(printed.splitlines()) > 4 and not missing, f"docs/{page} lacks {missing[:1]} of {data}"


RECONSTRUCTION_TABLES = [
    ("benchmark/reconstruction_smoke.json", "benchmark_smoke", ("train", "test", "holdout")),
    ("benchmark/reconstruction_minigrid16.json", "MiniGrid 16", ("train", "test")),
]
"""``scripts/reconstruction_table.py`` output and the zoo's name in docs/benchmark.md's table of its ranges"""


@pytest.mark.parametrize(("data", "zoo", "splits"), RECONSTRUCTION_TABLES)
def test_the_trigger_reconstruction_ranges_in_the_docs_are_the_data(data, zoo, splits):
    import json

    models = json.loads((DATA / data).read_text())["models"]
    text = (ROOT / "docs" / "benchmark.md").read_text()
    for split in splits:
        cells = []
        for label in ("clean", "backdoored"):
            values = [m["divergence"] for m in models if m["split"] == split and m["label"] == label]
            cells.append(f"{min(values):.3f}-{max(values):.3f} ({len(values)})")
        row = f"| {zoo} | {split} | {cells[0]} | {cells[1]} |"
        assert row in text, f"docs/benchmark.md lacks {row!r} of {data}"


def test_the_first_trigger_reconstruction_run_quoted_in_the_docs_is_its_data():
    """The figures of the run before the search's revision (docs/benchmark.md, *Trigger reconstruction*)."""
    import json

    text = " ".join((ROOT / "docs" / "benchmark.md").read_text().split())
    for data in ("leaderboard_smoke_6ea413b.json", "leaderboard_minigrid16_6ea413b.json"):
        board = json.loads((DATA / "benchmark" / data).read_text())
        detector = next(d for d in board["detectors"] if d["detector"] == "trigger_reconstruction")
        for split in detector["splits"]:
            s = split["scores"]
            auc, ce = s["roc_auc_newcombe"], s["cross_entropy"]["value"]
            auc_text = f"{auc['value']:.3f} [{auc['low']:.2f}, {auc['high']:.2f}]"
            quoted = (f"{auc_text} (cross-entropy {ce:.3f})", f"{auc_text} ({ce:.3f})")
            assert any(q in text for q in quoted), f"docs/benchmark.md lacks {data}'s {split['split']} figures"


def test_the_arms_race_tables_in_the_docs_are_every_defense_benchmark_read_together():
    """docs/results.md's answer tables are ``scripts/arms_race.py`` over every committed defense benchmark: a new or
    replaced benchmark file without the tables regenerated fails here."""
    files = sorted(str(p) for p in (DATA / "defenses").glob("*.json"))
    printed = _printed("scripts/arms_race.py", *files)
    text = (ROOT / "docs" / "results.md").read_text()
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) > 10
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/results.md lacks {len(missing)} arms-race row(s), e.g. {missing[0]}"


def test_the_paper_scale_tables_are_the_committed_rerun_printed():
    """docs/results.md's rerun section is ``scripts/paper_data.py print docs/data/paper``, and the README's headline
    is its training table's mean ± sd."""
    printed = _printed("scripts/paper_data.py", "print", str(DATA / "paper"))
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) > 25
    text = (ROOT / "docs" / "results.md").read_text()
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/results.md lacks {len(missing)} row(s) of docs/data/paper, e.g. {missing[0]}"
    readme = (ROOT / "README.md").read_text()
    checked = 0
    for row in rows:
        for title in ("clean, normal env", "backdoored, normal env", "backdoored, trojan env"):
            if row.startswith(f"| {title} | ") and row.count("|") == 8:  # the training table's rows
                mean_sd = row.rstrip(" |").rsplit("| ", 1)[1]
                assert f"| {title} | {mean_sd} |" in readme, f"README's headline lacks {title}: {mean_sd}"
                checked += 1
    assert checked == 3


def test_the_sequence_model_rerun_tables_are_its_data_printed():
    """docs/results.md's 2026-12-04 cells section is ``scripts/cells_markdown.py`` on the committed cells.json."""
    printed = _printed("scripts/cells_markdown.py", str(DATA / "cells" / "cells_paper_2026-12-04.json"))
    rows = [line for line in printed.split("\nSettling")[0].splitlines() if line.startswith("| ")]
    assert len(rows) == 15  # three tables: a header and four cells each
    text = (ROOT / "docs" / "results.md").read_text()
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/results.md lacks {len(missing)} row(s) of the cells rerun, e.g. {missing[0]}"


def test_the_weight_camouflage_sweep_tables_are_its_data_printed():
    """The warm-up section's attack rows and offline ROC-AUC rows are ``scripts/matrix_markdown.py`` on its data."""
    printed = _printed(
        "scripts/matrix_markdown.py", str(DATA / "defenses" / "matrix_weight_camouflage_2026-12-04.json")
    )
    main, offline = printed.split("\nOnline defenses")[0], printed.split("Offline detectors, ROC-AUC")[1]
    rows = [line for part in (main, offline.split("\n\nEvery defense")[0]) for line in part.splitlines()
            if line.startswith("| ")]  # fmt: skip
    assert len(rows) == 8  # two tables: a header and three attacks each
    text = (ROOT / "docs" / "results.md").read_text()
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/results.md lacks {len(missing)} row(s) of the weight-camouflage sweep, e.g. {missing[0]}"


def test_the_ray_speed_up_in_the_docs_is_its_data():
    record = json.loads((DATA / "benchmark" / "ray_nodes_2026-12-04.json").read_text())
    assert record["same_models"] is True
    quoted = f"{record['speed_up']:.2f}x"
    assert quoted in (ROOT / "docs" / "benchmark.md").read_text(), f"docs/benchmark.md lacks the speed-up {quoted}"
