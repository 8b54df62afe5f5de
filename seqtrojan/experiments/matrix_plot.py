"""The matrix's heat maps: attacks (rows) x defenses (columns)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqtrojan.experiment_results import MatrixResult


def matrix_grids(result: MatrixResult) -> dict[str, tuple[list[str], list[str], np.ndarray]]:
    """Panel title -> (attacks, defenses, values; NaN where a defense does not apply): what each defense leaves of
    the attack (mean attack success over seeds, the undefended attack first), and how well it detects (online
    detection rate, offline ROC-AUC)."""
    attacks = [a.attack for a in result.attacks]
    success_cols = ["none", *dict.fromkeys(c.defense for c in result.cells if c.attack_success is not None)]
    detect_cols = list(dict.fromkeys(c.defense for c in result.cells if c.kind in ("online", "offline")))
    success = np.full((len(attacks), len(success_cols)), np.nan)
    detect = np.full((len(attacks), len(detect_cols)), np.nan)
    for i, summary in enumerate(result.attacks):
        success[i, 0] = summary.attack_success.mean
    for c in result.cells:
        i = attacks.index(c.attack)
        if c.attack_success is not None:
            success[i, success_cols.index(c.defense)] = c.attack_success.mean
        if c.detection is not None:
            detect[i, detect_cols.index(c.defense)] = c.detection.mean
        elif c.auc is not None:
            detect[i, detect_cols.index(c.defense)] = c.auc
    return {
        "attack success with the defense acting (mean over seeds)": (attacks, success_cols, success),
        "detection: online detection rate at its false-alarm target, offline ROC-AUC": (attacks, detect_cols, detect),
    }


def plot_matrix(result: MatrixResult, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = matrix_grids(result)
    widths = [max(3.0, 1.1 * len(cols) + 2.5) for _, cols, _ in panels.values()]
    rows = max(len(a) for a, _, _ in panels.values())
    fig, axes = plt.subplots(1, len(panels), figsize=(sum(widths), 0.5 * rows + 2.4), squeeze=False,
                             gridspec_kw={"width_ratios": widths})  # fmt: skip
    for ax, (title, (attacks, cols, values)) in zip(axes[0], panels.items()):
        shown = np.ma.masked_invalid(values)
        ax.imshow(shown, cmap="RdYlGn_r" if title.startswith("attack") else "RdYlGn", vmin=0, vmax=1, aspect="auto")
        ax.set_xticks(range(len(cols)), cols, rotation=35, ha="right", fontsize=8)
        ax.set_yticks(range(len(attacks)), attacks, fontsize=8)
        for (i, j), v in np.ndenumerate(values):
            ax.text(j, i, "n/a" if np.isnan(v) else f"{v:.2f}", ha="center", va="center", fontsize=7)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
