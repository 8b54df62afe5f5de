"""Print a matrix.json (``seqtrojan matrix``) as the Markdown tables of docs/results.md.

python scripts/matrix_markdown.py results/matrix_smoke/matrix.json
"""

from __future__ import annotations

import sys
from pathlib import Path

from seqtrojan.experiment_results import MatrixResult
from seqtrojan.serde import load_json
from seqtrojan.stats import OverSeeds, Rate

sys.path.insert(0, str(Path(__file__).parent))
from arms_race import attack_table, defense_table  # the benchmarks' answer tables, in the same format


def spread(x: OverSeeds | None, pooled: Rate | None = None, digits: int = 3) -> str:
    if x is None:
        return ""
    text = x.text(digits)
    if pooled is not None:
        low, high = pooled.interval
        text += f" [{low:.{digits}f}, {high:.{digits}f}]"
    return text


def main(path: str) -> None:
    result = load_json(MatrixResult, Path(path))
    print(f"Scale {result.scale}, grid {result.grid}; mean ± sd over seeds [95% Wilson interval, seeds pooled].\n")
    print("| attack | seeds | attack success | clean success | unintentional activation | trigger seen by chance |")
    print("|---|---|---|---|---|---|")
    for a in result.attacks:
        natural = a.natural_trigger.text(4) if a.natural_trigger is not None else "-"
        print(
            f"| {a.attack} | {len(a.seeds)} | {spread(a.attack_success, a.attack_success_pooled)} | "
            f"{spread(a.clean_success, a.clean_success_pooled)} | "
            f"{spread(a.unintentional, a.unintentional_pooled)} | {natural} |"
        )
    online = [c for c in result.cells if c.kind == "online"]
    defenses = list(dict.fromkeys(c.defense for c in online))
    acting = [c for c in result.cells if c.attack_success is not None]
    if defenses:
        online_table(result, online, defenses)
    else:
        print("\nOnline defenses: none applied to this matrix.")
    if acting:
        acting_tables(result, acting)
    else:
        print("\nDefenses acting (online resets, mitigations): none applied to this matrix.")
    offline = [c for c in result.cells if c.kind == "offline"]
    detectors = list(dict.fromkeys(c.defense for c in offline))
    if detectors:
        offline_table(result, offline, detectors)
    else:
        print("\nOffline detectors: none applied to this matrix.")
    alone = {a.attack: (a.attack_success, a.attack_success_pooled) for a in result.attacks}
    print("\nEvery defense against the worst working attack tried on it (attack success >= 0.5 undefended):\n")
    print(defense_table(list(result.cells), alone))
    print("\nEvery working attack against the acting defense that stops it best:\n")
    print(attack_table(list(result.cells), alone))


def online_table(result: MatrixResult, online: list, defenses: list[str]) -> None:
    print("\nOnline defenses, detection at the 1% false-alarm target (false alarms in brackets after the slash):\n")
    print("| attack | " + " | ".join(defenses) + " |")
    print("|---|" + "---|" * len(defenses))
    for a in result.attacks:
        cells = {c.defense: c for c in online if c.attack == a.attack}
        row = [
            f"{spread(cells[d].detection, cells[d].detection_pooled)} / {spread(cells[d].false_alarm)}"
            if d in cells else "" for d in defenses
        ]  # fmt: skip
        print(f"| {a.attack} | " + " | ".join(row) + " |")


def acting_tables(result: MatrixResult, acting: list) -> None:
    names = list(dict.fromkeys(c.defense for c in acting))
    print("\nAttack success with the defense acting (online: state reset on an alarm; mitigations: after them):\n")
    print("| attack | none | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for a in result.attacks:
        cells = {c.defense: c for c in acting if c.attack == a.attack}
        row = [spread(cells[d].attack_success, cells[d].attack_success_pooled) if d in cells else "" for d in names]
        print(f"| {a.attack} | {spread(a.attack_success)} | " + " | ".join(row) + " |")
    print("\nClean success with the defense acting:\n")
    print("| attack | none | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for a in result.attacks:
        cells = {c.defense: c for c in acting if c.attack == a.attack}
        row = [spread(cells[d].clean_success) if d in cells else "" for d in names]
        print(f"| {a.attack} | {spread(a.clean_success)} | " + " | ".join(row) + " |")


def offline_table(result: MatrixResult, offline: list, detectors: list[str]) -> None:
    print("\nOffline detectors, ROC-AUC of the attack's models against the clean models [95% interval]:\n")
    print("| attack | " + " | ".join(detectors) + " |")
    print("|---|" + "---|" * len(detectors))
    for a in result.attacks:
        cells = {c.defense: c for c in offline if c.attack == a.attack}
        row = []
        for d in detectors:
            c = cells.get(d)
            row.append("" if c is None or c.auc is None or c.auc_interval is None
                       else f"{c.auc:.3f} [{c.auc_interval[0]:.3f}, {c.auc_interval[1]:.3f}]")  # fmt: skip
        print(f"| {a.attack} | " + " | ".join(row) + " |")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "results/matrix_smoke/matrix.json")
