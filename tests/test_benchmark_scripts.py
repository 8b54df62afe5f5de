"""What the benchmark scripts compute beyond printing a saved run (their tables: tests/test_docs_data.py)."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_zoo_rate_reads_when_a_backdoor_formed_from_a_kept_training_curve(tmp_path):
    steps_to_form = runpy.run_path(str(ROOT / "benchmarks" / "zoo_rate.py"))["steps_to_form"]
    rows = [(2048, 0.95, 0.50), (4096, 0.85, 0.95), (6144, 0.92, 0.93), (8192, 1.0, 1.0)]
    curve = tmp_path / "m0001.jsonl"
    keys = ("env_steps", "episodes/normal_success", "episodes/trojan_success")
    lines = [json.dumps(dict(zip(keys, row))) for row in rows]
    curve.write_text('{"env_steps": 1024, "episodes/norm\n' + "\n".join(lines) + "\n")  # a line cut short, skipped
    assert steps_to_form(curve) == 6144  # the first update with both envs at 0.9 or more
    never = tmp_path / "m0002.jsonl"
    never.write_text("\n".join(lines[:2]) + "\n" + json.dumps({"env_steps": 9000, "episodes/normal_success": 1.0}))
    assert steps_to_form(never) is None  # a clean run's rows have no trojan success
    assert steps_to_form(tmp_path / "absent.jsonl") is None
