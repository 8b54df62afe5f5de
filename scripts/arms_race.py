"""Print the arms race's answer tables from benchmark JSON files: every defense against the worst attack tried on it,
and every attack against the best defense tried on it.

    python scripts/arms_race.py docs/data/defenses/*.json

Reads what ``benchmarks/goal_switch.py`` (online monitors: alarms and the alarm-driven state reset),
``benchmarks/behaviour_evasion.py`` (the behaviour detector's ROC-AUC against clean agents) and
``benchmarks/finetune.py`` (fine-tuning and fine-pruning) and ``benchmarks/probe_camouflage.py`` (the benchmark
detectors' ROC-AUC against clean agents, out of sample) write; other JSON files are skipped with a line on stderr.
An attack is named as its benchmark named it (``recipe/knob`` for an adaptive recipe at another strength) and, where
two files measured the same attack on the same defense (other agents), by its file as well.

The worst case and the best defense are chosen as ``seqtrojan.arms_race`` says (the matrix's rule):
among the attacks whose backdoor works undefended (mean attack success >= 0.5 over seeds). Cells: mean ± sd over
seeds [95% Wilson interval, seeds pooled]; an AUC with its 95% interval.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from seqtrojan.arms_race import best_defenses, worst_cases
from seqtrojan.defense.behaviour import scores_auc
from seqtrojan.experiment_results import MatrixCell
from seqtrojan.stats import OverSeeds, Rate, over_seeds


def _rate(d: dict) -> Rate:
    return Rate(int(d["k"]), int(d["n"]))


def _grouped(rows: list[dict], *keys: str) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = {}
    for row in rows:
        out.setdefault(tuple(row[k] for k in keys), []).append(row)
    return out


Undefended = dict[str, tuple[OverSeeds, Rate]]


def _cell(attack: str, defense: str, kind: str, success: list[Rate] | None, clean: list[Rate],
          detected: list[Rate] | None = None, alarms: list[Rate] | None = None,
          auc: tuple[float, tuple[float, float]] | None = None) -> MatrixCell:  # fmt: skip
    s = over_seeds(success) if success else (None, None)
    d = over_seeds(detected) if detected else (None, None)
    f = over_seeds(alarms) if alarms else (None, None)
    return MatrixCell(attack, defense, kind, s[0], s[1], over_seeds(clean)[0], d[0], d[1], f[0], f[1],
                      auc[0] if auc else None, auc[1] if auc else None)  # fmt: skip


def monitor_cells(bench: dict) -> tuple[list[MatrixCell], Undefended]:
    """``benchmarks/goal_switch.py``: each (attack, monitor) over seeds, the reset acting."""
    cells, alone = [], {}
    for (attack, monitor), mine in _grouped(bench["rows"], "attack", "monitor").items():
        alone[attack] = over_seeds([_rate(r["attack_success"]) for r in mine])
        cells.append(_cell(attack, monitor, "online", [_rate(r["attack_success_reset"]) for r in mine],
                           [_rate(r["clean_success_reset"]) for r in mine], [_rate(r["detected"]) for r in mine],
                           [_rate(r["false_alarm"]) for r in mine]))  # fmt: skip
    return cells, alone


def behaviour_cells(bench: dict) -> tuple[list[MatrixCell], Undefended]:
    """``benchmarks/behaviour_evasion.py``: each attack's agents' scores against the clean agents'."""
    clean = [r for r in bench["rows"] if r["attack"] == "clean"]
    cells, alone = [], {}
    for (attack,), mine in _grouped(bench["rows"], "attack").items():
        if attack == "clean":
            continue
        a = scores_auc([r["score"] for r in mine + clean], [1] * len(mine) + [0] * len(clean))
        alone[attack] = over_seeds([_rate(r["attack_success"]) for r in mine])
        cells.append(_cell(attack, "behaviour_detector", "offline", None, [_rate(r["clean_success"]) for r in mine],
                           auc=(a.auc, a.interval)))  # fmt: skip
    return cells, alone


def mitigation_cells(bench: dict) -> tuple[list[MatrixCell], Undefended]:
    """``benchmarks/finetune.py``: each (attack, mitigation) over seeds, beside the same agents undefended; a
    mitigation named with its fine-tuning length (another length is another defense setting)."""
    rows = bench["rows"]
    cells, alone = [], {}
    for (attack, arm), mine in _grouped(rows, "attack", "arm").items():
        if arm == "none":
            alone[attack] = over_seeds([_rate(r["attack_success"]) for r in mine])
            continue
        defense = f"{arm} ({bench['finetune_steps'] // 1000}k steps)" if "finetune_steps" in bench else arm
        cells.append(_cell(attack, defense, "mitigation", [_rate(r["attack_success"]) for r in mine],
                           [_rate(r["clean_success"]) for r in mine]))  # fmt: skip
    return cells, alone


CONTROL_ROWS = ("clean_longer",)
"""rows of ``benchmarks/probe_camouflage.py`` that are controls, not attacks"""


def detector_cells(bench: dict) -> tuple[list[MatrixCell], Undefended]:
    """``benchmarks/probe_camouflage.py``: each benchmark detector's out-of-sample P(poisoned) of each attack's agents
    against the clean agents' (the ROC-AUC the benchmark wrote)."""
    cells, alone = [], {}
    for attack, detectors in bench["detectors"]["attacks"].items():
        if attack in CONTROL_ROWS:  # not an attack: what the detectors make of clean agents trained longer
            continue
        mine = [a for a in bench["agents"] if a["attack"] == attack]
        alone[attack] = over_seeds([_rate(a["attack_success_rate"]) for a in mine])
        for detector, scored in detectors.items():
            auc = (scored["auc"], tuple(scored["auc_ci95"]))
            cells.append(_cell(attack, detector, "offline", None, [_rate(a["clean_success_rate"]) for a in mine],
                               auc=auc))  # type: ignore[arg-type]  # fmt: skip
    return cells, alone


READERS = (("monitor", monitor_cells), ("best", behaviour_cells), ("arm", mitigation_cells))
"""a row key that marks a benchmark's JSON -> how its rows become cells"""
FILE_READERS = (("detectors", detector_cells),)
"""a top-level key that marks a benchmark's JSON without rows -> how it becomes cells"""


def read_cells(paths: list[str]) -> tuple[list[MatrixCell], Undefended]:
    """Every cell of every file. An attack name that more than one file measured (other agents, or other runs) is
    qualified by each file's stem, so that no two runs are pooled or mixed."""
    read: list[tuple[str, list[MatrixCell], Undefended]] = []
    for path in paths:
        bench = json.loads(Path(path).read_text())
        rows = bench.get("rows") if isinstance(bench, dict) else None
        reader = next((read for key, read in READERS if rows and key in rows[0]), None)
        if reader is None and isinstance(bench, dict):
            reader = next((read for key, read in FILE_READERS if bench.get(key) and "agents" in bench), None)
        if reader is None:
            print(f"skipped {path}: not a benchmark this script reads", file=sys.stderr)
            continue
        read.append((Path(path).stem, *reader(bench)))
    files_of: dict[str, int] = {}
    for _, _, undefended in read:
        for attack in undefended:
            files_of[attack] = files_of.get(attack, 0) + 1
    cells: list[MatrixCell] = []
    alone: Undefended = {}
    for stem, found, undefended in read:
        name = {a: f"{a} ({stem})" if files_of[a] > 1 else a for a in undefended}
        cells += [dataclasses.replace(c, attack=name[c.attack]) for c in found]
        alone.update({name[a]: v for a, v in undefended.items()})
    return cells, alone


def text(x: OverSeeds | None, pooled: Rate | None = None) -> str:
    if x is None:
        return "—"
    return x.text() + (f" [{pooled.interval[0]:.3f}, {pooled.interval[1]:.3f}]" if pooled is not None else "")


def defense_table(cells: list[MatrixCell], alone: Undefended) -> str:
    lines = [
        "| defense | attacks tried (working) | worst case | attack success, defense acting | clean success, "
        "defense acting | false alarms | detection |",
        "|---|---|---|---|---|---|---|",
    ]
    for w in worst_cases(cells, {a: v[0] for a, v in alone.items()}):
        tried = f"{w.tried} ({w.working})"
        c = w.worst
        if c is None:
            lines.append(f"| {w.defense} | {tried} | no working backdoor tried | | | | |")
            continue
        if c.auc is not None and c.auc_interval is not None:
            success = text(*alone[c.attack]) + " (offline: undefended)"
            detection = f"ROC-AUC {c.auc:.3f} [{c.auc_interval[0]:.3f}, {c.auc_interval[1]:.3f}]"
        else:
            success, detection = text(c.attack_success, c.attack_success_pooled), text(c.detection, c.detection_pooled)
        lines.append(f"| {w.defense} | {tried} | {c.attack} | {success} | {text(c.clean_success)} | "
                     f"{text(c.false_alarm, c.false_alarm_pooled)} | {detection} |")  # fmt: skip
    return "\n".join(lines)


def attack_table(cells: list[MatrixCell], alone: Undefended) -> str:
    lines = [
        "| attack | undefended attack success | best defense | attack success, defense acting | clean success, "
        "defense acting |",
        "|---|---|---|---|---|",
    ]
    for b in best_defenses(cells, alone):
        c = b.best
        if c is None:
            continue  # measured by offline detectors only: nothing acted on it
        lines.append(f"| {b.attack} | {text(b.undefended, b.undefended_pooled)} | {c.defense} | "
                     f"{text(c.attack_success, c.attack_success_pooled)} | {text(c.clean_success)} |")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", help="benchmark JSON files")
    cells, alone = read_cells(parser.parse_args().files)
    print(defense_table(cells, alone))
    print()
    print(attack_table(cells, alone))


if __name__ == "__main__":
    main()
