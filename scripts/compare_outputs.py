"""Compare the JSON outputs of two reproduction folders: every number and string, key by key.

    python scripts/compare_outputs.py results/before results/after [--tolerance 0]

What a refactor must leave unchanged (issue: one pipeline) is the science, so this walks every ``*.json`` under
the first folder (the model cards included) and reports each file missing from the second, each dotted key that
differs, and each key present on one side only. Wall times, dates, versions and absolute paths are skipped (they
change between any two runs). Exit status 0 when everything matched, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

SKIPPED_FILES = {"timings.json"}
SKIPPED_KEYS = {"created", "seqtrojan_version", "train_seconds", "wall_seconds", "weights_sha256", "out_dir", "model"}
SKIPPED_SUFFIXES = ("_s", "/elapsed_s", "steps_per_s", "_seconds")


def differences(a: Any, b: Any, path: str, tolerance: float) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b), key=str):
            if key in SKIPPED_KEYS or str(key).endswith(SKIPPED_SUFFIXES):
                continue
            where = f"{path}.{key}" if path else str(key)
            if key not in b:
                out.append(f"{where}: only in the first")
            elif key not in a:
                out.append(f"{where}: only in the second")
            else:
                out += differences(a[key], b[key], where, tolerance)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} items against {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]", tolerance)]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        same = (math.isnan(a) and math.isnan(b)) if isinstance(a, float) and math.isnan(a) else abs(a - b) <= tolerance
        return [] if same else [f"{path}: {a!r} against {b!r}"]
    return [] if a == b else [f"{path}: {str(a)[:60]!r} against {str(b)[:60]!r}"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("--tolerance", type=float, default=0.0, help="largest absolute difference between numbers")
    args = parser.parse_args(argv)
    problems, files = [], 0
    for path in sorted(args.first.rglob("*.json")):
        rel = path.relative_to(args.first)
        if rel.name in SKIPPED_FILES or "checkpoints" in rel.parts:
            continue
        files += 1
        other = args.second / rel
        if not other.exists():
            problems.append(f"{rel}: missing from {args.second}")
            continue
        a, b = json.loads(path.read_text()), json.loads(other.read_text())
        problems += [f"{rel}: {d}" for d in differences(a, b, "", args.tolerance)]
    for line in problems:
        print(line)
    print(f"{files} JSON files compared, {len(problems)} differences")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
