"""The benchmark leaderboard as a report section: its rows are the leaderboard's scores, the models left out are
named, and the reproduction's report shows it when the zoo has a leaderboard (``zoo detect --out`` writes its own
page too: tests/benchmark/test_benchmark.py)."""

from __future__ import annotations

import dataclasses
import re
import shutil

from seqtrojan.artifacts import RunLayout
from seqtrojan.benchmark.leaderboard import Leaderboard
from seqtrojan.defense.results import Rejected
from seqtrojan.report.html import build_report
from seqtrojan.report.sections.leaderboard import leaderboard_page, leaderboard_section
from seqtrojan.serde import load_json
from tests.conftest import ROOT

DATA = ROOT / "docs" / "data" / "benchmark" / "leaderboard_smoke.json"


def _text(cell: str) -> str:
    return re.sub(r"<[^>]+>", "", cell).strip()


def _rows(page: str) -> list[list[str]]:
    """Every table row of ``page`` as the text of its cells."""
    return [[_text(c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)] for row in re.findall(r"<tr>(.*?)</tr>", page)]


def test_the_section_s_rows_are_the_leaderboard_s_scores():
    board = load_json(Leaderboard, DATA)
    rows = _rows("".join(leaderboard_section(board)))
    main = [r for r in rows if len(r) == 8 and re.fullmatch(r"\d+ \(\d+\)", r[2])]  # models (poisoned) third
    assert len(main) == sum(len(d.splits) for d in board.detectors) == 12
    for d in board.detectors:
        for r in d.splits:
            s = r.scores
            auc, ce = s.roc_auc_newcombe, s.cross_entropy
            assert auc.value is not None and ce.value is not None
            auc_text = f"{auc.value:.3f} [{auc.low:.2f}, {auc.high:.2f}]"
            row = [
                d.detector,
                r.split,
                f"{s.models} ({s.poisoned})",
                auc_text,
                f"{ce.value:.3f} [{ce.low:.2f}, {ce.high:.2f}]",
            ]
            assert row in [m[:5] for m in main], row
    by_factor = [r for r in rows if len(r) == 8 and r[2] in ("cell", "env", "lstm_sizes", "trigger_value")]
    assert by_factor and all(r[0] in [d.detector for d in board.detectors] for r in by_factor)
    assert "trigger_reconstruction" in {r[0] for r in main}


def test_the_models_left_out_are_named_and_text_is_escaped():
    board = dataclasses.replace(
        load_json(Leaderboard, DATA), zoo="zoo<b>", excluded=(Rejected("m0099", "backdoor not functional (0.1)"),),
        rejected=(Rejected("m0098", "weights <tampered>"),),
    )  # fmt: skip
    page = leaderboard_page(board)
    assert page.startswith("<!doctype html>") and page.endswith("</html>")
    assert "zoo&lt;b&gt;" in page and "weights &lt;tampered&gt;" in page and "<b>zoo<b>" not in page
    assert "1 model(s) excluded (backdoor not working or task not learned)" in page
    assert "m0099: backdoor not functional (0.1)" in page


def test_the_reproduction_s_report_shows_a_leaderboard_only_when_the_zoo_has_one(tmp_path):
    without = build_report(tmp_path, "tiny", {"seqtrojan": "test"}).read_text()
    assert "benchmark leaderboard" not in without
    layout = RunLayout(tmp_path)
    layout.leaderboard_file.parent.mkdir(parents=True)
    shutil.copy(DATA, layout.leaderboard_file)
    with_board = build_report(tmp_path, "tiny", {"seqtrojan": "test"}).read_text()
    assert "<h2>Offline detection: the benchmark leaderboard</h2>" in with_board
    assert "trigger_reconstruction" in with_board
