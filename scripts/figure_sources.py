"""List every measured figure in README.md and docs/ with its source; ``--check`` fails on a figure without one.

python scripts/figure_sources.py                 # every figure: file:line, the number, its source kind and text
python scripts/figure_sources.py --unsourced     # only the figures without a source
python scripts/figure_sources.py --check         # exit 1, listing them, when any figure lacks a source

Pages read: README.md, docs/*.md and docs/commands/*.md (docs/api/ holds only mkdocstrings directives).

**What counts as a figure.** In prose, table cells, and the comments (after ``#``) of shell code blocks:

- a decimal number (``0.933``, ``13.7``, ``3.6e-7``), also with a suffix (``49.0k``, ``1.5M``, ``1.22x``,
  ``99.7%``); the numbers beside a ``±`` are decimals;
- a percentage (``25%``), a number grouped in thousands (``78,240``), a whole number of thousands (``78k``), a
  ratio (``7x``);
- a duration: a number followed by a time unit (``13.7 s``, ``23 min``, ``0.9 ms``, ``45 µs``).

**What does not** (masked before the search, or dropped after it):

- code: fenced blocks other than the comments of shell blocks (python, yaml, ... blocks entirely), inline code
  spans (so every CLI option value, ``--steps 153600``), link targets and HTML tags;
- headings (they name a section's settings: ``5M env steps, 5 seeds``);
- dates and times of day (``2026-12-02``, ``2026-11``, ``16:40``), version numbers (``2.13.0``, ``Python 3.10+``,
  ``torch 2.13``, ``YAML 1.2``), grid and shape names (``17x17/30``, ``7x7``, ``64+32``), section numbers
  (``section 5.2``), commit hashes, file paths;
- plain integers (counts such as ``3 seeds`` or ``1000 episodes``) and whole numbers of millions (``5M env
  steps``): budgets and settings far more often than measurements;
- settings written in prose: a number right after ``default``, ``weight``, ``margin``, ``target``, ``q =``,
  ``lr``, ``learning rate``, ``entropy``, ``lambda``, ``smoothing``, ``probability``, ``prevalence``, ``mixing``,
  ``fixed``, ``clip(``, ``must exceed`` or a comparison (``>= 0.9``, ``≥``, ``<=``, ``=``), a bracket
  or colon between them allowed; a number before ``interval``, ``CI``, ``Wilson`` (``95% interval``) or
  ``target``; and after ``at``, a number before ``false alarms`` (``at 1% false alarms``: an operating point);
- every number of a reference table, one with a ``default`` column (config fields and their defaults);
- in a command's comment, a number of thousands or millions of steps (``# ... (1.5M steps)``: its budget).

**What counts as a source**, nearest first:

- ``paper``: the figure is a rate (``0.934``) equal to one of the paper's (``seqtrojan/paper/paper_results.json``)
  and quoted as the paper's: in a table column headed ``paper``, or in a sentence that names the paper (the "paper
  scale" and the "paper's setting" do not count; in prose, neither do 0, 1, a mean ± sd or a range);
- ``unsourced observation``: the figure's own sentence says ``no stored command`` (stated, not hidden);
- then, in the figure's own block, its caption, and its section's intro, in that order, the first of:
  ``data``, a committed file under ``docs/data/`` (it must exist) named there; ``command+date``, a command (a code
  span, in backticks or ``<code>``, that starts with ``python``, ``seqtrojan``, ``make``, ``pytest``,
  ``PYTHONPATH=``, ``.venv/bin/`` or ``/usr/bin/time``, or a command line of a shell code block) and a date
  ``YYYY-MM-DD``, both there; ``unsourced observation``, the words ``no stored command`` there (block or caption
  only).

The places:

- the figure's own block: its paragraph, list item (with its continuation lines) or table; for a figure in a
  shell block's comment, that line (its command and a date in its comment);
- its caption: for a table, the paragraph (or ``<summary>``) directly above it, images skipped; for a list item,
  the paragraph directly above the list;
- its section's intro: the first paragraph after the nearest heading (with the shell blocks right before or after
  it). A ``<details><summary>`` block is a section of its own whose intro is the summary line, so a collapsed
  earlier run is never sourced by the section's current run.

A command elsewhere in the file is not a source, nor a date without a command, nor a command without a date.
``--check`` tolerates the unsourced figures of the sections listed in ``PENDING`` (being rewritten elsewhere) and
fails on an entry there that has none left.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

ROOT = Path(__file__).resolve().parents[1]
PAPER_RESULTS = ROOT / "seqtrojan" / "paper" / "paper_results.json"

BlockKind = Literal["heading", "paragraph", "item", "table", "code", "summary", "image", "details_end"]
SourceKind = Literal["data", "command+date", "paper", "unsourced observation"]
Place = Literal["block", "caption", "section intro"]

SHELL_LANGUAGES = frozenset({"", "bash", "sh", "shell", "console"})

# ---------------------------------------------------------------------------------------------------- the figures

FIGURE = re.compile(
    r"(?<![\w.,])(?:"
    r"\d+(?:\.\d+)?\s?(?:µs|us|ms|s|min|minutes|seconds|hours)\b(?!-)"  # a duration
    r"|\d+\.\d+(?:e-?\d+)?(?:\s?[kM]\b|x\b|\s?%)?"  # a decimal, maybe with a suffix
    r"|\d{1,3}(?:,\d{3})+(?!\d)"  # grouped in thousands
    r"|\d+\s?%"  # a percentage
    r"|\d+k\b"  # 78k (a whole number of millions, 5M, is a budget)
    r"|\d+x\b"  # a ratio
    r")"
)
MASKS = [
    re.compile(r"``.+?``|`[^`]+`|<code>.+?</code>", re.S),  # code spans (a span may cross a line break)
    re.compile(r"\]\([^)]*\)"),  # link targets
    re.compile(r"<[^>\n]+>"),  # HTML tags
    re.compile(r"\b\d{4}-\d{2}(?:-\d{2})?(?:/\d{2})?\b"),  # dates: 2026-12-02, 2026-11, 2026-12-01/02
    re.compile(r"\b\d{1,2}:\d{2}\b"),  # times of day
    re.compile(r"\b\d+(?:\.\d+){2,}\b"),  # versions: 2.13.0
    re.compile(r"\b(?:Python|python|torch|PyTorch|YAML|version|since|v)\s?\d+(?:\.\d+)+\+?"),  # Python 3.10, torch 2.13
    re.compile(r"\b\d+\.\d+\+"),  # 3.10+
    re.compile(r"\b\d+(?:x\d+)+(?:/\d+)?\b|\b\d+\+\d+\b"),  # grids and shapes: 17x17/30, 7x7, 2x2, 64+32
    re.compile(r"\b(?:[Ss]ection|§)\s?\d+(?:\.\d+)*"),  # section numbers
    re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"),  # commit hashes: 6e6ec7d
    re.compile(r"[\w.*{}-]*/[\w.*{}/-]*[A-Za-z_][\w.*{}/-]*|[\w.*{}-]*[A-Za-z_][\w.*{}-]*/[\w.*{}/-]+"),  # paths
]
SETTING_BEFORE = re.compile(
    r"(?:\bdefault|\bweight|\bmargin|\btarget|\bq\s?=|\bq|\blr|\blearning rate|\bentropy|\bent_coef|\blambda|"
    r"\bsmoothing|\bprobability|\bprevalence|\bmixing|\bfixed|\bclip\(|\bmust exceed|>=|<=|≥|≤|<|(?<!-)>|=)"
    r"\s*(?:of\s|at\s|is\s)?[(:]?\s*$"
)
SETTING_AFTER = re.compile(r"^\s*(?:\(?Wilson|\(?confidence|t-interval|interval|CI|target|false-alarm target)")
BUDGET_AFTER = re.compile(r"^\s*(?:env\s)?steps\b")  # in a command's comment, "(1.5M steps)" is its budget
OPERATING_POINT = re.compile(r"\bat (?:a |the |under )?$")
FALSE_ALARMS_AFTER = re.compile(r"^\s*false[- ]alarm")
COMMAND = re.compile(r"^(?:python3?|seqtrojan|make|pytest|PYTHONPATH=\S+|\.venv/bin/\S+|/usr/bin/time)(?:\s|$)")
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
DATA_PATH = re.compile(r"docs/data/[\w./-]+\.\w+")
UNSOURCED = re.compile(r"no\s+stored\s+command", re.I)
PAPER_SCALE = re.compile(
    r"paper[- ]scale|paper's (?:scale|setting|training grid)|--scale paper|paper_v\d|results/paper"
)
SENTENCE_END = re.compile(r"[.!?;]\**(?=\s)")

PENDING: dict[tuple[str, str], str] = {}
"""Sections (page, heading) whose unsourced figures ``--check`` reports but tolerates while another change rewrites
them. An entry without an unsourced figure left fails the check: remove it then."""


@dataclass(frozen=True)
class Block:
    """A run of lines that Markdown reads as one thing: a paragraph, list item, table, code block or heading."""

    kind: BlockKind
    start: int  # 1-based line number of the first line
    lines: tuple[str, ...]
    language: str = ""  # a code block's

    @property
    def text(self) -> str:
        return "\n".join(self.lines)


@dataclass(frozen=True)
class Figure:
    """One measured number: where it stands and the line it stands in."""

    path: str  # relative to the repository
    line: int
    number: str
    value: float
    column: str  # the table column's header, "" outside a table
    sentence: str  # the sentence (or table cell) around it
    section: str = ""  # the nearest heading's text


@dataclass(frozen=True)
class Source:
    kind: SourceKind
    place: Place
    text: str  # what was found: the file, the command and date, the phrase


@dataclass(frozen=True)
class Finding:
    figure: Figure
    source: Source | None


@dataclass(frozen=True)
class Context:
    """The places around a block where its source may be stated, nearest first."""

    caption: Block | None
    intro: tuple[Block, ...]


# -------------------------------------------------------------------------------------------------- the blocks


def _block_kind(line: str) -> BlockKind:
    stripped = line.strip()
    if re.match(r"#{1,6}\s", stripped):
        return "heading"
    if stripped.startswith("|"):
        return "table"
    if re.match(r"(?:[-*+]|\d+\.)\s", stripped):
        return "item"
    if stripped.startswith("<details"):
        return "summary"
    if stripped.startswith("</details"):
        return "details_end"
    if re.fullmatch(r"!\[[^\]]*\]\([^)]*\)(?:\{[^}]*\})?", stripped):
        return "image"
    return "paragraph"


def split_blocks(text: str) -> list[Block]:
    """Markdown's blocks, as far as the figures need them: fenced code, headings, tables, list items, paragraphs."""
    blocks: list[Block] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        fence = re.match(r"\s*(```|~~~)\s*([\w+-]*)", line)
        if fence:
            end = i + 1
            while end < len(lines) and not lines[end].strip().startswith(fence.group(1)):
                end += 1
            blocks.append(Block("code", i + 1, tuple(lines[i + 1 : end]), fence.group(2).lower()))
            i = end + 1
            continue
        if not line.strip():
            i += 1
            continue
        kind = _block_kind(line)
        end = i + 1
        if kind in ("paragraph", "item", "table"):
            while end < len(lines) and lines[end].strip() and not lines[end].lstrip().startswith(("```", "~~~")):
                nxt = _block_kind(lines[end])
                if kind == "table" and nxt != "table":
                    break
                if kind != "table" and nxt in ("heading", "table", "summary", "details_end"):
                    break
                if nxt == "item" and not (kind == "paragraph" and lines[end].startswith(" ")):
                    break  # a new list item (an indented "- " inside a paragraph is rare; treat it as text)
                end += 1
        blocks.append(Block(kind, i + 1, tuple(lines[i:end])))
        i = end
    return blocks


def contexts(blocks: Sequence[Block]) -> list[Context]:
    """Each block's caption and its section's intro (a heading's first paragraph, or a details block's summary)."""
    result: list[Context] = []
    intro_stack: list[tuple[Block, ...]] = [()]
    for index, block in enumerate(blocks):
        if block.kind == "heading":
            intro_stack = [_intro_after(blocks, index)]
        elif block.kind == "summary":
            intro_stack.append((block,))
        elif block.kind == "details_end" and len(intro_stack) > 1:
            intro_stack.pop()
        result.append(Context(_caption(blocks, index), intro_stack[-1]))
    return result


def _intro_after(blocks: Sequence[Block], heading: int) -> tuple[Block, ...]:
    intro: list[Block] = []
    for block in blocks[heading + 1 :]:
        if block.kind == "code":
            intro.append(block)
            if any(b.kind != "code" for b in intro):
                break  # the shell block right after the first paragraph
            continue
        if block.kind == "paragraph" and not any(b.kind == "paragraph" for b in intro):
            intro.append(block)
            continue
        break
    return tuple(intro)


def _caption(blocks: Sequence[Block], index: int) -> Block | None:
    block = blocks[index]
    if block.kind not in ("table", "item"):
        return None
    j = index - 1
    while j >= 0 and (blocks[j].kind == "image" or (block.kind == "item" and blocks[j].kind == "item")):
        j -= 1
    if j >= 0 and blocks[j].kind in ("paragraph", "summary"):
        return blocks[j]
    return None


# ------------------------------------------------------------------------------------------------ the sources


def _mask(text: str) -> str:
    """The text with everything that is not prose blanked out (same length, line breaks kept)."""
    for pattern in MASKS:
        text = pattern.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)
    return text


def commands_in(block: Block) -> list[str]:
    """The commands a block states: code spans that start like a command, or a shell block's command lines."""
    if block.kind == "code":
        if block.language not in SHELL_LANGUAGES:
            return []
        return [line.split(" #")[0].strip() for line in block.lines if COMMAND.match(line.strip())]
    spans = re.findall(r"``(.+?)``|`([^`]+)`|<code>(.+?)</code>", block.text, re.S)
    return [" ".join(s.split()) for group in spans for s in group if s and COMMAND.match(" ".join(s.split()))]


def _command_and_date(places: Iterable[Block]) -> str | None:
    text = "\n".join(b.text for b in places)
    commands = [c for b in places for c in commands_in(b)]
    dates = DATE.findall(text)
    if commands and dates:
        return f"`{commands[0]}`, {dates[0]}"
    return None


def _data_file(places: Iterable[Block]) -> str | None:
    for block in places:
        for path in DATA_PATH.findall(block.text):
            if (ROOT / path).is_file():
                return path
    return None


def find_source(figure: Figure, block: Block, context: Context, paper: frozenset[float]) -> Source | None:
    """The nearest source of a figure (see the module's docstring), or None."""
    if _quotes_the_paper(figure, paper):
        return Source("paper", "block", "paper_results.json (quoted as the paper's)")
    stated = UNSOURCED.search(figure.sentence)
    if stated:  # its own sentence says so, whatever else the paragraph names
        return Source("unsourced observation", "block", stated.group(0))
    places: list[tuple[Place, list[Block]]] = [("block", [block])]
    if context.caption is not None:
        places.append(("caption", [context.caption]))
    if context.intro:
        places.append(("section intro", list(context.intro)))  # the block itself may be part of it
    for place, where in places:
        data = _data_file(where)
        if data:
            return Source("data", place, data)
        found = _command_and_date(where)
        if found:
            return Source("command+date", place, found)
        stated = UNSOURCED.search(where[0].text) if place != "section intro" else None
        if stated:  # said in the paragraph, or in the caption of its table or list
            return Source("unsourced observation", place, stated.group(0))
    return None


def _quotes_the_paper(figure: Figure, paper: frozenset[float]) -> bool:
    """A rate of the paper's, in a column headed "paper" or a sentence naming the paper (not the paper scale)."""
    if not re.fullmatch(r"\d\.\d+", figure.number) or figure.value not in paper:
        return False
    if figure.column:
        return "paper" in PAPER_SCALE.sub("", figure.column.lower())
    number = re.escape(figure.number)
    if figure.value in (0.0, 1.0) or re.search(rf"{number} ±|± {number}|\d-{number}|{number}-\d", figure.sentence):
        return False  # in prose, 0, 1, a mean ± sd and a range are ours far more often than the paper's
    return "paper" in PAPER_SCALE.sub("", figure.sentence.lower())


def paper_values(path: Path = PAPER_RESULTS) -> frozenset[float]:
    """Every number in the paper's results file."""

    def walk(node: object) -> Iterator[float]:
        if isinstance(node, bool):
            return
        if isinstance(node, (int, float)):
            yield float(node)
        elif isinstance(node, dict):
            for value in node.values():
                yield from walk(value)
        elif isinstance(node, list):
            for value in node:
                yield from walk(value)

    return frozenset(walk(json.loads(path.read_text())))


# ------------------------------------------------------------------------------------------------ the search


def _is_setting(masked: str, start: int, end: int) -> bool:
    before = masked[max(0, start - 25) : start].replace("\n", " ")
    after = masked[end : end + 25].replace("\n", " ")
    if SETTING_BEFORE.search(before) or SETTING_AFTER.match(after):
        return True
    return bool(OPERATING_POINT.search(before) and FALSE_ALARMS_AFTER.match(after))


def _value(number: str) -> float:
    digits = re.match(r"[\d.,]+(?:e-?\d+)?", number)
    text = digits.group(0).replace(",", "") if digits else ""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _sentence(text: str, start: int, end: int) -> str:
    left = max((m.end() for m in SENTENCE_END.finditer(text, 0, start)), default=0)
    right = SENTENCE_END.search(text, end)
    return text[left : right.start() if right else len(text)].strip()


def figures_in(block: Block, path: str) -> list[Figure]:
    """The figures a block states (none in headings, reference tables, or code but shell comments)."""
    if block.kind in ("heading", "image", "details_end"):
        return []
    if block.kind == "code":
        if block.language not in SHELL_LANGUAGES:
            return []
        comments = tuple(line.split(" #", 1)[1] if " #" in line else "" for line in block.lines)
        return _figures(comments, block.start, path, header=None, comments=True)
    if block.kind == "table":
        header = [cell.strip() for cell in block.lines[0].strip().strip("|").split("|")]
        if any(cell.strip("` ").lower() == "default" for cell in header):
            return []
        return _figures(block.lines, block.start, path, header=header)
    return _figures(block.lines, block.start, path, header=None)


def _figures(
    lines: Sequence[str], first: int, path: str, header: list[str] | None, comments: bool = False
) -> list[Figure]:
    text = "\n".join(lines)
    masked = _mask(text)
    line_starts = [0]
    for line in lines:
        line_starts.append(line_starts[-1] + len(line) + 1)
    found: list[Figure] = []
    for m in FIGURE.finditer(masked):
        if _is_setting(masked, m.start(), m.end()):
            continue
        if comments and m.group(0)[-1] in "kM" and BUDGET_AFTER.match(masked[m.end() :]):
            continue
        row = max(i for i, s in enumerate(line_starts) if s <= m.start())
        column = ""
        if header is not None:
            cell = text[line_starts[row] : m.start()].count("|") - 1
            column = header[cell] if 0 <= cell < len(header) else ""
            sentence = text[line_starts[row] : line_starts[row + 1]].split("|")[cell + 1] if column else ""
        else:
            sentence = _sentence(text, m.start(), m.end())
        found.append(Figure(path, first + row, m.group(0), _value(m.group(0)), column, sentence))
    return found


def scan(path: Path, root: Path = ROOT, paper: frozenset[float] | None = None) -> list[Finding]:
    """Every figure of one Markdown file with its source (None where it has none)."""
    name = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
    return scan_text(path.read_text(), name, paper)


def scan_text(text: str, name: str, paper: frozenset[float] | None = None) -> list[Finding]:
    paper = paper_values() if paper is None else paper
    blocks = split_blocks(text)
    findings: list[Finding] = []
    section = ""
    for block, context in zip(blocks, contexts(blocks)):
        if block.kind == "heading":
            section = block.lines[0].lstrip("#").strip()
        for figure in figures_in(block, name):
            figure = replace(figure, section=section)
            if block.kind == "code":
                line = Block("code", figure.line, (block.lines[figure.line - block.start],), block.language)
                source = find_source(figure, line, Context(None, context.intro), paper)
            else:
                source = find_source(figure, block, context, paper)
            findings.append(Finding(figure, source))
    return findings


def pages(root: Path = ROOT) -> list[Path]:
    """README.md, docs/*.md and docs/commands/*.md."""
    docs = root / "docs"
    return [root / "README.md", *sorted(docs.glob("*.md")), *sorted((docs / "commands").glob("*.md"))]


# ---------------------------------------------------------------------------------------------------- output


def _short(text: str, width: int) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 1] + "…"


def row(finding: Finding) -> str:
    f, s = finding.figure, finding.source
    where = f"{f.path}:{f.line}"
    if s is None:
        return f"{where:<34} {f.number:<12} NONE"
    return f"{where:<34} {f.number:<12} {s.kind:<22} {s.place:<14} {_short(s.text, 70)}"


def summary(findings: Sequence[Finding]) -> str:
    kinds = Counter(f.source.kind if f.source else "none" for f in findings)
    files = Counter(f.figure.path for f in findings if f.source is None)
    lines = [f"{len(findings)} figures; " + ", ".join(f"{kind}: {n}" for kind, n in kinds.most_common())]
    if files:
        lines.append("without a source, per file: " + ", ".join(f"{p} {n}" for p, n in files.most_common()))
    return "\n".join(lines)


@dataclass(frozen=True)
class Check:
    """What ``--check`` decides: the figures without a source, those tolerated in pending sections, stale entries."""

    missing: tuple[Finding, ...]
    pending: tuple[Finding, ...]
    stale: tuple[tuple[str, str], ...]

    @property
    def ok(self) -> bool:
        return not self.missing and not self.stale


def check(findings: Sequence[Finding], pending: dict[tuple[str, str], str] = PENDING) -> Check:
    unsourced = [f for f in findings if f.source is None]
    held = [f for f in unsourced if (f.figure.path, f.figure.section) in pending]
    scanned = {f.figure.path for f in findings}
    used = {(f.figure.path, f.figure.section) for f in held}
    stale = tuple(key for key in pending if key[0] in scanned and key not in used)
    return Check(tuple(f for f in unsourced if f not in held), tuple(held), stale)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="*", type=Path, help="Markdown files (default: README.md and docs)")
    parser.add_argument("--check", action="store_true", help="exit 1 when a figure has no source, listing them")
    parser.add_argument("--unsourced", action="store_true", help="list only the figures without a source")
    args = parser.parse_args(argv)
    paper = paper_values()
    findings = [f for p in (args.files or pages()) for f in scan(p.resolve(), ROOT, paper)]
    result = check(findings)
    shown = result.missing + result.pending if (args.check or args.unsourced) else tuple(findings)
    for finding in shown:
        print(row(finding) + (" (pending)" if finding in result.pending else ""))
    print(summary(findings))
    for path, heading in sorted({(f.figure.path, f.figure.section) for f in result.pending}):
        print(f"pending: {path} '{heading}' ({PENDING[path, heading]}): tolerated by --check")
    for path, heading in result.stale:
        print(f"stale: {path} '{heading}' has no unsourced figure left: remove it from PENDING")
    if args.check and not result.ok:
        print(
            f"{len(result.missing)} figure(s) without a source: state the command and date that made each (or its "
            "committed data under docs/data/) in its paragraph, its table's caption or its section's first paragraph"
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
