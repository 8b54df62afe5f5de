"""The evaluation's results, typed: one :class:`SweepRow` per (agent, env, grid) and training seed, each rate a
:class:`~seqtrojan.stats.Rate`. :func:`write_sweep` saves them as ``evaluation.json`` (and a flat
``evaluation.csv``); :func:`load_sweep` reads them back through :func:`seqtrojan.serde.from_dict`, so that a
misspelt or missing key fails at load with its dotted path (``[3].success.k``).

The bottom of the evaluation package: this module imports only :mod:`seqtrojan.stats` and :mod:`seqtrojan.serde`.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.errors import ConfigError
from seqtrojan.serde import from_dict, to_dict
from seqtrojan.stats import Rate

EVALUATION_FILE = "evaluation.json"
EVALUATION_CSV = "evaluation.csv"


@dataclass(frozen=True)
class SweepRow:
    """One agent in one env on one grid, over its evaluation episodes (all rates of the same episodes)."""

    agent: str
    """a name for the model"""
    label: str
    """clean / backdoored"""
    env: str
    """normal / trojan"""
    size: int
    holes: int
    success: Rate
    """episodes that reached the goal they should: the user's, or the adversary's after the trigger"""
    hole: Rate
    timeout: Rate
    wrong_goal: Rate
    """episodes that reached the other goal"""
    mean_length: float
    paper: float | None
    """the paper's success rate for this cell, if reported"""
    seed: int = 0
    """the agent's training-seed index (0 for a single-seed evaluation)"""

    @property
    def config(self) -> str:
        return f"{self.size}x{self.size}/{self.holes}"

    @property
    def episodes(self) -> int:
        return self.success.n


def write_sweep(rows: Sequence[SweepRow], out_dir: Path) -> tuple[Path, Path]:
    """``evaluation.json`` (each row with its ``config`` label added, for a reader) and ``evaluation.csv`` (one
    column per number: success with ci_low and ci_high, the other rates as plain rates)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, csv_path = out_dir / EVALUATION_FILE, out_dir / EVALUATION_CSV
    json_path.write_text(json.dumps([to_dict(r) | {"config": r.config} for r in rows], indent=2))
    with csv_path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(_flat(rows[0])) if rows else ["agent"])
        writer.writeheader()
        writer.writerows(_flat(r) for r in rows)
    return json_path, csv_path


def _flat(r: SweepRow) -> dict[str, object]:
    low, high = r.success.interval
    return {
        "agent": r.agent, "label": r.label, "env": r.env, "size": r.size, "holes": r.holes, "episodes": r.episodes,
        "success": r.success.value, "ci_low": low, "ci_high": high, "hole": r.hole.value, "timeout": r.timeout.value,
        "wrong_goal": r.wrong_goal.value, "mean_length": r.mean_length, "paper": r.paper, "seed": r.seed,
        "config": r.config,
    }  # fmt: skip


def load_sweep(path: Path) -> list[SweepRow]:
    """The rows :func:`write_sweep` (or :func:`save_rows`) wrote. A row's ``config`` label, where present, must
    match its size and holes."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"cannot read sweep rows from {str(path)!r}: {err}") from None
    if not isinstance(data, list):
        raise ConfigError(f"{str(path)!r} must hold a list of sweep rows, got {type(data).__name__}")
    rows = []
    for i, record in enumerate(data):
        where = f"[{i}]"
        label = record.pop("config", None) if isinstance(record, dict) else None
        try:
            row = from_dict(SweepRow, record, where)
        except ConfigError as err:
            raise ConfigError(f"{str(path)!r}: {err}") from None
        if label is not None and label != row.config:
            raise ConfigError(f"{str(path)!r}: {where}.config={label!r} but size and holes give {row.config!r}")
        rows.append(row)
    return rows


def save_rows(rows: Sequence[SweepRow], path: Path) -> Path:
    """Rows as JSON, written to a temporary file first and moved into place (a stopped run leaves no half file)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps([to_dict(r) for r in rows], indent=2))
    tmp.replace(path)
    return path
