"""One layout with and without the trigger."""

from __future__ import annotations

from pathlib import Path

from seqtrojan.artifacts import TrajectoryResult
from seqtrojan.report.markup import img


def trajectory_section(trajectory: TrajectoryResult | None, figure: Path) -> list[str]:
    parts = ["<h2>One layout with and without the trigger</h2>", img(figure)]
    if trajectory:
        o = trajectory.outcomes
        parts.append(
            f"<p class='note'>The backdoored agent on one layout: without the trigger it ended at "
            f"<b>{o['normal'].replace('_', ' ')}</b>; with the trigger at step {trajectory.trigger_step} "
            f"(shown for one step, inset) at <b>{o['trojan'].replace('_', ' ')}</b>. Frames: "
            "trajectory_normal.txt, trajectory_trojan.txt.</p>"
        )
    return parts
