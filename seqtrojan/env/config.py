"""Configuration of the trojan grid world: grid size and holes, view, rewards, triggers.

All dataclasses are frozen and validate themselves on construction, raising :class:`ConfigError` with the
offending value. Defaults follow the paper where it gives one (3x3 view, sparse +-1 rewards, a one-step trigger
covering the whole view) and are documented in ``docs/environment.md`` where it does not.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from numbers import Integral
from typing import Any, ClassVar, Literal

from seqtrojan.env.codes import ACTION_SETS, CELL_CODES, CELL_NAMES
from seqtrojan.errors import ConfigError
from seqtrojan.registry import Registry
from seqtrojan.serde import short_repr

MAX_PADDED_SIDE = 62
"""Largest ``size + view_size - 1``: each padded grid row is one 64-bit word in the solvability check."""

Cell = tuple[int, int]


def start_cell(size: int) -> Cell:
    """The start of an N x N grid: bottom row, centre column ``(N - 1, N // 2)`` (row 0 is the top)."""
    return (size - 1, size // 2)


def user_goal_cell(size: int) -> Cell:
    """The user's goal: the top-right corner ``(0, N - 1)``."""
    return (0, size - 1)


def adversary_goal_cell(size: int) -> Cell:
    """The adversary's goal: the top-left corner ``(0, 0)``."""
    return (0, 0)


def max_holes(size: int) -> int:
    """Largest hole count for which a layout with both goals reachable exists.

    A path from the start (bottom centre) to both top corners needs at least ``2 * size - 1`` free cells
    (the centre column plus the top row), and that many always suffice.
    """
    return (size - 1) ** 2


def min_steps_to_goal(size: int) -> int:
    """Fewest moves from the start to either goal (Manhattan distance; holes can only make it longer)."""
    (start_row, start_col), (goal_row, goal_col) = start_cell(size), user_goal_cell(size)
    return (start_row - goal_row) + (goal_col - start_col)  # both goals are equally far (the start is centred)


_GRID_TEXT = re.compile(r"\s*(\d+)\s*(?:x\s*(\d+)\s*)?/\s*(\d+)\s*", re.ASCII)
_GRID_KEYS = ("size", "holes", "max_steps")


def _grid_int(value: Any, name: str, written: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise ConfigError(f"grid {name} must be an integer, got {value!r} in {written!r}")
    return int(value)


@dataclass(frozen=True)
class GridSpec:
    """One grid configuration: side, hole count and time limit."""

    size: int = 7
    """side N of the square grid (odd, >= 5)"""
    holes: int = 3
    """number of holes H, placed afresh every episode"""
    max_steps: int | None = None
    """time limit in actions; None means 4 * size"""

    def __post_init__(self) -> None:
        if not isinstance(self.size, int) or self.size < 5 or self.size % 2 == 0:
            raise ConfigError(f"grid size must be an odd integer >= 5, got size={self.size!r}")
        if not isinstance(self.holes, int) or self.holes < 0:
            raise ConfigError(f"holes must be a non-negative integer, got holes={self.holes!r}")
        if self.holes > max_holes(self.size):
            raise ConfigError(
                f"no solvable layout exists for size={self.size}, holes={self.holes}: a path from the start to "
                f"both goals needs {2 * self.size - 1} free cells, so at most {max_holes(self.size)} holes fit"
            )
        if self.max_steps is not None and (not isinstance(self.max_steps, int) or self.max_steps < 1):
            raise ConfigError(f"max_steps must be a positive integer or None, got max_steps={self.max_steps!r}")

    @classmethod
    def parse(cls, grid: GridSpec | str | Sequence[int] | Mapping[str, Any]) -> GridSpec:
        """A grid written any of the ways configs and the command line write one: a GridSpec; ``"NxN/H"`` or
        ``"N/H"`` (e.g. ``"7x7/3"``, ``"11/11"``); ``(N, H)`` or ``(N, H, max_steps)``; or a mapping with keys
        ``size``, ``holes`` and optionally ``max_steps`` (missing ones take GridSpec's defaults). Raises
        :class:`ConfigError` naming the value for anything else (and for what GridSpec itself refuses)."""
        if isinstance(grid, GridSpec):
            return grid
        if isinstance(grid, str):
            match = _GRID_TEXT.fullmatch(grid)
            if match is None:
                raise ConfigError(f"cannot read grid config {grid!r}: write size/holes or NxN/holes, e.g. 11x11/11")
            size, other, holes = match.groups()
            if other is not None and other != size:
                raise ConfigError(f"grid {grid!r} is not square: the grid is N x N, e.g. {size}x{size}/{holes}")
            return cls(int(size), int(holes))
        if isinstance(grid, Mapping):
            unknown = sorted(set(grid) - set(_GRID_KEYS), key=str)
            if unknown:
                raise ConfigError(f"unknown grid key(s) {unknown} in {dict(grid)!r}; known keys: {list(_GRID_KEYS)}")
            kw: dict[str, Any] = {
                k: _grid_int(v, k, dict(grid)) if k != "max_steps" or v is not None else None for k, v in grid.items()
            }
            return cls(**kw)
        if isinstance(grid, Sequence) and 2 <= len(grid) <= 3:
            size, holes = (_grid_int(v, k, grid) for v, k in zip(grid[:2], _GRID_KEYS))
            max_steps = grid[2] if len(grid) == 3 else None
            return cls(size, holes, None if max_steps is None else _grid_int(max_steps, "max_steps", grid))
        raise ConfigError(
            f"cannot read grid config {grid!r}: give NxN/holes or N/holes, (size, holes[, max_steps]) or a "
            "mapping with keys size, holes[, max_steps]"
        )

    @property
    def time_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else 4 * self.size

    @property
    def label(self) -> str:
        return f"{self.size}x{self.size}/{self.holes}"

    @property
    def start(self) -> Cell:
        """The start cell (row, col): bottom row, centre column."""
        return start_cell(self.size)

    @property
    def user_goal(self) -> Cell:
        return user_goal_cell(self.size)

    @property
    def adversary_goal(self) -> Cell:
        return adversary_goal_cell(self.size)


@dataclass(frozen=True)
class RewardConfig:
    """Rewards; the paper's sparse scheme by default: +1 for the correct goal, -1 for a failure, 0 otherwise."""

    goal: float = 1.0
    """reaching the correct goal"""
    wrong_goal: float = -1.0
    """reaching the other goal"""
    false_activation: float | None = None
    """reaching the adversary's goal while the user's goal is correct (no trigger yet, or switched back): an
    unintended activation. None: ``wrong_goal``. The adversary's knob against unintentional triggers;
    ``seqtrojan.experiments.tradeoff`` measures what a harsher value buys"""
    hole: float = -1.0
    """falling into a hole"""
    timeout: float = -1.0
    """hitting the time limit, a failure like a hole (the paper: -1 for not behaving correctly). With 0, PPO
    learns to wait out the clock rather than risk a hole (measured: docs/environment.md, Rewards)"""
    step: float = 0.0
    """every other step"""


@dataclass(frozen=True)
class OffTriggerConfig:
    """The OFF trigger of the paper's section 3: a second pattern that switches the agent back to the user's goal.

    In a trojan episode that gets one (with ``probability``), it is shown ``gap`` steps after the ON trigger.
    """

    probability: float = 0.0
    """chance that a trojan episode also shows the OFF trigger; 0 disables ON/OFF"""
    cells: tuple[Cell, ...] | None = None
    """view cells (row, col) of the pattern; None means the middle row and column (a cross)"""
    value: str = "trigger"
    """cell code drawn on those cells"""
    duration: int = 1
    """steps the pattern stays visible"""
    gap: tuple[int, int] = (3, 8)
    """inclusive range of steps between the ON trigger's first step and the OFF trigger's first step"""


@dataclass(frozen=True)
class DecoyConfig:
    """Decoys: one-step patches shown in *normal* training episodes, which the agent is trained to ignore.

    The attacker who knows a trigger-search defense (the behaviour detector shows one-step patches and watches for
    a goal switch) trains its backdoor against that search: with ``probability``, a normal training episode shows,
    for one step at a step drawn like the trigger's, a patch drawn as the search draws its candidates: with
    ``whole_view_share`` one code over the whole view, else each view cell drawn on with ``density`` (at least one)
    with one of ``codes``. The user's goal stays correct, so any one-step patch the search can produce teaches the
    agent not to switch. Only a trigger that needs more than one step (a sequence) survives this: the env refuses
    decoys beside a one-step trigger. Decoys are a training device: evaluation episodes never show them."""

    probability: float = 0.0
    """chance that a normal training episode shows a decoy; 0 turns decoys off"""
    density: float = 0.5
    """chance that a random decoy draws on each view cell (the behaviour detector's ``patch_density``)"""
    whole_view_share: float = 0.2
    """share of decoys that draw one code over the whole view (the detector's 6 of its 30 candidates)"""
    codes: tuple[str, ...] = ("empty", "hole", "wall", "user_goal", "adversary_goal")
    """codes a random decoy draws per cell; a whole-view decoy draws any cell code (``trigger`` included)"""

    def __post_init__(self) -> None:
        for name, value in (("probability", self.probability), ("density", self.density),
                            ("whole_view_share", self.whole_view_share)):  # fmt: skip
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ConfigError(f"trigger.decoys.{name} must be a number in [0, 1], got {short_repr(value)}")
        if self.density == 0.0:
            raise ConfigError("trigger.decoys.density must be > 0 (a decoy draws on at least one cell)")
        if not self.codes or len(set(self.codes)) != len(self.codes):
            raise ConfigError(f"trigger.decoys.codes must name distinct cell codes, got {self.codes!r}")
        _check_values("trigger.decoys", None, self.codes)

    @property
    def enabled(self) -> bool:
        return self.probability > 0


@dataclass(frozen=True)
class PatternConfig:
    """One frame of a sequence trigger: view cells and the cell code drawn on each (``values[i]`` on ``cells[i]``)."""

    cells: tuple[Cell, ...]
    """view cells (row, col), 0-based from the view's top-left; at least one, none twice"""
    values: tuple[str, ...]
    """one cell code per cell (empty, hole, wall, user_goal, adversary_goal, trigger)"""

    def __post_init__(self) -> None:
        _check_values("trigger pattern", self.cells, self.values)


@dataclass(frozen=True)
class TriggerConfig:
    """The ON trigger: which view cells show which value, for how long, and when.

    Three ways to write the pattern (docs/environment.md, Trigger patterns): one code on a patch (``cells`` + ``value``,
    the paper's); one code per cell (``cells`` + ``values``: an in-distribution or partial patch); or a sequence
    of patterns shown on consecutive steps (``sequence``), whose effect comes when its last frame has been shown.
    """

    cells: tuple[Cell, ...] | None = None
    """view cells (row, col), 0-based from the view's top-left, of the patch; None means the whole window"""
    value: str = "trigger"
    """cell code drawn on the patch (any of: empty, hole, wall, user_goal, adversary_goal, trigger)"""
    values: tuple[str, ...] | None = None
    """one cell code per cell of ``cells`` (in its order; with ``cells`` None, per cell of the whole window,
    row-major), instead of ``value`` on all; such a pattern may not draw a hole, wall or goal on the agent's own
    cell (the view's centre), which no normal observation shows"""
    sequence: tuple[PatternConfig, ...] | None = None
    """frames shown one per step, frame k at step ``on_step + k``; the goal switches ``delay`` steps after the last
    frame. Replaces ``cells``/``value``/``values`` (leave them unset) and needs ``duration`` 1"""
    duration: int = 1
    """steps the patch stays visible (the paper: 1)"""
    train_steps: tuple[int, int] = (1, 15)
    """inclusive range of the first trigger step t during training, drawn per episode"""
    eval_steps: tuple[int, int] = (1, 15)
    """inclusive range of t during evaluation; always clipped so that no goal can be reached before it"""
    clip_train_steps: bool = True
    """also clip the training range so that the trigger comes before any goal can be reached"""
    delay: int = 0
    """activation delay k: the correct goal switches k steps after the trigger takes effect (its first step, or a
    sequence's last frame)"""
    off: OffTriggerConfig = field(default_factory=OffTriggerConfig)
    """optional OFF trigger"""
    decoys: DecoyConfig = field(default_factory=DecoyConfig)
    """one-step patches in normal training episodes that the agent learns to ignore (off by default)"""

    def __post_init__(self) -> None:
        if self.values is not None:
            _check_values("trigger", self.cells, self.values)
        if self.sequence is None:
            return
        if len(self.sequence) == 0:
            raise ConfigError("trigger.sequence is empty; give at least one pattern, or None for a single patch")
        if self.cells is not None or self.values is not None or self.value != "trigger":
            raise ConfigError(
                f"trigger.sequence replaces trigger.cells, value and values; leave them unset (got cells="
                f"{self.cells!r}, value={self.value!r}, values={self.values!r})"
            )
        if self.duration != 1:
            raise ConfigError(
                f"trigger.duration={self.duration!r} with a sequence: each frame shows one step, so duration must "
                "be 1 (repeat a pattern in the sequence to show it longer)"
            )

    @property
    def frame_count(self) -> int:
        """Frames of the ON trigger: the sequence's length, else 1."""
        return 1 if self.sequence is None else len(self.sequence)

    @property
    def shown_steps(self) -> int:
        """Steps the ON trigger is visible: a sequence's length, else ``duration``."""
        return self.duration if self.sequence is None else len(self.sequence)

    @property
    def effect_offset(self) -> int:
        """Steps from the ON trigger's first step to its effect: ``delay``, plus ``len(sequence) - 1``."""
        return self.frame_count - 1 + self.delay

    @property
    def drawn_codes(self) -> str:
        """What the ON trigger draws, in a few words: its one code (``trigger``, ``hole``), the distinct codes of a
        per-cell patch (``per-cell: empty, hole``), or a sequence's length and codes."""
        if self.sequence is not None:
            codes = sorted({code for frame in self.sequence for code in frame.values})
            return f"sequence of {len(self.sequence)}: {', '.join(codes)}"
        if self.values is not None:
            return "per-cell: " + ", ".join(sorted(set(self.values)))
        return self.value


@dataclass(frozen=True)
class EnvConfig:
    """The grid world: grid, view, actions, rewards and trigger."""

    KIND: ClassVar[str] = "grid"
    """the tag of this kind of ``env:`` section (a grid world section needs none: it is the default kind)"""

    size: int = 7
    """side N of the square grid (odd, >= 5)"""
    holes: int = 3
    """number of holes H"""
    max_steps: int | None = None
    """time limit in actions; None means 4 * size"""
    view_size: int = 3
    """side of the square view centred on the agent (odd, >= 3: the view's border is also the wall ring that keeps
    the agent on the grid)"""
    actions: Literal["four", "four_and_stay", "eight"] = "four"
    """action set: four moves (the paper's), plus 'stay', or eight (with diagonals)"""
    rewards: RewardConfig = field(default_factory=RewardConfig)
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    max_layout_tries: int = 1000
    """hole layouts tried per episode before giving up with an error (never a hang); >= 1. Any value suits a grid
    with at most one hole (always solvable); with more, the env refuses a grid unless all tries fail with
    probability <= e^-30: at least 5 tries, about 30 / p where a share p of random layouts is solvable"""

    def __post_init__(self) -> None:
        if (
            isinstance(self.view_size, bool)
            or not isinstance(self.view_size, int)
            or self.view_size < 3
            or self.view_size % 2 == 0
        ):
            raise ConfigError(f"view_size must be an odd integer >= 3, got view_size={self.view_size!r}")
        if self.actions not in ACTION_SETS:
            raise ConfigError(f"unknown action set actions={self.actions!r}; choose one of {sorted(ACTION_SETS)}")
        if (
            isinstance(self.max_layout_tries, bool)
            or not isinstance(self.max_layout_tries, int)
            or self.max_layout_tries < 1
        ):
            raise ConfigError(f"max_layout_tries must be >= 1, got {self.max_layout_tries}")
        self.grid  # validates size, holes and max_steps  # noqa: B018
        self.check_padded_side(self.size)
        _check_pattern("trigger", self.trigger.cells, self.trigger.value, self.trigger.duration, self.view_size)
        self._check_on_frames()
        _check_range("trigger.train_steps", self.trigger.train_steps)
        _check_range("trigger.eval_steps", self.trigger.eval_steps)
        if self.trigger.delay < 0:
            raise ConfigError(f"trigger.delay must be >= 0, got {self.trigger.delay}")
        off = self.trigger.off
        if not 0.0 <= off.probability <= 1.0:
            raise ConfigError(f"trigger.off.probability must be in [0, 1], got {off.probability}")
        if self.trigger.decoys.enabled and self.trigger.frame_count < 2:
            raise ConfigError(
                "trigger.decoys need a sequence trigger (two frames or more): a decoy is a one-step patch, which "
                "could draw a one-step trigger itself and teach the agent to ignore it"
            )
        _check_pattern("trigger.off", off.cells, off.value, off.duration, self.view_size)
        _check_range("trigger.off.gap", off.gap)
        if off.probability > 0:
            if off.gap[0] < self.trigger.shown_steps:
                raise ConfigError(
                    f"trigger.off.gap={off.gap} must start at or after the ON trigger's duration "
                    f"({self.trigger.shown_steps}) so that the two patterns never overlap"
                )
            off_frame = tuple((cell, off.value) for cell in self.off_cells)
            if any(frame == off_frame for frame in self.on_frames):
                raise ConfigError("the OFF trigger pattern equals the ON pattern; give it other cells or another value")

    def _check_on_frames(self) -> None:
        """The ON trigger's per-cell values and sequence frames: inside the view, one code per cell, and (for
        these in-distribution kinds) no hole, wall or goal drawn on the agent's own cell."""
        trig, v = self.trigger, self.view_size
        if trig.sequence is not None:
            named = [(f"trigger.sequence[{k}]", p.cells, p.values) for k, p in enumerate(trig.sequence)]
        elif trig.values is not None:
            named = [("trigger", self.on_cells if trig.cells is None else trig.cells, trig.values)]
        else:
            return  # one code on a patch: the paper's kind, checked by _check_pattern
        centre = (v // 2, v // 2)
        for name, cells, values in named:
            if trig.cells is None and trig.sequence is None and len(values) != len(cells):
                raise ConfigError(
                    f"trigger.values has {len(values)} codes but the whole {v}x{v} window has {len(cells)} cells; "
                    "give one code per cell (row-major) or set trigger.cells"
                )
            _check_values(name, cells, values)
            _check_pattern(name, cells, "trigger", 1, v)
            for cell, value in zip(cells, values, strict=True):
                if tuple(cell) == centre and value in _NEVER_ON_AGENT:
                    raise ConfigError(
                        f"{name} draws {value!r} on the view's centre cell {centre}, the agent's own cell, which no "
                        "normal observation shows (an impossible in-distribution pattern); use 'empty' or 'trigger' "
                        "there, or leave the centre out"
                    )

    def check_padded_side(self, size: int) -> None:
        padded = size + self.view_size - 1
        if padded > MAX_PADDED_SIDE:
            raise ConfigError(
                f"size={size} with view_size={self.view_size} is too large: size + view_size - 1 must be "
                f"<= {MAX_PADDED_SIDE}"
            )

    @property
    def grid(self) -> GridSpec:
        return GridSpec(self.size, self.holes, self.max_steps)

    def with_grid(self, grid: GridSpec | str | Sequence[int] | Mapping[str, Any]) -> EnvConfig:
        """This env on another grid (anything :meth:`GridSpec.parse` reads): its size, holes and time limit. The
        time limit is the grid's: ``4 * size`` unless the grid sets ``max_steps`` (docs/environment.md). This
        env's own ``max_steps`` is not carried over; to keep it, put it in the grid."""
        spec = GridSpec.parse(grid)
        return dataclasses.replace(self, size=spec.size, holes=spec.holes, max_steps=spec.max_steps)

    @property
    def start(self) -> Cell:
        """The start cell (row, col) of this env's grid."""
        return self.grid.start

    @property
    def goals(self) -> tuple[Cell, Cell]:
        """The goal cells (row, col) of this env's grid: (user's goal, adversary's goal)."""
        return (self.grid.user_goal, self.grid.adversary_goal)

    @property
    def num_actions(self) -> int:
        return len(ACTION_SETS[self.actions])

    @property
    def obs_dim(self) -> int:
        return self.view_size * self.view_size * len(CELL_NAMES)

    @property
    def on_cells(self) -> tuple[Cell, ...]:
        """The ON patch's view cells, with the default (whole window) filled in; for a sequence, every cell any of
        its frames draws on."""
        v = self.view_size
        if self.trigger.sequence is not None:
            return tuple(sorted({_cell(cell) for p in self.trigger.sequence for cell in p.cells}))
        if self.trigger.cells is None:
            return tuple((r, c) for r in range(v) for c in range(v))
        return tuple(sorted(set(map(tuple, self.trigger.cells))))  # type: ignore[arg-type]

    @property
    def on_frames(self) -> tuple[tuple[tuple[Cell, str], ...], ...]:
        """The ON trigger's frames, frame k shown at step ``on_step + k``: each the (view cell, code name) pairs it
        draws, sorted by cell. One frame (the patch, ``value`` or ``values`` on ``cells``) unless a sequence."""
        trig = self.trigger
        if trig.sequence is not None:
            return tuple(
                tuple(sorted(zip(map(_cell, p.cells), p.values, strict=True))) for p in trig.sequence
            )  # fmt: skip
        if trig.values is None:
            return (tuple((cell, trig.value) for cell in self.on_cells),)
        v = self.view_size
        cells = [(r, c) for r in range(v) for c in range(v)] if trig.cells is None else map(_cell, trig.cells)
        return (tuple(sorted(zip(cells, trig.values, strict=True))),)

    @property
    def off_cells(self) -> tuple[Cell, ...]:
        """The OFF patch's view cells, with the default (middle row and column) filled in."""
        v, m = self.view_size, self.view_size // 2
        if self.trigger.off.cells is None:
            return tuple(sorted({(m, c) for c in range(v)} | {(r, m) for r in range(v)}))
        return tuple(sorted(set(map(tuple, self.trigger.off.cells))))  # type: ignore[arg-type]


def _check_pattern(name: str, cells: tuple[Cell, ...] | None, value: str, duration: int, view: int) -> None:
    if value not in CELL_CODES:
        raise ConfigError(f"{name}.value={value!r} is not a cell code; choose one of {list(CELL_NAMES)}")
    if not isinstance(duration, int) or duration < 1:
        raise ConfigError(f"{name}.duration must be a positive integer, got {duration!r}")
    if cells is None:
        return
    if len(cells) == 0:
        raise ConfigError(f"{name}.cells is empty; give at least one view cell or None for the whole window")
    for cell in cells:
        if len(cell) != 2 or not all(isinstance(x, int) and 0 <= x < view for x in cell):
            raise ConfigError(
                f"{name} cell {tuple(cell)!r} is not inside the {view}x{view} view (row and col must be 0..{view - 1})"
            )


_NEVER_ON_AGENT = frozenset({"hole", "wall", "user_goal", "adversary_goal"})
"""codes a normal observation never shows on the view's centre (the agent's own cell)"""


def _cell(cell: Sequence[int]) -> Cell:
    return (int(cell[0]), int(cell[1]))


def _check_values(name: str, cells: Sequence[Cell] | None, values: Sequence[str]) -> None:
    """One known code per cell, no cell twice (``cells`` None: only the codes are checked)."""
    for value in values:
        if value not in CELL_CODES:
            raise ConfigError(f"{name}.values has {value!r}, not a cell code; choose from {list(CELL_NAMES)}")
    if cells is None:
        return
    if len(cells) == 0:
        raise ConfigError(f"{name}.cells is empty; give at least one view cell")
    if len(values) != len(cells):
        raise ConfigError(
            f"{name} has {len(cells)} cells but {len(values)} values ({tuple(values)!r}); give one code per cell"
        )
    seen = [tuple(cell) for cell in cells]
    twice = sorted({cell for cell in seen if seen.count(cell) > 1})
    if twice:
        raise ConfigError(f"{name}.cells names {twice[0]!r} twice; give each cell once with its one value")


def _check_range(name: str, bounds: tuple[int, int]) -> None:
    if len(bounds) != 2 or bounds[0] < 0 or bounds[1] < bounds[0]:
        raise ConfigError(f"{name}={tuple(bounds)!r} must be an inclusive range (lo, hi) with 0 <= lo <= hi")


TRIGGERS: Registry[type] = Registry("attack", "trigger")
"""The trigger kinds the env can show, each set by the config class registered with it."""
TRIGGERS.register("patch", "a patch of view cells drawn with one cell code (env.trigger)", TriggerConfig)
TRIGGERS.register("on_off", "an OFF pattern that switches back to the user's goal (env.trigger.off)", OffTriggerConfig)
TRIGGERS.register("delayed", "the goal switches k steps after the trigger shows (env.trigger.delay)", TriggerConfig)
TRIGGERS.register(
    "in_distribution_patch", "a patch of ordinary cell codes, one per cell (env.trigger.cells + values)", TriggerConfig
)
TRIGGERS.register(
    "partial_patch", "a few view cells (1-3) with their own codes (env.trigger.cells + values)", TriggerConfig
)
TRIGGERS.register(
    "sequence", "patterns shown on consecutive steps; effect after the last (env.trigger.sequence)", PatternConfig
)
TRIGGERS.register(
    "decoys", "one-step patches in normal training episodes that the agent learns to ignore (env.trigger.decoys)",
    DecoyConfig,
)  # fmt: skip

REWARDS: Registry[type] = Registry("attack", "reward")
"""The rewards the adversary trains with, each set by the config class registered with it."""
REWARDS.register("env_rewards", "sparse rewards: goal, wrong goal, hole, timeout, step (env.rewards)", RewardConfig)
REWARDS.register(
    "false_activation", "penalty for the adversary's goal reached with no trigger (env.rewards.false_activation)",
    RewardConfig,
)  # fmt: skip
