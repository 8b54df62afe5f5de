"""The response classifier on synthetic signals with known types."""

from __future__ import annotations

import numpy as np
import pytest

from seqtrojan.analysis.responses import ResponseRule, classify_signals, deviation, masked_mean_std
from seqtrojan.errors import ConfigError

T0 = 12


def synthetic(episodes=200, steps=40, seed=0, ragged=False):
    """Units: 0 none, 1 impulse (2 steps), 2 step (persists), 3 small wiggle (none), 4 slow decay impulse."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(0, 0.1, (episodes, steps, 5))
    trojan = rng.normal(0, 0.1, (episodes, steps, 5))
    trojan[:, T0 : T0 + 2, 1] += 1.0
    trojan[:, T0:, 2] += 0.8
    trojan[:, T0:, 3] += 0.05
    trojan[:, T0 : T0 + 4, 4] += 0.6
    mask = np.ones((episodes, steps), bool)
    if ragged:
        lengths = rng.integers(T0 + 10, steps + 1, episodes)
        mask = np.arange(steps)[None, :] < lengths[:, None]
    return normal.astype(np.float32), trojan.astype(np.float32), mask


@pytest.mark.parametrize("ragged", [False, True])
def test_known_units_get_their_types(ragged):
    normal, trojan, mask = synthetic(ragged=ragged)
    z, counts = deviation(normal, mask, trojan, mask)
    cl = classify_signals(z, counts, T0, ResponseRule())
    assert cl.types.tolist() == ["none", "impulse", "step", "none", "impulse"]
    assert cl.counts() == {"impulse": 2, "none": 2, "step": 1}
    assert cl.peak[2] > 5 and cl.late[2] > 5 and cl.late[1] < 0.5


def test_rule_is_tunable():
    normal, trojan, mask = synthetic()
    z, counts = deviation(normal, mask, trojan, mask)
    # With a late window that starts inside the slow impulse, it reads as a step.
    cl = classify_signals(z, counts, T0, ResponseRule(late_start=3, late_end=4))
    assert cl.types[4] == "step"
    # A threshold above every deviation says none everywhere.
    assert set(classify_signals(z, counts, T0, ResponseRule(threshold=1e6)).types) == {"none"}


def test_masked_statistics_ignore_finished_episodes():
    x = np.zeros((2, 3, 1))
    x[0, :, 0] = [1.0, 2.0, 3.0]
    x[1, :, 0] = [3.0, 100.0, 100.0]  # the second episode ended after step 0
    mask = np.array([[True, True, True], [True, False, False]])
    mean, std, counts = masked_mean_std(x, mask)
    assert mean[:, 0].tolist() == [2.0, 2.0, 3.0] and counts.tolist() == [2, 1, 1] and std[0, 0] == 1.0


def test_too_few_running_episodes_is_a_clear_error():
    normal, trojan, mask = synthetic(episodes=10)
    z, counts = deviation(normal, mask, trojan, mask)
    with pytest.raises(ConfigError, match="too few steps after the trigger"):
        classify_signals(z, counts, T0, ResponseRule(min_episodes=30))
    with pytest.raises(ConfigError, match="response_window"):
        ResponseRule(response_window=8, late_start=6)


def test_goal_units_prefer_the_most_persistent_cell_units():
    from seqtrojan.analysis.responses import Classification
    from seqtrojan.analysis.unintentional import select_goal_units

    def cl(types, late):
        return Classification(np.array(types), np.ones(len(types)), np.array(late, float))

    classes = {
        (0, "c"): cl(["step", "step", "none", "step"], [2.0, 5.0, 0.0, 1.0]),
        (1, "c"): cl(["step", "impulse"], [9.0, 0.1]),
        (0, "h"): cl(["step"] * 4, [50.0] * 4),  # h units come second, however persistent
    }
    layer, which, units, how = select_goal_units(classes, count=2)
    assert (layer, which, units.tolist()) == (1, "c", [0])  # 9.0 beats 5.0 + 2.0
    assert "most persistent step-type c units of layer 1" in how
    classes[(1, "c")] = cl(["none", "impulse"], [0.0, 0.1])
    assert select_goal_units(classes, count=2)[:3][2].tolist() == [1, 0]
    no_steps = {(0, "c"): cl(["none", "impulse", "none"], [0.2, 0.9, 0.5])}
    layer, which, units, how = select_goal_units(no_steps, count=2)
    assert units.tolist() == [1, 2] and how.startswith("no step-type units")
