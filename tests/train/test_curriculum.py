"""Curriculum promotion and the stage mix."""

from __future__ import annotations

import torch

from seqtrojan.config import CurriculumConfig
from seqtrojan.train.curriculum import Curriculum, EpisodeCounts


def counts(stage: int, stages: int, normal=(0, 0), trojan=(0, 0)) -> EpisodeCounts:
    c = EpisodeCounts.zeros(stages)
    c.episodes[stage] = torch.tensor([normal[0], trojan[0]])
    c.successes[stage] = torch.tensor([normal[1], trojan[1]])
    return c


def test_promotes_only_with_enough_episodes_at_the_threshold():
    cur = Curriculum(CurriculumConfig(promote_at=0.9, min_episodes=100, window_updates=2), 3)
    assert not cur.update(counts(0, 3, normal=(60, 60)))  # 60 < 100 episodes
    assert cur.update(counts(0, 3, normal=(60, 50)))  # window: 120 episodes, 110/120 = 0.917
    assert cur.stage == 1
    assert not cur.update(counts(1, 3, normal=(200, 170)))  # 0.85 < 0.9
    assert not cur.update(counts(1, 3, normal=(200, 179)))  # window (400, 349): 0.8725
    assert cur.update(counts(1, 3, normal=(200, 199)))  # window drops the first: (400, 378) = 0.945
    assert cur.finished and not cur.update(counts(2, 3, normal=(1000, 1000)))


def test_backdoor_needs_both_env_types():
    cur = Curriculum(CurriculumConfig(promote_at=0.8, min_episodes=10, window_updates=1), 2, env_types=(0, 1))
    assert not cur.update(counts(0, 2, normal=(50, 50), trojan=(50, 30)))
    assert not cur.update(counts(0, 2, normal=(50, 50), trojan=(5, 5)))
    assert cur.update(counts(0, 2, normal=(50, 45), trojan=(50, 41)))


def test_earlier_stages_keep_their_share():
    cur = Curriculum(CurriculumConfig(previous_fraction=0.3), 4)
    assert cur.weights() == [1.0, 0.0, 0.0, 0.0]
    cur.stage = 3
    w = cur.weights()
    assert abs(sum(w) - 1.0) < 1e-12 and w[3] == 0.7 and abs(w[0] - 0.1) < 1e-12


def test_state_round_trip():
    cur = Curriculum(CurriculumConfig(window_updates=3), 3)
    cur.update(counts(0, 3, normal=(5, 1)))
    other = Curriculum(CurriculumConfig(window_updates=3), 3)
    other.load_state_dict(cur.state_dict())
    assert other.stage == cur.stage
    assert torch.equal(other.window_counts().episodes, cur.window_counts().episodes)
