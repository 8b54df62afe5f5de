"""Print the trigger reconstruction's features of every model of a zoo (docs/benchmark.md, *Trigger reconstruction*)
as JSON, with each model's split where a leaderboard's splits.json is given.

    PYTHONPATH=. .venv/bin/python scripts/reconstruction_table.py results/benchmark_smoke \
        results/benchmark_smoke_board/splits.json > docs/data/benchmark/reconstruction_smoke.json
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

from seqtrojan.benchmark.reconstruction import ReconstructionSettings, reconstruction_features
from seqtrojan.benchmark.suspect import load_suspect


def main() -> None:
    zoo = Path(sys.argv[1])
    splits = json.loads(Path(sys.argv[2]).read_text()) if len(sys.argv) > 2 else {}
    settings = ReconstructionSettings()
    rows = []
    for folder in sorted((zoo / "models").iterdir()):
        truth = json.loads((folder / "label.json").read_text())
        start = time.perf_counter()
        features = reconstruction_features(load_suspect(folder), settings)
        seconds = time.perf_counter() - start
        rows.append({"model": folder.name, "label": truth["label"], "split": splits.get(folder.name),
                     "trigger": truth["variation"]["trigger_value"], "seconds": seconds, **features})  # fmt: skip
    command = "python scripts/reconstruction_table.py " + " ".join(sys.argv[1:])
    print(json.dumps({"command": command, "settings": dataclasses.asdict(settings), "models": rows}, indent=2))


if __name__ == "__main__":
    main()
