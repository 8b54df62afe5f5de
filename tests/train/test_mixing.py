"""Algorithm 1: the trojan-episode probability, its clipping, and that the env samples episodes by it."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.config import BackdoorConfig
from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.train.mixing import TrojanMixer, trojan_probability


@pytest.mark.parametrize(
    ("p_c", "p_t", "expected"),
    [(0.0, 0.0, 0.5), (0.9, 0.5, 0.9), (0.5, 0.9, 0.1), (1.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.2, 0.9, 0.0)],
)
def test_probability_is_p_of_u_above_half_plus_gap(p_c, p_t, expected):
    assert trojan_probability(p_c, p_t) == pytest.approx(expected)
    # the same number, from the algorithm's own sampling rule: U(0,1) > 0.5 + (P_t - P_c)
    u = torch.rand(200_000, generator=torch.Generator().manual_seed(0))
    assert float((u > 0.5 + (p_t - p_c)).float().mean()) == pytest.approx(expected, abs=0.005)


def test_bounds_clip_the_probability():
    assert trojan_probability(1.0, 0.0, bounds=(0.1, 0.8)) == 0.8
    assert trojan_probability(0.0, 1.0, bounds=(0.1, 0.8)) == 0.1


def test_mixer_modes():
    mixer = TrojanMixer(BackdoorConfig(enabled=True, mixing="running"), num_stages=2)
    assert mixer.probabilities() == [0.5, 0.5]
    mixer.observe(1, 0.9, 0.3)
    mixer.observe(0, None, 0.7)
    assert mixer.probabilities() == pytest.approx([0.0, 1.0])  # 0.5 - (0.7 - 0) < 0; 0.5 - (0.3 - 0.9) > 1
    assert TrojanMixer(BackdoorConfig(enabled=False), 2).probabilities() == [0.0, 0.0]
    assert TrojanMixer(BackdoorConfig(enabled=True, mixing="fixed", fixed_probability=0.3), 1).probabilities() == [0.3]


def test_env_draws_trojan_episodes_at_the_set_probability():
    core = TrojanGridCore(EnvConfig(size=5, holes=0), 20_000, seed=3, trojan_probability=0.3)
    assert float(core.trojan.float().mean()) == pytest.approx(0.3, abs=0.01)
    core.set_trojan_probability(trojan_probability(p_clean=0.8, p_trojan=0.4))  # 0.9
    core.reset()
    assert float(core.trojan.float().mean()) == pytest.approx(0.9, abs=0.01)
