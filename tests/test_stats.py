"""Intervals for reported rates: the ROC-AUC interval used for detection from a handful of models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from seqtrojan.errors import ConfigError
from seqtrojan.serde import to_dict
from seqtrojan.stats import OverSeeds, auc_interval, reaches


def hanley_mcneil(auc: float, m: int, n: int) -> tuple[float, float]:
    q1, q2 = auc / (2 - auc), 2 * auc * auc / (1 + auc)
    se = math.sqrt((auc * (1 - auc) + (m - 1) * (q1 - auc**2) + (n - 1) * (q2 - auc**2)) / (m * n))
    return auc - 1.959964 * se, auc + 1.959964 * se


def newcombe_variance(theta: float, m: int, n: int) -> float:
    n_star = (m + n) / 2 - 1
    return theta * (1 - theta) / (m * n) * (1 + n_star * ((1 - theta) / (2 - theta) + theta / (1 + theta)))


def test_auc_interval_contains_the_estimate_and_stays_open_at_the_edges():
    lo, hi = auc_interval(1.0, 8, 8)
    assert hi == 1.0 and 0.6 < lo < 0.9  # a perfect AUC from 16 models is far from certain
    lo, hi = auc_interval(0.0, 5, 5)
    assert lo == 0.0 and 0.2 < hi < 0.5
    for auc in (0.3, 0.5, 0.8, 0.95):  # each bound solves Newcombe's score equation (auc - t)^2 = z^2 var(t)
        for bound in auc_interval(auc, 10, 12):
            assert (auc - bound) ** 2 == pytest.approx(1.959964**2 * newcombe_variance(bound, 10, 12), rel=1e-6)
    assert sum(auc_interval(0.5, 8, 8)) == pytest.approx(1.0)  # symmetric about 0.5 with equal classes
    # more models, narrower; many models: close to the Hanley-McNeil interval
    widths = [np.subtract(*auc_interval(0.85, k, k)[::-1]) for k in (5, 20, 80)]
    assert widths[0] > widths[1] > widths[2]
    assert auc_interval(0.8, 400, 400) == pytest.approx(hanley_mcneil(0.8, 400, 400), abs=5e-3)


def test_auc_interval_covers_the_true_auc_about_95_percent_of_the_time():
    from sklearn.metrics import roc_auc_score

    rng = np.random.default_rng(0)
    shift, m, n, trials = 1.8, 10, 10, 400
    truth = 0.5 * math.erfc(-shift / 2)  # P(N(shift, 1) > N(0, 1)) = Phi(shift / sqrt(2))
    hits = 0
    for _ in range(trials):
        scores = np.r_[rng.normal(shift, 1, m), rng.normal(0, 1, n)]
        lo, hi = auc_interval(roc_auc_score([1] * m + [0] * n, scores), m, n)
        hits += lo <= truth <= hi
    assert 0.91 <= hits / trials <= 0.99


def test_auc_interval_refuses_bad_input():
    with pytest.raises(ConfigError, match="both classes, got 0 positives"):
        auc_interval(0.5, 0, 4)
    with pytest.raises(ConfigError, match=r"lies in \[0, 1\], got 1.5"):
        auc_interval(1.5, 4, 4)


def test_over_seeds_mean_sd_and_its_saved_form_checked_at_load():
    x = OverSeeds((0.9, 0.8, 1.0))
    assert x.mean == pytest.approx(0.9) and x.sd == pytest.approx(0.1) and x.seeds == 3
    assert x.text() == "0.900 ± 0.100" and OverSeeds((0.5,)).text() == "0.500" and OverSeeds((0.5,)).sd == 0.0
    assert OverSeeds.serde_load(to_dict(x), "at") == x
    with pytest.raises(ConfigError, match=r"at\.mean=0\.5 is not what its values give"):
        OverSeeds.serde_load({**to_dict(x), "mean": 0.5}, "at")
    with pytest.raises(ConfigError, match="exactly the keys mean, sd and values"):
        OverSeeds.serde_load({"values": [1.0]}, "at")
    with pytest.raises(ConfigError, match="at least one seed"):
        OverSeeds(())


def test_rates_over_seeds_pool_their_episodes():
    from seqtrojan.stats import Rate, over_seeds, pooled

    rates = [Rate(9, 10), Rate(1, 10), Rate(50, 100)]
    assert pooled(rates) == Rate(60, 120)
    values, pool = over_seeds(rates)
    assert values.values == (0.9, 0.1, 0.5) and pool == Rate(60, 120)


def test_a_rate_read_in_float32_reaches_the_threshold_it_equals():
    """90 of 100 episodes, averaged in float32 as a card's rates are, reads 0.8999999762: it reaches 0.9; 89 does
    not (a zoo's functional_at would otherwise drop a model whose backdoor works exactly at the threshold)."""
    ninety, eighty_nine = float(np.float32(90) / np.float32(100)), float(np.float32(89) / np.float32(100))
    assert ninety < 0.9 and reaches(ninety, 0.9)
    assert not reaches(eighty_nine, 0.9) and reaches(1.0, 0.9) and not reaches(0.0, 0.5)
