"""The grid picture's colours (:func:`seqtrojan.env.render.render_rgb`) as a matplotlib legend, for every figure
that shows a grid: the report's trajectory figure and the analysis's findings. Outside the report package, so that
the analysis can draw it while the report reads the analysis's results."""

from __future__ import annotations

from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from seqtrojan.env.render import COLORS


def _rgb(name: str) -> tuple[float, float, float]:
    r, g, b = COLORS[name]
    return r / 255, g / 255, b / 255


def color_legend_handles(trigger: bool = True, off_trigger: bool = False) -> list:
    """Legend entries for the colours of :func:`seqtrojan.env.render.render_rgb`."""
    edge = _rgb("window")
    handles = [
        Patch(facecolor=_rgb("empty"), edgecolor=edge, label="empty cell"),
        Patch(facecolor=_rgb("hole"), label="hole"),
        Patch(facecolor=_rgb("user_goal"), label="user's goal (top right)"),
        Patch(facecolor=_rgb("adversary_goal"), label="adversary's goal (top left)"),
        Line2D([], [], color=_rgb("path"), lw=1.5, label="path taken"),
        Line2D(
            [],
            [],
            color="none",
            marker="o",
            markerfacecolor=_rgb("agent"),
            markeredgecolor="none",
            markersize=8,
            label="agent (last position)",
        ),
        Patch(facecolor="none", edgecolor=edge, lw=1.2, label="the agent's view"),
    ]
    if trigger:
        handles.append(Patch(facecolor=_rgb("on_trigger"), label="trigger patch (when shown)"))
    if off_trigger:
        handles.append(Patch(facecolor=_rgb("off_trigger"), label="OFF trigger patch (when shown)"))
    return handles


def add_color_legend(target, trigger: bool = True, off_trigger: bool = False, **kwargs):
    """A legend of the grid picture's colours on ``target`` (a matplotlib Axes or Figure)."""
    options = {"fontsize": 8, "frameon": False, "ncol": 2, "handlelength": 1.4} | kwargs
    return target.legend(handles=color_legend_handles(trigger, off_trigger), **options)
