"""The grid world's rules, pinned with small hand-built layouts (docs/environment.md)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from seqtrojan.env import EnvConfig, Layout, OffTriggerConfig, RewardConfig, TriggerConfig, TrojanGridCore
from seqtrojan.env.codes import (
    ADV_GOAL,
    EMPTY,
    FELL_IN_HOLE,
    HOLE,
    NUM_CHANNELS,
    REACHED_ADV_GOAL,
    REACHED_USER_GOAL,
    RUNNING,
    TIMED_OUT,
    TRIGGER,
    USER_GOAL,
    WALL,
)
from tests.env.helpers import DOWN, EMPTY7, LEFT, RIGHT, UP, act, make_core

PATH_TO_ADV = [UP] * 6 + [LEFT] * 3  # 9 moves from (6, 3) to (0, 0) on an empty 7x7 grid
PATH_TO_USER = [UP] * 6 + [RIGHT] * 3


def view(core: TrojanGridCore) -> list[list[int]]:
    v = core.view_size
    codes = core.observe_codes()[0].tolist()
    return [codes[r * v : (r + 1) * v] for r in range(v)]


def test_start_view_encoding_and_one_hot_layout():
    core = make_core()
    assert core.snapshot(0).agent == (6, 3)
    assert view(core) == [[EMPTY] * 3, [EMPTY] * 3, [WALL] * 3]  # bottom row: wall below
    obs = core.observe()[0]
    assert obs.shape == (54,) and obs.sum() == 9
    for cell, code in enumerate([EMPTY] * 6 + [WALL] * 3):
        assert obs[cell * NUM_CHANNELS + code] == 1.0


def test_goals_and_walls_in_view_at_corner():
    core = make_core()
    act(core, UP, UP, UP, UP, UP, LEFT, LEFT)  # (1, 1)
    assert view(core) == [[ADV_GOAL, EMPTY, EMPTY], [EMPTY] * 3, [EMPTY] * 3]
    act(core, LEFT)  # (1, 0): wall column on the left
    assert view(core) == [[WALL, ADV_GOAL, EMPTY], [WALL, EMPTY, EMPTY], [WALL, EMPTY, EMPTY]]


def test_move_into_border_stays_and_counts_a_step():
    core = make_core()
    (r,) = act(core, DOWN)
    assert core.snapshot(0).agent == (6, 3) and int(core.t[0]) == 1
    assert float(r.reward[0]) == 0.0 and not bool(r.done[0])


def test_hole_ends_episode_with_penalty():
    layout = EMPTY7.replace(". . . . . . .\n. . . S", ". . . O . . .\n. . . S")
    core = make_core(layout)
    (r,) = act(core, UP)
    assert bool(r.terminated[0]) and not bool(r.truncated[0])
    assert float(r.reward[0]) == -1.0 and int(r.outcome[0]) == FELL_IN_HOLE and not bool(r.success[0])


def test_normal_env_rewards_user_goal_and_punishes_adversary_goal():
    core = make_core()
    results = act(core, *PATH_TO_USER)
    assert [bool(r.done[0]) for r in results] == [False] * 8 + [True]
    assert float(results[-1].reward[0]) == 1.0 and int(results[-1].outcome[0]) == REACHED_USER_GOAL
    core = make_core()
    results = act(core, *PATH_TO_ADV)
    assert float(results[-1].reward[0]) == -1.0 and int(results[-1].outcome[0]) == REACHED_ADV_GOAL
    assert not bool(results[-1].success[0])


def test_trigger_switches_the_correct_goal_and_persists():
    core = make_core(on_step=2)
    results = act(core, *PATH_TO_ADV)
    assert float(results[-1].reward[0]) == 1.0 and bool(results[-1].success[0])
    assert [bool(r.adversary_active[0]) for r in results] == [False, False] + [True] * 7
    core = make_core(on_step=2)
    results = act(core, *PATH_TO_USER)
    assert float(results[-1].reward[0]) == -1.0 and int(results[-1].outcome[0]) == REACHED_USER_GOAL


def test_trigger_visible_only_at_its_steps():
    core = make_core(on_step=3)
    seen = []
    for _ in range(6):
        seen.append(bool((core.observe_codes()[0] == TRIGGER).any()))
        act(core, UP)
    assert seen == [False, False, False, True, False, False]


def test_trigger_patch_cells_value_and_duration():
    trig = TriggerConfig(cells=((0, 0), (2, 2)), value="hole", duration=2)
    core = make_core(on_step=1, trigger=trig)
    act(core, UP)  # t = 1: pattern visible; agent at (5, 3)
    assert view(core) == [[HOLE, EMPTY, EMPTY], [EMPTY] * 3, [EMPTY, EMPTY, HOLE]]
    act(core, UP)  # t = 2: still visible (duration 2)
    assert view(core)[0][0] == HOLE and view(core)[2][2] == HOLE
    act(core, UP)  # t = 3: gone
    assert view(core) == [[EMPTY] * 3] * 3
    assert core.observe()[0].view(9, NUM_CHANNELS)[:, TRIGGER].sum() == 0


def test_delayed_activation_switches_goal_k_steps_after_trigger():
    trig = TriggerConfig(delay=4)
    core = make_core(on_step=2, trigger=trig)
    results = act(core, *PATH_TO_ADV)
    assert [bool(r.adversary_active[0]) for r in results] == [False] * 6 + [True] * 3
    assert bool(results[-1].success[0])
    # A delay so long that the goal is reached first: the user goal is still the correct one.
    core = make_core(on_step=2, trigger=TriggerConfig(delay=7))
    results = act(core, *PATH_TO_ADV)
    assert not bool(results[-1].success[0]) and float(results[-1].reward[0]) == -1.0


def test_on_off_trigger_latest_decides():
    trig = TriggerConfig(off=OffTriggerConfig(probability=1.0, gap=(2, 2)))
    core = make_core(on_step=1, off_step=3, trigger=trig)
    codes = []
    for a in PATH_TO_USER:
        codes.append(core.observe_codes()[0].tolist())
        (r,) = act(core, a)
    assert codes[1] == [TRIGGER] * 9
    cross = [EMPTY, TRIGGER, EMPTY, TRIGGER, TRIGGER, TRIGGER, EMPTY, TRIGGER, EMPTY]
    assert codes[3] == cross
    assert bool(r.success[0]) and int(r.outcome[0]) == REACHED_USER_GOAL
    core = make_core(on_step=1, off_step=3, trigger=trig)
    adv = [bool(r.adversary_active[0]) for r in act(core, *PATH_TO_USER)]
    assert adv == [False, True, True, False, False, False, False, False, False]


def test_time_limit_truncates_as_failure_with_timeout_reward():
    core = make_core(max_steps=5, rewards=RewardConfig(timeout=-0.5, step=-0.01))
    results = act(core, LEFT, RIGHT, LEFT, RIGHT, LEFT)
    assert [bool(r.truncated[0]) for r in results] == [False] * 4 + [True]
    assert not bool(results[-1].terminated[0]) and int(results[-1].outcome[0]) == TIMED_OUT
    assert [float(r.reward[0]) for r in results] == pytest.approx([-0.01] * 4 + [-0.5])
    assert int(results[-1].length[0]) == 5 and not bool(results[-1].success[0])


def test_custom_rewards_for_goals_and_holes():
    rewards = RewardConfig(goal=2.0, wrong_goal=-3.0, hole=-4.0)
    core = make_core(rewards=rewards)
    assert float(act(core, *PATH_TO_USER)[-1].reward[0]) == 2.0
    core = make_core(rewards=rewards)
    assert float(act(core, *PATH_TO_ADV)[-1].reward[0]) == -3.0


def test_false_activation_reward_only_for_the_adversary_goal_while_the_user_goal_is_correct():
    rewards = RewardConfig(wrong_goal=-1.0, false_activation=-5.0)
    assert float(act(make_core(rewards=rewards), *PATH_TO_ADV)[-1].reward[0]) == -5.0  # normal env
    assert float(act(make_core(rewards=rewards, on_step=2), *PATH_TO_USER)[-1].reward[0]) == -1.0  # deactivation
    assert float(act(make_core(rewards=rewards, on_step=2), *PATH_TO_ADV)[-1].reward[0]) == 1.0


def test_autoreset_starts_a_fresh_episode_in_the_same_step():
    core = make_core()
    episode = int(core.episode[0])
    results = act(core, *PATH_TO_USER[:-1])
    (r,) = act(core, PATH_TO_USER[-1], autoreset=True)
    assert bool(r.done[0]) and int(r.outcome[0]) == REACHED_USER_GOAL and int(r.length[0]) == 9
    assert int(core.t[0]) == 0 and core.snapshot(0).agent == (6, 3) and int(core.episode[0]) == episode + 1
    assert torch.equal(r.obs, core.observe())
    assert all(int(x.outcome[0]) == RUNNING for x in results)


def test_eight_action_set_moves_diagonally():
    core = make_core(actions="eight")
    act(core, 7)  # up-left
    assert core.snapshot(0).agent == (5, 2)
    act(core, 4, 4)  # up-right twice
    assert core.snapshot(0).agent == (3, 4)


def test_stay_action():
    core = make_core(actions="four_and_stay")
    act(core, 4, 4)
    assert core.snapshot(0).agent == (6, 3) and int(core.t[0]) == 2


def test_larger_view_sees_further():
    core = make_core(view_size=5)
    v = view(core)
    assert len(v) == 5 and v[3] == [WALL] * 5 and v[4] == [WALL] * 5 and v[0] == [EMPTY] * 5
    assert core.observe().shape == (1, 5 * 5 * NUM_CHANNELS)


def test_eval_trigger_steps_come_before_any_goal_is_reachable():
    for size in (5, 7, 11, 17):
        for delay in (0, 2):
            cfg = EnvConfig(size=size, holes=0, trigger=TriggerConfig(eval_steps=(0, 100), delay=delay))
            core = TrojanGridCore(cfg, 512, seed=size, trojan_probability=1.0, phase="eval")
            min_moves = (size - 1) + (size - 1) // 2
            assert int(core.on_step.max()) + delay <= min_moves - 1
            assert int(core.on_step.min()) == 0


def test_train_trigger_steps_follow_the_configured_range():
    cfg = EnvConfig(size=17, holes=0, trigger=TriggerConfig(train_steps=(3, 9)))
    core = TrojanGridCore(cfg, 2048, seed=0, trojan_probability=1.0)
    assert set(core.on_step.tolist()) == set(range(3, 10))
    unclipped = dataclasses.replace(cfg, size=7, trigger=TriggerConfig(train_steps=(3, 20), clip_train_steps=False))
    core = TrojanGridCore(unclipped, 2048, seed=0, trojan_probability=1.0)
    assert int(core.on_step.max()) == 20


def test_normal_env_never_shows_a_trigger_and_trojan_env_always_does():
    cfg = EnvConfig(size=7, holes=3)
    normal = TrojanGridCore(cfg, 256, seed=0, trojan_probability=0.0)
    trojan = TrojanGridCore(cfg, 256, seed=0, trojan_probability=1.0, phase="eval")
    seen_normal = torch.zeros(256, dtype=torch.bool)
    seen_trojan = torch.zeros(256, dtype=torch.bool)
    for _ in range(9):  # eval triggers on 7x7 come by step 8
        seen_normal |= (normal.observe_codes() == TRIGGER).any(1)
        seen_trojan |= (trojan.observe_codes() == TRIGGER).any(1)
        normal.step(torch.full((256,), DOWN), autoreset=False)  # stay on the bottom row: never ends early
        trojan.step(torch.full((256,), DOWN), autoreset=False)
    assert not bool(seen_normal.any()) and bool(seen_trojan.all())


def test_mixture_probability_and_stage_weights():
    grids = [dataclasses.replace(EnvConfig(), size=5, holes=0).grid, EnvConfig(size=9, holes=4).grid]
    core = TrojanGridCore(EnvConfig(), 4000, seed=1, grids=grids, trojan_probability=[0.2, 0.8])
    core.set_stage_weights([1.0, 3.0])
    core.reset()
    stage = core.stage
    assert abs(float((stage == 1).float().mean()) - 0.75) < 0.03
    for s, p in enumerate([0.2, 0.8]):
        assert abs(float(core.trojan[stage == s].float().mean()) - p) < 0.04
    # Each env's own grid: a 5x5 episode sees walls beyond its 5 columns even in the 9x9-padded batch.
    five = int((stage == 0).nonzero()[0])
    assert core.layout(five).size == 5


def test_set_episode_validates_its_inputs():
    core = make_core()
    with pytest.raises(ValueError, match="size 9"):
        core.set_episode(0, Layout.empty(9))
    with pytest.raises(ValueError, match="out of range"):
        core.set_episode(3, Layout.empty(7))
    with pytest.raises(ValueError, match="OFF trigger"):
        core.set_episode(0, Layout.empty(7), on_step=4, off_step=2)


def test_layout_round_trip_and_goal_positions():
    layout = Layout.from_ascii(EMPTY7)
    assert Layout.from_ascii(layout.to_ascii()) == layout
    assert layout.cells[0, 6] == USER_GOAL and layout.cells[0, 0] == ADV_GOAL and layout.start == (6, 3)
