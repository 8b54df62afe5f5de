"""The sequence-model comparison's figure: persistence, trigger step, settling and the edit experiment per cell."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqtrojan.experiment_results import CellsResult


def plot_cells(result: CellsResult, path: Path) -> Path:
    """Four panels, one line per cell (mean over seeds; bars: sd over seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    persistence, trigger, settle, units = axes
    bins = sorted({(lo, hi) for s in result.summaries for lo, hi, _, _ in s.persistence})
    persistence.set_xticks(range(len(bins)), [f"{lo}-{hi}" if hi < 1000 else f">={lo}" for lo, hi in bins])
    for s in result.summaries:
        if s.persistence:
            x = [bins.index((lo, hi)) for lo, hi, _, _ in s.persistence]
            persistence.errorbar(x, [b[2].mean for b in s.persistence], [b[2].sd for b in s.persistence], marker="o",
                                 capsize=2, label=s.cell)  # fmt: skip
        steps = [step for step, _ in s.by_trigger_step]
        trigger.errorbar(steps, [v.mean for _, v in s.by_trigger_step], [v.sd for _, v in s.by_trigger_step],
                         marker="o", capsize=2, label=s.cell)  # fmt: skip
        mine = [a for a in result.agents if a.cell == s.cell and a.label == "backdoored"]
        settled = [a.settling for a in mine if a.settling is not None]
        if settled:
            n = min(len(x.change) for x in settled)
            settle.plot(settled[0].steps[:n], np.mean([x.change[:n] for x in settled], 0), label=s.cell)
        with_units = [a.units for a in mine if a.units is not None]
        if with_units:
            counts = with_units[0].counts
            same = [u for u in with_units if u.counts == counts]
            units.errorbar(counts, np.mean([[r.value for r in u.activation] for u in same], 0),
                           np.std([[r.value for r in u.activation] for u in same], 0), marker="o", capsize=2,
                           label=s.cell)  # fmt: skip
    persistence.set(title="adversary's share of goals, by steps after the trigger", xlabel="steps", ylim=(-0.02, 1.02))
    trigger.set(title=f"attack success by trigger step ({result.grid})", xlabel="trigger step", ylim=(-0.02, 1.02))
    settle_grid = next((a.settling.grid for a in result.agents if a.settling), "")
    settle.set(title=f"state change per step, normal episodes ({settle_grid})", xlabel="step", yscale="log")
    units.set(title="goal switched by editing k goal units", xlabel="units edited", xscale="log", ylim=(-0.02, 1.02))
    for ax in axes:
        ax.title.set_fontsize(9)
        if ax.get_legend_handles_labels()[0]:  # a panel with no data (e.g. no persistence bin filled) has no legend
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
