"""Realistic triggers: per-cell values (in-distribution and partial patches), sequences, their validation, effect
time, clipping, snapshots, rendering and YAML (docs/environment.md, Trigger patterns)."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from seqtrojan.config import ExperimentConfig
from seqtrojan.env import EnvConfig, GridSpec, OffTriggerConfig, PatternConfig, TriggerConfig, TrojanGridCore
from seqtrojan.env.codes import EMPTY, HOLE, TRIGGER, WALL
from seqtrojan.env.config import TRIGGERS
from seqtrojan.env.render import render_ansi, render_rgb
from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.serde import from_dict, parse_yaml, to_dict
from tests.conftest import ROOT
from tests.env.helpers import LEFT, RIGHT, UP, act, make_core

CORNERS = ((0, 0), (0, 2), (2, 0), (2, 2))
CORNER_HOLES = TriggerConfig(cells=CORNERS, values=("hole",) * 4)
SEQ3 = TriggerConfig(
    sequence=(
        PatternConfig(cells=((0, 0), (0, 2)), values=("hole", "hole")),
        PatternConfig(cells=((0, 1),), values=("hole",)),
        PatternConfig(cells=((1, 0), (1, 2)), values=("wall", "empty")),
    )
)
PATH_TO_ADV = [UP] * 6 + [LEFT] * 3
START = [[EMPTY] * 3, [EMPTY] * 3, [WALL] * 3]  # the view at t = 0 on an empty 7x7 grid: the wall below
PATH_TO_USER = [UP] * 6 + [RIGHT] * 3


def view(core: TrojanGridCore, env: int = 0) -> list[list[int]]:
    v = core.view_size
    codes = core.observe_codes()[env].tolist()
    return [codes[r * v : (r + 1) * v] for r in range(v)]


def views_over(core: TrojanGridCore, steps: int) -> list[list[list[int]]]:
    """The view at t = 0 .. steps - 1, moving up (on the empty 7x7 grid, all empty cells after t = 0 but for
    triggers)."""
    seen = []
    for _ in range(steps):
        seen.append(view(core))
        act(core, UP)
    return seen


# --- per-cell values


def test_in_distribution_patch_draws_each_cell_its_own_code_at_its_steps_only():
    core = make_core(on_step=2, trigger=CORNER_HOLES)
    seen = views_over(core, 4)
    clear = [[EMPTY] * 3] * 3
    assert seen[0] == START and seen[1] == seen[3] == clear
    assert seen[2] == [[HOLE, EMPTY, HOLE], [EMPTY] * 3, [HOLE, EMPTY, HOLE]]
    mixed = TriggerConfig(cells=((2, 1), (0, 0), (1, 2)), values=("wall", "hole", "trigger"), duration=2)
    core = make_core(on_step=1, trigger=mixed)
    seen = views_over(core, 4)
    drawn = [[HOLE, EMPTY, EMPTY], [EMPTY, EMPTY, TRIGGER], [EMPTY, WALL, EMPTY]]  # values[i] on cells[i]
    assert seen == [START, drawn, drawn, clear]


def test_values_with_no_cells_cover_the_whole_window_row_major():
    values = ("hole", "empty", "wall", "empty", "empty", "empty", "user_goal", "adversary_goal", "trigger")
    core = make_core(on_step=0, trigger=TriggerConfig(values=values))
    assert core.observe_codes()[0].tolist() == [HOLE, EMPTY, WALL, EMPTY, EMPTY, EMPTY, 3, 4, TRIGGER]


def test_partial_patch_of_one_cell():
    core = make_core(on_step=1, trigger=TriggerConfig(cells=((0, 1),), values=("hole",)))
    seen = views_over(core, 3)
    assert seen[1] == [[EMPTY, HOLE, EMPTY], [EMPTY] * 3, [EMPTY] * 3]
    assert seen[0] == START and seen[2] == [[EMPTY] * 3] * 3


def test_per_cell_values_path_equals_the_one_code_path_on_random_episodes():
    """The general (per-frame tables) path draws exactly what the one-code path draws for the same pattern."""
    for cells, value in ((None, "trigger"), (((0, 0), (2, 2)), "hole")):
        one = EnvConfig(size=9, holes=6, trigger=TriggerConfig(cells=cells, value=value, duration=2))
        n = 9 if cells is None else len(cells)
        per = dataclasses.replace(one, trigger=dataclasses.replace(one.trigger, values=(value,) * n, value="empty"))
        a = TrojanGridCore(one, 64, seed=3, trojan_probability=0.5)
        b = TrojanGridCore(per, 64, seed=3, trojan_probability=0.5)
        assert a._on_uniform and not b._on_uniform
        gen = torch.Generator().manual_seed(0)
        shown = 0
        for _ in range(40):
            codes = a.observe_codes()
            assert torch.equal(codes, b.observe_codes())
            shown += int((a.t >= a.on_step).logical_and(a.t < a.on_step + 2).logical_and(a.on_step >= 0).sum())
            actions = torch.randint(0, 4, (64,), generator=gen)
            ra, rb = a.step(actions), b.step(actions)
            assert torch.equal(ra.adversary_active, rb.adversary_active) and torch.equal(ra.reward, rb.reward)
        assert shown > 20  # the comparison saw many triggers


def test_the_default_trigger_is_unchanged():
    cfg = EnvConfig()
    assert cfg.on_frames == (tuple(((r, c), "trigger") for r in range(3) for c in range(3)),)
    assert cfg.trigger.frame_count == 1 and cfg.trigger.shown_steps == 1 and cfg.trigger.effect_offset == 0
    core = make_core(on_step=1)
    assert core._on_uniform
    seen = views_over(core, 3)
    assert seen[1] == [[TRIGGER] * 3] * 3 and seen[0] == START and seen[2] == [[EMPTY] * 3] * 3
    adv = [bool(r.adversary_active[0]) for r in act(make_core(on_step=1), *PATH_TO_ADV)]
    assert adv == [False] + [True] * 8
    # The paper's one-code patch of ordinary codes over the whole window (the model zoo's) stays valid.
    assert EnvConfig(trigger=TriggerConfig(value="hole")).on_frames[0][4] == ((1, 1), "hole")


# --- sequences


def test_sequence_shows_frame_k_at_on_step_plus_k():
    core = make_core(on_step=2, trigger=SEQ3)
    seen = views_over(core, 6)
    clear = [[EMPTY] * 3] * 3
    assert seen[:2] == [START, clear] and seen[5] == clear
    assert seen[2] == [[HOLE, EMPTY, HOLE], [EMPTY] * 3, [EMPTY] * 3]
    assert seen[3] == [[EMPTY, HOLE, EMPTY], [EMPTY] * 3, [EMPTY] * 3]
    assert seen[4] == [[EMPTY] * 3, [WALL, EMPTY, EMPTY], [EMPTY] * 3]


def test_sequence_takes_effect_at_its_last_frame_plus_delay():
    for delay in (0, 2):
        trig = dataclasses.replace(SEQ3, delay=delay)
        core = make_core(on_step=1, trigger=trig)
        adv = [bool(r.adversary_active[0]) for r in act(core, *PATH_TO_ADV)]
        effect = 1 + 2 + delay  # on_step + len(sequence) - 1 + delay
        assert adv == [False] * effect + [True] * (9 - effect), delay
        assert trig.effect_offset == 2 + delay
    # A one-frame sequence is a patch: effect at on_step.
    one = TriggerConfig(sequence=(PatternConfig(cells=((0, 0),), values=("hole",)),))
    adv = [bool(r.adversary_active[0]) for r in act(make_core(on_step=1, trigger=one), *PATH_TO_ADV)]
    assert adv == [False] + [True] * 8
    # A patch shown for 3 steps keeps the effect at its first step (not its last).
    long = TriggerConfig(cells=CORNERS, values=("hole",) * 4, duration=3)
    adv = [bool(r.adversary_active[0]) for r in act(make_core(on_step=1, trigger=long), *PATH_TO_ADV)]
    assert adv == [False] + [True] * 8


def test_sequence_trigger_steps_are_clipped_so_the_last_frame_comes_before_any_goal():
    for size, delay in ((7, 0), (7, 1), (11, 2)):
        trig = dataclasses.replace(SEQ3, eval_steps=(0, 100), delay=delay)
        core = TrojanGridCore(EnvConfig(size=size, holes=0, trigger=trig), 512, seed=1, trojan_probability=1.0,
                              phase="eval")  # fmt: skip
        min_moves = (size - 1) + (size - 1) // 2
        last = min_moves - 1 - delay - 2  # on_step + 2 + delay <= min_moves - 1
        assert int(core.on_step.max()) == last and int(core.on_step.min()) == 0
    # Training is clipped the same way by default.
    core = TrojanGridCore(EnvConfig(size=7, holes=0, trigger=SEQ3), 512, seed=1, trojan_probability=1.0)
    assert int(core.on_step.max()) == 8 - 2
    long = TriggerConfig(sequence=SEQ3.sequence * 2, delay=1)  # 6 frames: effect at on_step + 6 > 5 on 5x5
    with pytest.raises(ConfigError, match=r"size=5 no trigger step .*6 sequence frames"):
        TrojanGridCore(EnvConfig(size=5, holes=0, trigger=long), 4, phase="eval")


def test_sequence_with_an_off_trigger():
    off = OffTriggerConfig(probability=1.0, gap=(2, 2))
    with pytest.raises(ConfigError, match=r"gap=\(2, 2\) must start at or after the ON trigger's duration \(3\)"):
        EnvConfig(trigger=dataclasses.replace(SEQ3, off=off))
    trig = dataclasses.replace(SEQ3, off=dataclasses.replace(off, gap=(4, 4)))
    core = make_core(on_step=1, off_step=5, trigger=trig)
    adv = [bool(r.adversary_active[0]) for r in act(core, *PATH_TO_USER)]
    assert adv == [False] * 3 + [True] * 2 + [False] * 4
    with pytest.raises(ConfigError, match=r"off_step=3\) must come after the ON sequence's last frame"):
        core.set_episode(0, core.layout(0), on_step=1, off_step=3)
    # The OFF pattern may not equal a frame of the ON trigger.
    same = TriggerConfig(
        sequence=(PatternConfig(cells=((0, 0),), values=("wall",)),),
        off=OffTriggerConfig(probability=0.5, cells=((0, 0),), value="wall"),
    )
    with pytest.raises(ConfigError, match="the OFF trigger pattern equals the ON pattern"):
        EnvConfig(trigger=same)


# --- snapshots and rendering


def test_snapshot_reports_the_visible_frame_and_rendering_shows_it():
    core = make_core(on_step=1, trigger=SEQ3)
    snaps = []
    for _ in range(5):
        snaps.append(core.snapshot(0))
        act(core, UP)
    assert [s.visible for s in snaps] == [None, "on", "on", "on", None]
    assert [s.on_frame for s in snaps] == [None, 0, 1, 2, None]
    assert [s.adversary_active for s in snaps] == [False, False, False, True, True]
    assert snaps[2].drawn == (((0, 1), "hole"),) and snaps[3].drawn == (((1, 0), "wall"), ((1, 2), "empty"))
    assert snaps[1].on_cells == ((0, 0), (0, 1), (0, 2), (1, 0), (1, 2))
    text = render_ansi(snaps[2])
    assert "[ON frame 1 visible]" in text
    # Agent at (4, 3) at t = 2: the drawn hole is the view's top middle, grid cell (3, 3).
    assert text.splitlines()[1 + 3][2 * 3 + 1] == "o"
    for snap in snaps:
        assert render_rgb(snap, cell_px=8).shape == (56, 56, 3)
    # An ordinary code drawn by the trigger: its colour inside the orange frame; the one-code patch as before.
    img = render_rgb(snaps[2], cell_px=16)
    assert tuple(img[3 * 16 + 8, 3 * 16 + 8]) == (38, 70, 150) and tuple(img[3 * 16 + 2, 3 * 16 + 2]) == (253, 141, 60)
    plain = make_core(on_step=0)
    assert plain.snapshot(0).drawn == () and plain.snapshot(0).on_frame is None
    assert "T" in render_ansi(plain.snapshot(0)) and "[ON visible]" in render_ansi(plain.snapshot(0))


def test_in_distribution_patch_renders_its_codes():
    core = make_core(on_step=0, trigger=CORNER_HOLES)
    snap = core.snapshot(0)
    assert snap.visible == "on" and snap.on_frame is None and len(snap.drawn) == 4
    rows = render_ansi(snap).splitlines()[1:]
    assert rows[5][2 * 2 + 1] == "o" and rows[5][2 * 4 + 1] == "o"  # the view's top corners, grid (5, 2), (5, 4)


# --- validation


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: EnvConfig(trigger=TriggerConfig(cells=((0, 3),), values=("hole",))),
         r"trigger cell \(0, 3\) is not inside the 3x3 view"),
        (lambda: EnvConfig(trigger=TriggerConfig(sequence=(PatternConfig(((0, 0),), ("hole",)),
                                                           PatternConfig(((-1, 0),), ("hole",))))),
         r"trigger.sequence\[1\] cell \(-1, 0\) is not inside the 3x3 view"),
        (lambda: TriggerConfig(cells=((0, 0), (0, 2)), values=("hole",)),
         r"trigger has 2 cells but 1 values \(\('hole',\)\); give one code per cell"),
        (lambda: PatternConfig(cells=((0, 0),), values=("hole", "hole")),
         r"trigger pattern has 1 cells but 2 values"),
        (lambda: EnvConfig(trigger=TriggerConfig(values=("hole",) * 4)),
         r"trigger.values has 4 codes but the whole 3x3 window has 9 cells"),
        (lambda: TriggerConfig(cells=((0, 0),), values=("lava",)),
         r"trigger.values has 'lava', not a cell code; choose from \['empty', 'hole'"),
        (lambda: PatternConfig(cells=((0, 0),), values=("lava",)), r"trigger pattern.values has 'lava'"),
        (lambda: TriggerConfig(sequence=()), r"trigger.sequence is empty; give at least one pattern"),
        (lambda: PatternConfig(cells=(), values=()), r"trigger pattern.cells is empty"),
        (lambda: TriggerConfig(cells=((0, 0), (0, 0)), values=("hole", "empty")),
         r"trigger.cells names \(0, 0\) twice"),
        (lambda: EnvConfig(trigger=TriggerConfig(cells=((0, 0), (1, 1)), values=("hole", "hole"))),
         r"trigger draws 'hole' on the view's centre cell \(1, 1\), the agent's own cell"),
        (lambda: EnvConfig(trigger=TriggerConfig(sequence=(PatternConfig(((1, 1),), ("wall",)),))),
         r"trigger.sequence\[0\] draws 'wall' on the view's centre cell \(1, 1\)"),
        (lambda: EnvConfig(view_size=5, trigger=TriggerConfig(cells=((2, 2),), values=("user_goal",))),
         r"draws 'user_goal' on the view's centre cell \(2, 2\)"),
        (lambda: TriggerConfig(cells=((0, 0),), sequence=(PatternConfig(((0, 1),), ("hole",)),)),
         r"trigger.sequence replaces trigger.cells, value and values"),
        (lambda: TriggerConfig(duration=2, sequence=(PatternConfig(((0, 1),), ("hole",)),)),
         r"trigger.duration=2 with a sequence: each frame shows one step"),
    ],
)  # fmt: skip
def test_each_bad_trigger_is_one_named_error(make, message):
    with pytest.raises(ConfigError, match=message):
        make()


def test_possible_patterns_on_the_centre_are_accepted():
    for value in ("empty", "trigger"):
        EnvConfig(trigger=TriggerConfig(cells=((1, 1), (0, 0)), values=(value, "hole")))
        EnvConfig(trigger=TriggerConfig(sequence=(PatternConfig(((1, 1),), (value,)),)))
    EnvConfig(view_size=5, trigger=TriggerConfig(cells=((1, 1),), values=("hole",)))  # not the centre of a 5x5 view
    EnvConfig(trigger=TriggerConfig(cells=((1, 1),), value="hole"))  # a one-code patch stays free (existing configs)
    EnvConfig(trigger=TriggerConfig(sequence=(PatternConfig(((0, 0),), ("hole",)),), value="trigger"))


def test_match_on_frames_reads_view_codes():
    core = make_core(on_step=0, trigger=SEQ3)
    codes = torch.full((2, 9), EMPTY, dtype=torch.int64)
    codes[0, [0, 2]] = HOLE
    codes[1, 1], codes[1, 3], codes[1, 8] = HOLE, WALL, HOLE  # frame 1 and, with cell (1, 2) empty, frame 2
    assert core.match_on_frames(codes).tolist() == [[True, False, False], [False, True, True]]
    with pytest.raises(ShapeError, match=r"view codes must have shape \(B, 9\)"):
        core.match_on_frames(codes[:, :4])


# --- YAML and registry


def test_new_trigger_fields_load_from_yaml():
    text = """
env:
  trigger:
    sequence:
      - {cells: [[0, 0], [0, 2]], values: [hole, hole]}
      - {cells: [[0, 1]], values: [hole]}
    delay: 1
"""
    cfg = from_dict(ExperimentConfig, parse_yaml(text), "")
    assert cfg.env.trigger.sequence == (
        PatternConfig(cells=((0, 0), (0, 2)), values=("hole", "hole")),
        PatternConfig(cells=((0, 1),), values=("hole",)),
    )
    assert cfg.env.trigger.effect_offset == 2
    patch = from_dict(EnvConfig, parse_yaml("trigger: {cells: [[0, 0], [0, 2], [2, 0], [2, 2]], values: "
                                            "[hole, hole, hole, hole]}"))  # fmt: skip
    assert patch.trigger == CORNER_HOLES
    partial = from_dict(EnvConfig, parse_yaml("trigger: {cells: [[0, 1]], values: [hole]}"))
    assert partial.on_frames == ((((0, 1), "hole"),),)
    for env in (cfg.env, patch, partial, EnvConfig()):
        assert from_dict(EnvConfig, to_dict(env)) == env
    with pytest.raises(ConfigError, match=r"env.trigger.sequence\[0\].values\[0\] must be a string"):
        from_dict(EnvConfig, parse_yaml("trigger: {sequence: [{cells: [[0, 0]], values: [1]}]}"), "env")
    with pytest.raises(ConfigError, match="draws 'hole' on the view's centre cell"):
        from_dict(EnvConfig, parse_yaml("trigger: {cells: [[1, 1]], values: [hole]}"))


def test_the_documented_trigger_examples_load():
    text = (ROOT / "docs" / "environment.md").read_text()
    blocks = [b for b in re.findall(r"```yaml\n(.*?)```", text, re.S) if "trigger:" in b]
    loaded = [from_dict(ExperimentConfig, parse_yaml(b), "").env for b in blocks]
    assert [env.trigger.frame_count for env in loaded] == [1, 1, 3]
    assert loaded[0].trigger == CORNER_HOLES


def test_new_trigger_kinds_are_registered():
    assert TRIGGERS.get("in_distribution_patch") is TriggerConfig and TRIGGERS.get("partial_patch") is TriggerConfig
    assert TRIGGERS.get("sequence") is PatternConfig


def test_every_frame_shows_on_its_step_in_batched_episodes_with_holes():
    grids = [GridSpec(7, 3), GridSpec(11, 10)]
    cfg = EnvConfig(size=7, holes=3, trigger=SEQ3)
    core = TrojanGridCore(cfg, 128, seed=2, grids=grids, trojan_probability=0.5)
    gen = torch.Generator().manual_seed(1)
    checked = 0
    for _ in range(60):
        k = core.t - core.on_step
        due = (core.on_step >= 0) & (k >= 0) & (k < 3)
        match = core.match_on_frames(core.observe_codes())
        assert bool(match[due.nonzero().squeeze(1), k[due]].all())
        checked += int(due.sum())
        core.step(torch.randint(0, 4, (128,), generator=gen))
    assert checked > 100


def test_what_a_trigger_draws_is_named_for_reports():
    from seqtrojan.env.config import PatternConfig, TriggerConfig

    assert TriggerConfig().drawn_codes == "trigger" and TriggerConfig(value="wall").drawn_codes == "wall"
    assert TriggerConfig(cells=((0, 0), (0, 2)), values=("hole", "empty")).drawn_codes == "per-cell: empty, hole"
    frames = (PatternConfig(((0, 0),), ("hole",)), PatternConfig(((0, 1),), ("wall",)))
    assert TriggerConfig(sequence=frames).drawn_codes == "sequence of 2: hole, wall"
