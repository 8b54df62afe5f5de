"""Every figure in README.md and docs/ names its source (``scripts/figure_sources.py --check``), and the script's
rules: what a figure is, and which command, date, data file or quotation counts as its source."""

from __future__ import annotations

import pytest

from scripts.figure_sources import (
    PENDING,
    Finding,
    check,
    main,
    pages,
    paper_values,
    scan,
    scan_text,
)
from tests.conftest import ROOT

PAPER = paper_values()


def sources(text: str) -> dict[str, str | None]:
    """Each figure of a page -> its source kind (None: no source)."""
    return {f.figure.number: (f.source.kind if f.source else None) for f in scan_text(text, "page.md", PAPER)}


def figures(text: str) -> list[str]:
    return [f.figure.number for f in scan_text(text, "page.md", PAPER)]


# ------------------------------------------------------------------------------------------------- the repository


def test_every_figure_in_the_docs_has_a_source():
    findings: list[Finding] = [f for page in pages(ROOT) for f in scan(page, ROOT, PAPER)]
    assert len(findings) > 1000  # the pages were read
    result = check(findings)
    listed = "\n".join(f"{f.figure.path}:{f.figure.line} {f.figure.number}" for f in result.missing[:20])
    assert not result.missing, (
        f"{len(result.missing)} figure(s) without a source (run `python scripts/figure_sources.py --check`): state the "
        f"command and date that made each, or its data under docs/data/, beside it:\n{listed}"
    )
    assert not result.stale, f"PENDING sections with no unsourced figure left, remove them: {result.stale}"


def test_the_command_line_check_lists_a_figure_without_a_source(tmp_path, capsys):
    assert main(["--check", str(ROOT / "docs" / "world.md")]) == 0
    page = tmp_path / "page.md"
    page.write_text("# Page\n\nIntro.\n\nTraining ran at 78,240 env steps/s.\n")
    assert main(["--check", str(page)]) == 1
    assert f"{page}:5" in capsys.readouterr().out


def test_a_pending_section_is_tolerated_until_it_is_sourced():
    page = "## Measured\n\nTraining ran at 3.3k env steps/s.\n"
    findings = scan_text(page, "docs/x.md", PAPER)
    assert not check(findings, {}).ok
    assert check(findings, {("docs/x.md", "Measured"): "being rewritten"}).ok
    sourced = scan_text(page.replace("s/s.", "s/s (`python b.py`, 2026-12-03)."), "docs/x.md", PAPER)
    assert check(sourced, {("docs/x.md", "Measured"): "being rewritten"}).stale == (("docs/x.md", "Measured"),)
    assert all(PENDING.values())  # each entry (none today: every section is sourced) says why


# -------------------------------------------------------------------------------------------------- what a figure is


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Clean success 0.933 ± 0.019 over 5 seeds.", ["0.933", "0.019"]),
        ("49.0k random actions/s, 78,240 env steps/s, 13.7 s and 23 min.", ["49.0k", "78,240", "13.7 s", "23 min"]),
        ("Detected in 99.7% of the episodes, 1.22x faster, 7x more wall time.", ["99.7%", "1.22x", "7x"]),
        ("The largest difference is 3.6e-7.", ["3.6e-7"]),
    ],
)  # fmt: skip
def test_measured_numbers_are_figures(text, expected):
    assert figures(text) == expected


@pytest.mark.parametrize(
    "text",
    [
        "Python 3.10+ and torch 2.13.0, YAML 1.2, torch's format since 1.6.",
        "On 2026-12-02 at 16:40, see section 5.2 and commit 6e6ec7d.",
        "Trained on 17x17/30 with a 64+32 LSTM, 5M env steps, 3 seeds, 1000 episodes.",
        "Run `seqtrojan train --ppo.learning-rate 0.002 --steps 153600` (option values are code).",
        "Calibrated at a 1% false-alarm target with 95% Wilson intervals, q = 0.05, weight 0.5, margin 2.5.",
        "Log in `docs/data/minigrid/minigrid_bench_5seeds.log` and results/speed_i_0.5.log.",
        "## Training (17x17, 5M env steps, 0.95 target)",
        "```python\nx = 0.933  # 13.7 s\n```",
        "| field | default | meaning |\n|---|---|---|\n| `quantile` | 0.05 | in [0, 0.5) |",
        "```bash\nseqtrojan train --config minigrid_memory   # clean (1.5M steps)\n```",
    ],
)
def test_versions_dates_settings_and_code_are_not_figures(text):
    assert figures(text) == []


def test_a_shell_comment_is_read_for_figures():
    assert figures("```bash\nseqtrojan reproduce --scale paper   # 25 min on 2 cores\n```") == ["25 min"]


# ------------------------------------------------------------------------------------------------- what a source is


def test_a_command_and_a_date_in_the_paragraph_are_a_source():
    text = "## Speed\n\nIntro.\n\nTraining ran at 78,240 env steps/s (`python bench.py`, 2026-11-25).\n"
    assert sources(text) == {"78,240": "command+date"}


def test_a_command_elsewhere_in_the_file_is_not_a_source():
    text = (
        "## Speed\n\nIntro.\n\nTraining ran at 78,240 env steps/s.\n\n"
        "## Other\n\nRun `python benchmarks/train_throughput.py` on 2026-11-25.\n"
    )
    assert sources(text) == {"78,240": None}


def test_a_command_without_a_date_or_a_date_without_a_command_is_not_a_source():
    assert sources("## S\n\nIntro.\n\nIt ran at 78,240 env steps/s (`python b.py`).\n") == {"78,240": None}
    assert sources("## S\n\nIntro.\n\nIt ran at 78,240 env steps/s on 2026-11-25.\n") == {"78,240": None}


def test_command_and_date_must_stand_together_not_in_two_paragraphs():
    text = "## S\n\nIntro.\n\nMeasured on 2026-11-25.\n\nIt ran at 78,240 env steps/s (`python b.py`).\n"
    assert sources(text) == {"78,240": None}


def test_a_tables_caption_covers_the_table():
    table = "| grid | steps/s |\n|---|---|\n| 7x7/3 | 78,240 |\n"
    captioned = f"## S\n\nIntro.\n\n`python benchmarks/train_throughput.py`, run alone on 2026-11-25:\n\n{table}"
    assert sources(captioned) == {"78,240": "command+date"}
    uncaptioned = f"## S\n\nIntro.\n\nRun alone:\n\n{table}\n`python benchmarks/train_throughput.py`, 2026-11-25.\n"
    assert sources(uncaptioned) == {"78,240": None}  # a paragraph below the table is no caption


def test_a_lists_intro_covers_its_items():
    text = "## S\n\nIntro.\n\nThe runs of 2026-12-02 (`seqtrojan cells --scale paper`):\n\n- lstm 0.972\n- gru 0.987\n"
    assert sources(text) == {"0.972": "command+date", "0.987": "command+date"}


def test_the_sections_first_paragraph_covers_the_section_and_a_details_block_stands_alone():
    intro = "## Defenses\n\nOne run of `seqtrojan reproduce --scale paper` on 2026-12-02.\n\n"
    assert sources(intro + "Detection 0.983.\n") == {"0.983": "command+date"}
    earlier = intro + "<details><summary>The earlier run</summary>\n\nDetection 0.997.\n\n</details>\n"
    assert sources(earlier) == {"0.997": None}
    dated = earlier.replace("The earlier run", "The run of 2026-11-25, <code>seqtrojan reproduce --scale paper</code>")
    assert sources(dated) == {"0.997": "command+date"}
    assert sources("## Other\n\nIntro.\n\nDetection 0.983.\n") == {"0.983": None}


def test_a_committed_data_file_named_beside_it_is_a_source():
    assert sources("Clean 0.998 (`docs/data/minigrid/minigrid_bench_5seeds_64x32.log`).\n") == {"0.998": "data"}
    assert sources("Clean 0.998 (`docs/data/minigrid/no_such_file.log`).\n") == {"0.998": None}


def test_the_papers_numbers_quoted_as_the_papers_are_sourced_and_ours_beside_them_are_not():
    text = "## S\n\nIntro.\n\nOurs 0.933 ± 0.019 against the paper's 0.549.\n"
    assert sources(text) == {"0.933": None, "0.019": None, "0.549": "paper"}
    table = "| grid | ours | paper |\n|---|---|---|\n| 7x7/7 | 0.933 | 0.549 |\n"
    assert sources(table) == {"0.933": None, "0.549": "paper"}
    assert sources("At the paper scale the agents reached 0.934.\n") == {"0.934": None}


def test_an_observation_stated_as_without_a_stored_command_is_its_own_kind():
    text = "Training slowed to 3.8k env steps/s (one observation of 2026-11, no stored command).\n"
    assert sources(text) == {"3.8k": "unsourced observation"}


def test_a_comment_is_sourced_by_its_own_line():
    block = "```bash\nseqtrojan cells --scale paper   # 73 min here on 2026-12-02\nseqtrojan cells   # 40 min\n```\n"
    assert sources(block) == {"73 min": "command+date", "40 min": None}


def test_the_label_belongs_to_its_sentence_when_the_paragraph_also_names_a_run():
    text = (
        "## S\n\nIntro.\n\nSeed 0 reached 0.942 in the run of 2026-12-01 (`seqtrojan reproduce --scale headline`). "
        "With 1 thread it reached 0.966 (one run, no stored command).\n"
    )
    assert sources(text) == {"0.942": "command+date", "0.966": "unsourced observation"}
