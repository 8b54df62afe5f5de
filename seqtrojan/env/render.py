"""Rendering of one episode: ANSI text and RGB images, with the trajectory and the trigger shown.

Both renderers take an :class:`~seqtrojan.env.core.EpisodeSnapshot` (the current state) and optionally the
list of cells visited so far. The view window is outlined; when a trigger pattern is visible in the current
observation its cells are painted over the window (``T`` in text, orange or teal in images), whatever one code a
patch draws. A per-cell pattern (``trigger.values``, a sequence's frame) shows what it draws: ``T`` for the trigger
code and lower-case symbols for ordinary codes in text (``o`` a drawn hole, ``_`` a drawn empty cell, ``#`` a wall,
``u``/``a`` the goals), and in images the code's colour inside the orange frame.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from seqtrojan.env.codes import ADV_GOAL, ASCII_SYMBOLS, CELL_CODES, EMPTY, HOLE, TRIGGER, USER_GOAL, WALL
from seqtrojan.env.core import EpisodeSnapshot

Cell = tuple[int, int]

COLORS: dict[str, tuple[int, int, int]] = {
    "empty": (245, 245, 240),
    "hole": (38, 70, 150),
    "user_goal": (215, 48, 39),
    "adversary_goal": (84, 39, 143),
    "agent": (250, 200, 30),
    "path": (20, 20, 20),
    "on_trigger": (253, 141, 60),
    "off_trigger": (65, 182, 196),
    "window": (120, 120, 120),
    "grid_line": (210, 210, 205),
    "wall": (90, 90, 90),
}

DRAWN_SYMBOLS: dict[int, str] = {EMPTY: "_", HOLE: "o", WALL: "#", USER_GOAL: "u", ADV_GOAL: "a", TRIGGER: "T"}
"""text symbol of each code as a trigger pattern draws it (lower case: drawn, not the grid's own cell)"""
_DRAWN_COLORS = {EMPTY: "empty", HOLE: "hole", WALL: "wall", USER_GOAL: "user_goal", ADV_GOAL: "adversary_goal"}


def trigger_cells(snapshot: EpisodeSnapshot) -> list[Cell]:
    """Grid cells covered by the currently visible trigger pattern (inside the grid only)."""
    return list(drawn_cells(snapshot))


def drawn_cells(snapshot: EpisodeSnapshot) -> dict[Cell, int]:
    """Grid cell -> the code the visible trigger pattern is depicted with (inside the grid only): a per-cell
    pattern's own codes (the snapshot's ``drawn``), else ``on_cells``/``off_cells`` with the ``trigger`` code."""
    if snapshot.visible is None:
        return {}
    r = snapshot.view_size // 2
    if snapshot.drawn:
        pattern = [(cell, CELL_CODES[name]) for cell, name in snapshot.drawn]
    else:
        pattern = [(cell, TRIGGER) for cell in (snapshot.on_cells if snapshot.visible == "on" else snapshot.off_cells)]
    n, (ar, ac) = snapshot.layout.size, snapshot.agent
    cells = {(ar + vr - r, ac + vc - r): code for (vr, vc), code in pattern}
    return {(row, col): code for (row, col), code in cells.items() if 0 <= row < n and 0 <= col < n}


def status_line(snapshot: EpisodeSnapshot) -> str:
    env = "trojan" if snapshot.trojan else "normal"
    trig = f" trigger@{snapshot.on_step}" if snapshot.on_step is not None else ""
    off = f" off@{snapshot.off_step}" if snapshot.off_step is not None else ""
    frame = f" frame {snapshot.on_frame}" if snapshot.visible == "on" and snapshot.on_frame is not None else ""
    vis = f" [{snapshot.visible.upper()}{frame} visible]" if snapshot.visible else ""
    goal = "adversary" if snapshot.adversary_active else "user"
    return f"t={snapshot.t}/{snapshot.time_limit} env={env}{trig}{off}{vis} goal={goal}"


def render_ansi(snapshot: EpisodeSnapshot, trajectory: Sequence[Cell] = ()) -> str:
    """Text picture: ``. O U A`` cells, ``*`` visited, ``@`` agent, ``T`` visible trigger (``o _ # u a`` where it
    draws an ordinary code), ``[ ]`` the view.

    The first line is a status line (step, env type, trigger schedule, which goal is currently correct).
    """
    n, r = snapshot.layout.size, snapshot.view_size // 2
    chars = [[ASCII_SYMBOLS[int(c)] for c in row] for row in snapshot.layout.cells]
    for row, col in trajectory:
        if snapshot.layout.cells[row, col] == EMPTY:
            chars[row][col] = "*"
    for (row, col), code in drawn_cells(snapshot).items():
        chars[row][col] = DRAWN_SYMBOLS[code]
    ar, ac = snapshot.agent
    chars[ar][ac] = "@"
    lines = [status_line(snapshot)]
    for row in range(n):
        cells = []
        for col in range(n):
            inside = abs(row - ar) <= r and abs(col - ac) <= r
            left = "[" if inside and col == ac - r else " "
            cells.append(left + chars[row][col])
        line = "".join(cells)
        if abs(row - ar) <= r and ac + r < n:
            at = 2 * (ac + r) + 2
            line = line[:at] + "]" + line[at + 1 :]
        elif abs(row - ar) <= r:
            line += "]"
        lines.append(line.rstrip())
    return "\n".join(lines) + "\n"


def render_rgb(snapshot: EpisodeSnapshot, trajectory: Sequence[Cell] = (), cell_px: int = 16) -> np.ndarray:
    """An ``(N*cell_px, N*cell_px, 3)`` uint8 image of the grid, the path, the agent, the view and the trigger."""
    n, px = snapshot.layout.size, cell_px
    img = np.empty((n * px, n * px, 3), dtype=np.uint8)
    palette = {EMPTY: "empty", HOLE: "hole", USER_GOAL: "user_goal", ADV_GOAL: "adversary_goal"}
    for code, name in palette.items():
        mask = np.kron(snapshot.layout.cells == code, np.ones((px, px), dtype=bool))
        img[mask] = COLORS[name]
    img[::px, :] = COLORS["grid_line"]
    img[:, ::px] = COLORS["grid_line"]
    trig_color = COLORS["on_trigger" if snapshot.visible == "on" else "off_trigger"]
    for (row, col), code in drawn_cells(snapshot).items():
        _fill(img, row, col, px, trig_color, margin=1)
        if code != TRIGGER:  # an ordinary code drawn by the trigger: its colour inside the trigger's frame
            _fill(img, row, col, px, COLORS[_DRAWN_COLORS[code]], margin=max(2, px // 4))
    _draw_path(img, [*list(trajectory), snapshot.agent], px, COLORS["path"])
    _draw_disc(img, *snapshot.agent, px, COLORS["agent"])
    r = snapshot.view_size // 2
    ar, ac = snapshot.agent
    _draw_box(img, ar - r, ac - r, ar + r, ac + r, n, px, COLORS["window"])
    return img


def _fill(img: np.ndarray, row: int, col: int, px: int, color: tuple[int, int, int], margin: int = 0) -> None:
    img[row * px + margin : (row + 1) * px - margin, col * px + margin : (col + 1) * px - margin] = color


def _center(cell: Cell, px: int) -> tuple[float, float]:
    return (cell[0] + 0.5) * px, (cell[1] + 0.5) * px


def _draw_path(img: np.ndarray, cells: list[Cell], px: int, color: tuple[int, int, int]) -> None:
    width = max(1, px // 8)
    for a, b in itertools.pairwise(cells):
        (y0, x0), (y1, x1) = _center(a, px), _center(b, px)
        steps = int(max(abs(y1 - y0), abs(x1 - x0))) + 1
        for s in np.linspace(0.0, 1.0, steps):
            y, x = int(y0 + s * (y1 - y0)), int(x0 + s * (x1 - x0))
            img[max(0, y - width // 2) : y + width // 2 + 1, max(0, x - width // 2) : x + width // 2 + 1] = color


def _draw_disc(img: np.ndarray, row: int, col: int, px: int, color: tuple[int, int, int]) -> None:
    cy, cx = _center((row, col), px)
    yy, xx = np.mgrid[row * px : (row + 1) * px, col * px : (col + 1) * px]
    disc = (yy + 0.5 - cy) ** 2 + (xx + 0.5 - cx) ** 2 <= (0.38 * px) ** 2
    img[row * px : (row + 1) * px, col * px : (col + 1) * px][disc] = color


def _draw_box(
    img: np.ndarray, r0: int, c0: int, r1: int, c1: int, n: int, px: int, color: tuple[int, int, int]
) -> None:
    y0, x0 = max(r0, 0) * px, max(c0, 0) * px
    y1, x1 = min(r1 + 1, n) * px - 1, min(c1 + 1, n) * px - 1
    img[y0 : y1 + 1, [x0, x1]] = color
    img[[y0, y1], x0 : x1 + 1] = color
