"""Cell codes, observation channels and actions of the trojan grid world.

The encoding is part of the public, stable interface (trained models depend on it):

* Each cell of the agent's view is one of six codes, in this order:
  ``0 empty, 1 hole, 2 wall (outside the grid), 3 user goal, 4 adversary goal, 5 trigger``.
* An observation is the view window (``view_size x view_size``, centred on the agent) one-hot encoded and
  flattened row-major over cells, channel-minor: feature ``(row * view_size + col) * 6 + code``.
  The default 3x3 view gives 54 features, the paper's input size.
* Actions ``0 up, 1 right, 2 down, 3 left`` (the default ``four`` action set); ``four_and_stay`` adds
  ``4 stay``; ``eight`` adds the diagonals ``4 up-right, 5 down-right, 6 down-left, 7 up-left``.
"""

from __future__ import annotations

EMPTY, HOLE, WALL, USER_GOAL, ADV_GOAL, TRIGGER = range(6)
CELL_NAMES: tuple[str, ...] = ("empty", "hole", "wall", "user_goal", "adversary_goal", "trigger")
CELL_CODES: dict[str, int] = {name: code for code, name in enumerate(CELL_NAMES)}
NUM_CHANNELS = len(CELL_NAMES)

# (row delta, col delta) per action; row 0 is the top of the grid.
ACTION_SETS: dict[str, tuple[tuple[int, int], ...]] = {
    "four": ((-1, 0), (0, 1), (1, 0), (0, -1)),
    "four_and_stay": ((-1, 0), (0, 1), (1, 0), (0, -1), (0, 0)),
    "eight": ((-1, 0), (0, 1), (1, 0), (0, -1), (-1, 1), (1, 1), (1, -1), (-1, -1)),
}
ACTION_NAMES: dict[str, tuple[str, ...]] = {
    "four": ("up", "right", "down", "left"),
    "four_and_stay": ("up", "right", "down", "left", "stay"),
    "eight": ("up", "right", "down", "left", "up_right", "down_right", "down_left", "up_left"),
}

# Episode outcomes reported by a batched env for finished episodes (0 while running). The grid world reports the
# first five; FAILED is a Gymnasium env's episode that ended neither at a goal nor by its time limit.
RUNNING, REACHED_USER_GOAL, REACHED_ADV_GOAL, FELL_IN_HOLE, TIMED_OUT, FAILED = range(6)
OUTCOME_NAMES: tuple[str, ...] = ("running", "user_goal", "adversary_goal", "hole", "timeout", "failed")
GRID_OUTCOMES: tuple[str, ...] = OUTCOME_NAMES[:FAILED]
"""the outcomes the grid world reports (what its tallies list)"""

# ASCII symbols used by Layout.from_ascii / to_ascii and by the ANSI renderer.
ASCII_SYMBOLS: dict[int, str] = {EMPTY: ".", HOLE: "O", WALL: "#", USER_GOAL: "U", ADV_GOAL: "A", TRIGGER: "T"}
