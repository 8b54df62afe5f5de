"""Run logging: TensorBoard events, the same scalars as JSON lines and CSV, and a progress bar."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class RunLogger:
    """Writes ``metrics.jsonl``, ``metrics.csv`` and TensorBoard events under a run directory.

    On resume the files are appended to; rows past the resume step are dropped first so that a restarted run
    never holds two rows for one step. A fresh start (no ``resume_step``) empties them, and removes old TensorBoard
    event files, so that a run name reused after a stop before the first checkpoint does not log its steps twice.
    """

    def __init__(self, run_dir: Path, tensorboard: bool = True, resume_step: int | None = None) -> None:
        self.run_dir = run_dir
        self.jsonl_path = run_dir / "metrics.jsonl"
        self.csv_path = run_dir / "metrics.csv"
        if resume_step is not None:
            self._truncate_after(resume_step)
        else:
            self._clear()
        self._writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step)

    def add_text(self, tag: str, text: str) -> None:
        if self._writer is not None:
            self._writer.add_text(tag, text)

    def log(self, step: int, scalars: dict[str, Any]) -> None:
        row = {"env_steps": step, **{k: _plain(v) for k, v in scalars.items()}}
        with self.jsonl_path.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        self._append_csv(row)
        if self._writer is not None:
            for key, value in row.items():
                if key != "env_steps" and isinstance(value, (int, float)) and math.isfinite(value):
                    self._writer.add_scalar(key, value, step)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

    def _append_csv(self, row: dict[str, Any]) -> None:
        fields = list(row)
        if self.csv_path.exists():
            with self.csv_path.open() as fh:
                header = next(csv.reader(fh), [])
            if header != fields:
                fields = header + [k for k in row if k not in header]
                if fields != header:  # new columns: rewrite the file with the wider header
                    rows = list(csv.DictReader(self.csv_path.open()))
                    with self.csv_path.open("w", newline="") as fh:
                        writer = csv.DictWriter(fh, fieldnames=fields)
                        writer.writeheader()
                        writer.writerows(rows)
            with self.csv_path.open("a", newline="") as fh:
                csv.DictWriter(fh, fieldnames=fields).writerow(row)
        else:
            with self.csv_path.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=fields)
                writer.writeheader()
                writer.writerow(row)

    def _clear(self) -> None:
        self.jsonl_path.unlink(missing_ok=True)
        self.csv_path.unlink(missing_ok=True)
        for events in (self.run_dir / "tb").glob("events.out.tfevents.*"):
            events.unlink()

    def _truncate_after(self, step: int) -> None:
        if self.jsonl_path.exists():
            lines = [
                ln for ln in self.jsonl_path.read_text().splitlines() if ln and json.loads(ln)["env_steps"] <= step
            ]
            self.jsonl_path.write_text("".join(ln + "\n" for ln in lines))
        if self.csv_path.exists():
            with self.csv_path.open() as fh:
                reader = csv.DictReader(fh)
                fields = reader.fieldnames or []
                rows = [r for r in reader if int(float(r["env_steps"])) <= step]
            with self.csv_path.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=fields)
                writer.writeheader()
                writer.writerows(rows)


def _plain(value: Any) -> Any:
    if hasattr(value, "item"):
        return value.item()
    return value


def make_progress(enabled: bool) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        disable=not enabled,
        transient=False,
    )
