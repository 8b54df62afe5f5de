"""The matrix's cells from agents' measurements (no training): pooling, spread over seeds, AUC, bad names."""

from __future__ import annotations

import pytest

from seqtrojan.errors import ConfigError
from seqtrojan.experiment_results import AgentMeasurement, MitigationOutcome, OnlineArm
from seqtrojan.experiments.matrix import MatrixConfig, assemble, roc_auc
from seqtrojan.stats import Rate, auc_interval


def measured(attack: str, seed: int, success: int, detected: int, score: float) -> AgentMeasurement:
    arm = OnlineArm(Rate(1, 100), Rate(detected, 100), Rate(success // 2, 100), Rate(90, 100))
    return AgentMeasurement(
        agent=f"{attack}_s{seed}", attack=attack, seed=seed, grid="7x7/3", clean_success=Rate(95, 100),
        attack_success=Rate(success, 100), unintentional=Rate(seed, 100), natural_trigger=Rate(0, 100),
        online={"state_monitor": arm},
        mitigation={"fine_tuned": MitigationOutcome(Rate(96, 100), Rate(10 * seed, 100))},
        offline_scores={"weight_detector": score},
    )  # fmt: skip


def test_cells_pool_the_seeds_and_spread_over_them():
    cfg = MatrixConfig(attacks=("dedicated_code",), online=("state_monitor",), offline=("weight_detector",))
    agents = [measured("dedicated_code", s, 90 + 4 * s, 80 + 10 * s, 0.6 + 0.1 * s) for s in range(3)]
    agents += [measured("clean", s, 0, 0, 0.1 * s + 0.55) for s in range(3)]  # scores 0.55, 0.65, 0.75
    result = assemble(cfg, agents, "test")
    (summary,) = result.attacks
    assert summary.seeds == (0, 1, 2) and summary.attack_success.values == (0.90, 0.94, 0.98)
    assert summary.attack_success_pooled == Rate(282, 300) and summary.attack_success.sd == pytest.approx(0.04)
    assert summary.unintentional_pooled == Rate(3, 300) and summary.natural_trigger == Rate(0, 300)
    online = next(c for c in result.cells if c.defense == "state_monitor")
    assert online.detection_pooled == Rate(270, 300) and online.detection.mean == pytest.approx(0.9)
    assert online.attack_success_pooled == Rate(45 + 47 + 49, 300) and online.false_alarm_pooled == Rate(3, 300)
    tuned = next(c for c in result.cells if c.defense == "fine_tuned")
    assert tuned.kind == "mitigation" and tuned.attack_success.values == (0.0, 0.1, 0.2) and tuned.detection is None
    offline = next(c for c in result.cells if c.kind == "offline")
    # positives 0.6, 0.7, 0.8 against negatives 0.55, 0.65, 0.75: 6 of 9 pairs ordered right
    assert offline.auc == pytest.approx(6 / 9) and offline.auc_interval == auc_interval(6 / 9, 3, 3)


def test_roc_auc_counts_ties_half():
    assert roc_auc([1.0, 2.0], [0.0, 0.5]) == 1.0
    assert roc_auc([0.0], [1.0]) == 0.0
    assert roc_auc([1.0, 1.0], [1.0, 0.0]) == pytest.approx(0.75)


def test_unknown_names_and_bad_sizes_are_refused_with_the_known_ones():
    with pytest.raises(ConfigError, match=r"unknown attack 'nope'; known: dedicated_code"):
        MatrixConfig(attacks=("nope",))
    with pytest.raises(ConfigError, match=r"unknown monitor 'nope'; known: state_monitor"):
        MatrixConfig(online=("nope",))
    with pytest.raises(ConfigError, match=r"matrix\.seeds"):
        MatrixConfig(seeds=0)
    with pytest.raises(ConfigError, match=r"matrix\.attacks is empty"):
        MatrixConfig(attacks=())
