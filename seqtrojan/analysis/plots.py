"""Figures of the internal states: unit responses (the paper's Figures 7-8), heatmaps of all units (its
supplement), and one unintentional-trigger finding: trajectory plus goal units over time (its Figure 9)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from seqtrojan.analysis.responses import masked_mean_std
from seqtrojan.analysis.traces import StateTrace
from seqtrojan.legend import add_color_legend

NORMAL, TROJAN = "#2166ac", "#d6604d"
STATE_NAMES = {"h": "hidden state h", "c": "cell state c"}
GOAL_SCALE = "goal units, projected and scaled:\n0 = normal-env mean, 1 = trojan-env mean"


def _mean_std(trace: StateTrace, which: str, layer: int, min_episodes: int) -> tuple[np.ndarray, np.ndarray, int]:
    mean, std, counts = masked_mean_std(trace.states(which, layer), trace.mask)
    steps = int(np.flatnonzero(counts >= min_episodes).max(initial=0)) + 1
    return mean[:steps], std[:steps], steps


def plot_unit_responses(
    normal: StateTrace,
    trojan: StateTrace,
    units: Sequence[tuple[str, int, int, str]],
    trigger_step: int,
    path: Path,
    title: str,
    min_episodes: int = 30,
) -> Path:
    """One panel per (which, layer, unit, label): mean and standard deviation over episodes, both envs."""
    cols = min(4, max(1, len(units)))
    rows = (len(units) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.3 * cols, 2.5 * rows), squeeze=False)
    for ax in axes.flat[len(units) :]:
        ax.axis("off")
    for ax, (which, layer, unit, label) in zip(axes.flat, units):
        for trace, color, name in ((normal, NORMAL, "normal env"), (trojan, TROJAN, "trojan env")):
            mean, std, steps = _mean_std(trace, which, layer, min_episodes)
            t = np.arange(steps)
            ax.plot(t, mean[:, unit], color=color, lw=1.3, label=name)
            ax.fill_between(t, mean[:, unit] - std[:, unit], mean[:, unit] + std[:, unit], color=color, alpha=0.2)
        ax.axvline(trigger_step, color="k", ls=":", lw=0.8, label="trigger step")
        ax.set_title(f"{which} layer {layer} unit {unit}: {label}", fontsize=8)
        ax.set_xlabel("step", fontsize=7)
        ax.set_ylabel(f"{STATE_NAMES[which]} (mean ± sd)", fontsize=7)
        ax.tick_params(labelsize=7)
    axes.flat[0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_heatmaps(
    normal: StateTrace,
    trojan: StateTrace,
    which: str,
    layer: int,
    trigger_step: int,
    path: Path,
    title: str,
    min_episodes: int = 30,
) -> Path:
    """Mean of every unit over time in the normal env, the trojan env, and their difference."""
    mean_n, _, steps_n = _mean_std(normal, which, layer, min_episodes)
    mean_t, _, steps_t = _mean_std(trojan, which, layer, min_episodes)
    steps = min(steps_n, steps_t)
    panels = (("normal env", mean_n[:steps]), ("trojan env", mean_t[:steps]), ("trojan - normal", None))
    fig, axes = plt.subplots(1, 3, figsize=(13, 0.12 * mean_n.shape[1] + 2.2))
    bound = max(np.abs(mean_n[:steps]).max(), np.abs(mean_t[:steps]).max(), 1e-6)
    diff = mean_t[:steps] - mean_n[:steps]
    for ax, (name, data) in zip(axes, panels):
        data = diff if data is None else data
        im = ax.imshow(data.T, aspect="auto", cmap="RdBu_r", vmin=-bound, vmax=bound, interpolation="nearest")
        ax.axvline(trigger_step, color="k", ls=":", lw=0.8)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("step")
    axes[0].set_ylabel(f"unit of {STATE_NAMES[which]}")
    fig.colorbar(im, ax=axes, fraction=0.02, label=f"mean {which} over episodes (right: difference)")
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_finding(
    rgb: np.ndarray,
    series: dict[str, np.ndarray],
    reference: dict[str, np.ndarray] | None,
    event_step: int | None,
    path: Path,
    title: str,
) -> Path:
    """Left: the episode's trajectory image (with a colour legend). Right: goal-keeping units over time, as
    :meth:`GoalUnits.activation` gives them: their state projected onto the normal-to-trojan direction and scaled
    so that 0 is their mean in the normal env and 1 their mean in the trojan env, over the steps after the trigger
    step of the analysis episodes (single steps and early steps can lie well outside [0, 1]). Dashed: the other
    env's mean at each step."""
    fig, axes = plt.subplots(1, 1 + len(series), figsize=(4.2 * (1 + len(series)), 4.4))
    axes[0].imshow(rgb)
    axes[0].axis("off")
    add_color_legend(axes[0], trigger=event_step is not None, loc="upper center", bbox_to_anchor=(0.5, 0.0))
    for ax, (name, values) in zip(axes[1:], series.items()):
        ax.axhline(0.0, color=NORMAL, lw=0.8, alpha=0.6, label="0: normal-env mean")
        ax.axhline(1.0, color=TROJAN, lw=0.8, alpha=0.6, label="1: trojan-env mean")
        ax.plot(np.arange(len(values)), values, color=TROJAN, lw=1.4, label="this episode")
        if reference is not None and name in reference:
            ref = reference[name]
            ax.plot(np.arange(len(ref)), ref, color=NORMAL, ls="--", lw=1.0, label="other env, mean")
        if event_step is not None:
            ax.axvline(event_step, color="k", ls=":", lw=0.8, label="trigger step")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel(GOAL_SCALE, fontsize=8)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")  # keeps the colour legend below the picture
    plt.close(fig)
    return path
