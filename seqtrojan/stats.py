"""Small statistics helpers used wherever a rate is reported."""

from __future__ import annotations

import math

from seqtrojan.errors import ConfigError


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (well behaved at 0 and 1, unlike the normal interval)."""
    if trials <= 0:
        return (0.0, 1.0)
    z = _z(confidence)
    p = successes / trials
    denom = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def _z(confidence: float) -> float:
    """Two-sided standard-normal quantile, by bisection on erf (no SciPy needed)."""
    target = confidence
    lo, hi = 0.0, 10.0
    for _ in range(100):
        mid = (lo + hi) / 2
        if math.erf(mid / math.sqrt(2)) < target:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


def auc_interval(auc: float, positives: int, negatives: int, confidence: float = 0.95) -> tuple[float, float]:
    """Confidence interval for a ROC-AUC from ``positives`` and ``negatives`` scored items.

    Newcombe's (2006) score-type interval (his method 5): the Hanley-McNeil (1982) variance of an AUC evaluated
    at the candidate value ``theta`` rather than at the estimate, with both ``n - 1`` terms replaced by
    ``(positives + negatives) / 2 - 1``; the interval is every ``theta`` with ``(auc - theta)^2 <= z^2 var(theta)``.
    Like Wilson's interval for a proportion, it stays inside [0, 1] and does not collapse to a point at an AUC of
    0 or 1, which a handful of models reach easily.
    """
    if positives < 1 or negatives < 1:
        raise ConfigError(f"an AUC needs both classes, got {positives} positives and {negatives} negatives")
    if not 0.0 <= auc <= 1.0:
        raise ConfigError(f"an AUC lies in [0, 1], got {auc}")
    z2 = _z(confidence) ** 2
    n_star = (positives + negatives) / 2 - 1

    def outside(theta: float) -> bool:  # theta lies outside the interval
        var = theta * (1 - theta) / (positives * negatives)
        var *= 1 + n_star * ((1 - theta) / (2 - theta) + theta / (1 + theta))
        return (auc - theta) ** 2 > z2 * var

    def bound(far: float) -> float:  # bisection between a point outside (far) and the estimate (inside)
        out, inside = far, auc
        if not outside(out):
            return far
        for _ in range(100):
            mid = (out + inside) / 2
            out, inside = (mid, inside) if outside(mid) else (out, mid)
        return inside

    return (bound(0.0), bound(1.0))
