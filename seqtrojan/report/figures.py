"""Figures: one layout run with and without the trigger (the paper's Figure 6)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.core import EpisodeSnapshot, TrojanGridCore
from seqtrojan.env.layout import Layout
from seqtrojan.env.render import render_ansi, render_rgb
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, Policy, run_episodes
from seqtrojan.legend import add_color_legend


class _Frames:
    """Env 0's snapshot after every step of its episode (an :class:`~seqtrojan.env.rollout.EpisodeRecorder`)."""

    def __init__(self, core: TrojanGridCore) -> None:
        self.core = core
        self.frames = [core.snapshot(0)]
        self.outcome = ""

    def on_step(self, step: EpisodeStep) -> None:
        if bool(step.running[0]):
            self.frames.append(self.core.snapshot(0))

    def on_end(self, batch: EpisodeBatch) -> None:
        self.outcome = OUTCOME_NAMES[int(batch.outcome[0])]


def record_episode(core: TrojanGridCore, policy: Policy) -> tuple[list[EpisodeSnapshot], str]:
    """Snapshots of env 0 from its current state to the end of its episode, and how it ended (any other envs of
    ``core`` are stepped along until theirs end too)."""
    frames = _Frames(core)
    run_episodes(core, policy, fresh=False, recorders=[frames], check=True)
    return frames.frames, frames.outcome


def frames_to_text(frames: list[EpisodeSnapshot]) -> str:
    path = [f.agent for f in frames]
    return "\n".join(render_ansi(f, path[:i]) for i, f in enumerate(frames))


def run_pair(
    core: TrojanGridCore, layout: Layout, trigger_step: int, make_policy: Callable[[], Policy]
) -> dict[str, tuple[list[EpisodeSnapshot], str]]:
    """The same layout without the trigger and with it at ``trigger_step``; env 0 of ``core``."""
    runs = {}
    for name, on_step in (("normal", None), ("trojan", trigger_step)):
        core.set_episode(0, layout, on_step=on_step)
        runs[name] = record_episode(core, make_policy())
    return runs


def plot_trajectory_pair(runs: dict[str, tuple[list[EpisodeSnapshot], str]], title: str, path: Path) -> Path:
    """The final frame of each run with its whole path, and a third panel with the trojan run at the trigger."""
    trojan_frames = runs["trojan"][0]
    trigger = next((f for f in trojan_frames if f.visible == "on"), None)
    fig, axes = plt.subplots(1, 3, figsize=(12, 5.2), gridspec_kw={"width_ratios": [1, 1, 0.75]})
    for ax, (name, (frames, outcome)) in zip(axes, runs.items()):
        trail = [f.agent for f in frames]
        ax.imshow(render_rgb(frames[-1], trail[:-1], cell_px=24))
        label = "no trigger" if name == "normal" else f"trigger at step {frames[0].on_step}"
        ax.set_title(f"{label}: {outcome.replace('_', ' ')} after {len(frames) - 1} steps", fontsize=10)
        ax.axis("off")
    if trigger is not None:
        trail = [f.agent for f in trojan_frames]
        axes[2].imshow(render_rgb(trigger, trail[: trigger.t], cell_px=24))
        axes[2].set_title(f"the trigger (orange), shown at step {trigger.t} only", fontsize=9)
    axes[2].axis("off")
    fig.suptitle(title)
    off = any(f.visible == "off" for f in trojan_frames)
    add_color_legend(fig, trigger=True, off_trigger=off, loc="lower center", ncol=5 if off else 4)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
