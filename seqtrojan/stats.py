"""Small statistics helpers used wherever a rate is reported, and :class:`Rate`, the one type for a rate."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

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


@dataclass(frozen=True)
class Rate:
    """``k`` events out of ``n`` trials: a rate that keeps its counts, with its 95% Wilson interval.

    Every rate of a stage's results is one (success, switch, alarm, activation, recall ...). It is saved as
    ``{"k", "n", "rate", "ci95"}`` (:meth:`serde_dump`): the counts, and the rate and interval they give, for a
    reader of the JSON; loading (:meth:`serde_load`, through :func:`seqtrojan.serde.from_dict`) checks that the
    two agree. A rate over no trials is 0.0 with the interval [0, 1] (nothing measured).
    """

    k: int
    n: int

    def __post_init__(self) -> None:
        for name in ("k", "n"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"a rate's {name} must be an integer, got {value!r}")
        if not 0 <= self.k <= self.n:
            raise ConfigError(f"a rate needs 0 <= k <= n, got k={self.k}, n={self.n}")

    @property
    def value(self) -> float:
        return self.k / self.n if self.n else 0.0

    @property
    def interval(self) -> tuple[float, float]:
        """The 95% Wilson interval (:func:`wilson_interval`)."""
        return wilson_interval(self.k, self.n)

    def text(self, digits: int = 3) -> str:
        """``'0.125 [0.050, 0.281]'``: the rate and its 95% interval."""
        low, high = self.interval
        return f"{self.value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"

    def __str__(self) -> str:
        return self.text()

    def serde_dump(self) -> dict[str, Any]:
        return {"k": self.k, "n": self.n, "rate": self.value, "ci95": list(self.interval)}

    @classmethod
    def serde_load(cls, data: Any, path: str) -> Rate:
        """The :meth:`serde_dump` form back; a missing or unknown key, a count that is not an integer, or a rate or
        interval that its counts do not give is a ConfigError naming ``path``."""
        where = path or "rate"
        if not isinstance(data, dict):
            raise ConfigError(f"{where} must be a mapping with k, n, rate and ci95, got {type(data).__name__}")
        keys = {"k", "n", "rate", "ci95"}
        missing, unknown = sorted(keys - set(data)), sorted(set(data) - keys)
        if missing or unknown:
            problems = []
            if missing:
                problems.append(f"missing key(s) {missing}")
            if unknown:
                problems.append(f"unknown key(s) {unknown}")
            raise ConfigError(f"{where}: {' and '.join(problems)}; a rate has the keys ['ci95', 'k', 'n', 'rate']")
        for name in ("k", "n"):
            if isinstance(data[name], bool) or not isinstance(data[name], int):
                raise ConfigError(f"{where}.{name} must be an integer, got {data[name]!r}")
        try:
            rate = cls(data["k"], data["n"])
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None
        ci = data["ci95"]
        if not _close(data["rate"], rate.value):
            raise ConfigError(f"{where}.rate={data['rate']!r} is not k/n = {rate.k}/{rate.n}")
        if not (isinstance(ci, list) and len(ci) == 2 and all(_close(a, b) for a, b in zip(ci, rate.interval))):
            raise ConfigError(f"{where}.ci95={ci!r} is not the Wilson interval of {rate.k}/{rate.n}")
        return rate


def _close(value: Any, expected: float) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return math.isclose(value, expected, rel_tol=1e-9, abs_tol=1e-12)


@dataclass(frozen=True)
class OverSeeds:
    """One figure measured once per training seed: each seed's value, their mean and sample standard deviation."""

    values: tuple[float, ...]
    """one per training seed, in seed order"""

    def __post_init__(self) -> None:
        if not self.values:
            raise ConfigError("a figure over seeds needs at least one seed's value")

    @property
    def seeds(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float:
        return sum(self.values) / len(self.values)

    @property
    def sd(self) -> float:
        """Sample standard deviation (ddof=1); 0.0 for one seed, where no spread can be measured."""
        n = len(self.values)
        if n < 2:
            return 0.0
        mean = self.mean
        return math.sqrt(sum((v - mean) ** 2 for v in self.values) / (n - 1))

    def text(self, digits: int = 3) -> str:
        """``'0.912 ± 0.031'`` (no spread claimed for one seed)."""
        return f"{self.mean:.{digits}f}" + (f" ± {self.sd:.{digits}f}" if self.seeds > 1 else "")

    def serde_dump(self) -> dict[str, Any]:
        return {"mean": self.mean, "sd": self.sd, "values": list(self.values)}

    @classmethod
    def serde_load(cls, data: Any, path: str) -> OverSeeds:
        """The :meth:`serde_dump` form back; mean and sd must be what the values give."""
        where = path or "over_seeds"
        if not isinstance(data, dict) or set(data) != {"mean", "sd", "values"}:
            raise ConfigError(f"{where} must be a mapping with exactly the keys mean, sd and values")
        values = data["values"]
        if not isinstance(values, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in values
        ):
            raise ConfigError(f"{where}.values must be a list of numbers")
        try:
            summary = cls(tuple(float(v) for v in values))
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None
        for name in ("mean", "sd"):
            if not _close(data[name], getattr(summary, name)):
                raise ConfigError(f"{where}.{name}={data[name]!r} is not what its values give")
        return summary


def pooled(rates: Sequence[Rate]) -> Rate:
    """One rate per training seed pooled into one: every seed's episodes together (its interval covers the episode
    sampling, not the spread between seeds)."""
    return Rate(sum(r.k for r in rates), sum(r.n for r in rates))


def over_seeds(rates: Sequence[Rate]) -> tuple[OverSeeds, Rate]:
    """One rate per training seed as the matrix shows it: the values over seeds, and the pooled rate."""
    return OverSeeds(tuple(r.value for r in rates)), pooled(rates)


@dataclass(frozen=True)
class Mean:
    """The mean of ``n`` independent measurements (e.g. one per episode: a return), with their sample standard
    deviation and the 95% normal-approximation interval of the mean (mean ± 1.96 sd / sqrt(n))."""

    mean: float
    sd: float
    n: int

    @classmethod
    def of(cls, values: Any) -> Mean:
        """The mean of ``values`` (a sequence, array or tensor of numbers; at least one)."""
        data = [float(v) for v in (values.tolist() if hasattr(values, "tolist") else values)]
        if not data:
            raise ConfigError("a mean needs at least one value")
        n = len(data)
        mean = sum(data) / n
        sd = math.sqrt(sum((v - mean) ** 2 for v in data) / (n - 1)) if n > 1 else 0.0
        return cls(mean, sd, n)

    @property
    def interval(self) -> tuple[float, float]:
        half = _z(0.95) * self.sd / math.sqrt(self.n) if self.n > 0 else math.inf
        return self.mean - half, self.mean + half

    def text(self, digits: int = 3) -> str:
        """``'0.412 [0.380, 0.444]'``: the mean and its 95% interval."""
        low, high = self.interval
        return f"{self.mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"

    def serde_dump(self) -> dict[str, Any]:
        return {"mean": self.mean, "sd": self.sd, "n": self.n, "ci95": list(self.interval)}

    @classmethod
    def serde_load(cls, data: Any, path: str) -> Mean:
        where = path or "mean"
        if not isinstance(data, dict) or set(data) != {"mean", "sd", "n", "ci95"}:
            raise ConfigError(f"{where} must be a mapping with exactly the keys mean, sd, n and ci95")
        numbers = [data["mean"], data["sd"]]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers):
            raise ConfigError(f"{where}.mean and .sd must be finite numbers")
        if isinstance(data["n"], bool) or not isinstance(data["n"], int) or data["n"] < 1 or data["sd"] < 0:
            raise ConfigError(f"{where}.n must be an integer >= 1 and .sd >= 0")
        return cls(float(data["mean"]), float(data["sd"]), data["n"])


RATE_TOLERANCE = 1e-6
"""how far below a threshold a success rate may read and still reach it: the rates are float32 means (90 of 100
episodes reads 0.8999999762), and a threshold of 0.9 means 90 of 100"""


def reaches(success: float, threshold: float) -> bool:
    """Whether a success rate (a card's float32 mean) reaches ``threshold`` (``functional_at``)."""
    return success >= threshold - RATE_TOLERANCE
