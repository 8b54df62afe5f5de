"""Success rates over several training seeds: mean, spread, each seed's value, and an interval for the mean.

A headline number from one training run is one sample of the experiment: retraining the same preset with another
seed (or the same seed at another thread count, see docs/results.md) moves the 17x17/30 trojan success by several
points. So the reproduction trains its headline agents with several seeds, evaluates each, and reports

* ``mean`` and ``sd`` (sample standard deviation, ``ddof=1``) of the per-seed success rates,
* each seed's rate and its 95% Wilson interval (``rows``),
* a 95% t-interval for the mean over seeds (the episodes' sampling noise is inside each seed's rate),
* ``differs``: the paper's value lies outside every seed's Wilson interval (it is one training run as well, so
  it is compared with what one of our runs gives, not with our mean).

With a single seed the summary is that seed's rate with its Wilson interval, and no spread is claimed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from scipy.stats import t as student_t

from seqtrojan.evaluation.results import SweepRow


@dataclass(frozen=True)
class SeedSummary:
    """One (agent role, env, grid) cell over the training seeds that were evaluated in it."""

    agent: str
    label: str
    env: str
    size: int
    holes: int
    rows: tuple[SweepRow, ...]  # one per seed, in seed order
    paper: float | None

    @property
    def config(self) -> str:
        return f"{self.size}x{self.size}/{self.holes}"

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(r.seed for r in self.rows)

    @property
    def successes(self) -> tuple[float, ...]:
        return tuple(r.success.value for r in self.rows)

    @property
    def mean(self) -> float:
        return sum(self.successes) / len(self.rows)

    @property
    def sd(self) -> float:
        """Sample standard deviation over seeds (0.0 for one seed, where no spread can be measured)."""
        n = len(self.rows)
        if n < 2:
            return 0.0
        m = self.mean
        return math.sqrt(sum((s - m) ** 2 for s in self.successes) / (n - 1))

    @property
    def interval(self) -> tuple[float, float]:
        """95% interval: the Wilson interval for one seed, a t-interval for the mean over several (in [0, 1])."""
        n = len(self.rows)
        if n == 1:
            return self.rows[0].success.interval
        half = float(student_t.ppf(0.975, n - 1)) * self.sd / math.sqrt(n)
        return max(0.0, self.mean - half), min(1.0, self.mean + half)

    @property
    def differs(self) -> bool:
        """The paper's value lies outside every seed's 95% Wilson interval."""
        if self.paper is None:
            return False
        paper = self.paper
        return not any(r.success.interval[0] <= paper <= r.success.interval[1] for r in self.rows)

    def to_dict(self) -> dict[str, object]:
        low, high = self.interval
        return {
            "agent": self.agent,
            "label": self.label,
            "env": self.env,
            "config": self.config,
            "seeds": list(self.seeds),
            "success": list(self.successes),
            "mean": self.mean,
            "sd": self.sd,
            "mean_ci95": [low, high],
            "episodes_per_seed": self.rows[0].episodes,
            "paper": self.paper,
            "paper_outside_every_seed_interval": self.differs,
        }


def summarise_over_seeds(rows: Sequence[SweepRow]) -> list[SeedSummary]:
    """Group sweep rows by (agent, env, grid) in first-seen order; a seed evaluated twice in a cell is an error."""
    groups: dict[tuple[str, str, int, int], list[SweepRow]] = {}
    for row in rows:
        groups.setdefault((row.agent, row.env, row.size, row.holes), []).append(row)
    out = []
    for (agent, env, size, holes), members in groups.items():
        members.sort(key=lambda r: r.seed)
        seeds = [r.seed for r in members]
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"seed evaluated twice for {agent}/{env} on {size}x{size}/{holes}: {seeds}")
        out.append(SeedSummary(agent, members[0].label, env, size, holes, tuple(members), members[0].paper))
    return out


def find_summary(summaries: Sequence[SeedSummary], agent: str, env: str, config: str) -> SeedSummary | None:
    return next((s for s in summaries if s.agent == agent and s.env == env and s.config == config), None)
