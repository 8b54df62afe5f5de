"""Print the recurrent-state probe's features of every model of a zoo (docs/benchmark.md, *Measured*) as JSON.

    PYTHONPATH=. .venv/bin/python scripts/state_probe_table.py results/matrix_minigrid_v2/zoo \
        > docs/data/benchmark/state_probe_minigrid16.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from seqtrojan.benchmark.state_probe import ProbeSettings, probe_features
from seqtrojan.benchmark.suspect import load_suspect


def main() -> None:
    zoo = Path(sys.argv[1])
    settings = ProbeSettings()
    rows = []
    for folder in sorted((zoo / "models").iterdir()):
        truth = json.loads((folder / "label.json").read_text())
        features = probe_features(load_suspect(folder), settings)
        rows.append({"model": folder.name, "label": truth["label"], "trigger": truth["variation"]["trigger_value"],
                     **features})  # fmt: skip
    command = f"python scripts/state_probe_table.py {zoo}"
    settings_out = {"episodes": settings.episodes, "at": settings.at, "after": settings.after}
    print(json.dumps({"command": command, "settings": settings_out, "models": rows}, indent=2))


if __name__ == "__main__":
    main()
