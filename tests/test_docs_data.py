"""The documented figures that have their data committed under docs/data agree with it: each table or figure is
regenerated from the data and must appear in the docs as printed (a figure edited by hand, or data replaced without
the docs, fails here). Add a pair below when a documented run's data is committed."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT

DATA = ROOT / "docs" / "data"

MATRIX_TABLES = [("minigrid/matrix_minigrid_smoke.json", "results.md")]
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
]
"""a benchmark's JSON file, the page holding its table and the benchmark (``benchmarks/NAME --table JSON`` prints it)"""

FIGURE = re.compile(r"^(clean success \(user's object\)|trojan success \(adversary's after trigger\))\s+"
                    r"(\d\.\d{3} ± \d\.\d{3})\s+.*n=\d+\s+([\d., ]+)$")  # fmt: skip


@pytest.mark.parametrize(("data", "page"), MATRIX_TABLES)
def test_matrix_tables_in_the_docs_are_the_data_printed(data, page):
    printed = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "matrix_markdown.py"), str(DATA / data)],
        capture_output=True, text=True, check=True, cwd=ROOT,
    ).stdout  # fmt: skip
    text = (ROOT / "docs" / page).read_text()
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) > 10
    missing = [line for line in rows if line not in text]
    assert not missing, f"docs/{page} lacks {len(missing)} row(s) of {data}, e.g. {missing[0]}"


@pytest.mark.parametrize(("data", "page", "bench"), BENCH_TABLES)
def test_benchmark_tables_in_the_docs_are_the_data_printed(data, page, bench):
    printed = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / bench), "--table", str(DATA / data)],
        capture_output=True, text=True, check=True, cwd=ROOT,
    ).stdout  # fmt: skip
    text = (ROOT / "docs" / page).read_text()
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert len(rows) > 3
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
