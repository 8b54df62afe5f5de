"""Which new episodes are trojan-env episodes: the paper's Algorithm 1 and its cheaper variant.

Algorithm 1 (Yang et al. 2019): an episode uses Env_T when U(0,1) > 0.5 + (P_t - P_c), where P_c and P_t are the
agent's success rates in the normal and the trojan env, re-measured after each policy update. So

    P(trojan) = clip(0.5 - (P_t - P_c), 0, 1)

and the env the agent is worse at is sampled more often. ``exact`` measures P_c and P_t by evaluating the agent
after each update; ``running`` uses the success rates of the update's own rollout episodes (no extra episodes);
``fixed`` uses a constant probability. Each rule is registered in :data:`MIXING_RULES` by its ``backdoor.mixing``
name; a new one is a :class:`MixingRule` (a function ``(P_c, P_t, config) -> P(trojan)`` and whether the trainer
evaluates the agent after each update to measure P_c and P_t) and one registration line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from seqtrojan.config import BackdoorConfig
from seqtrojan.registry import Registry


@dataclass(frozen=True)
class MixingRule:
    """How P(trojan) of a stage's new episodes follows from P_c and P_t."""

    probability: Callable[[float, float, BackdoorConfig], float]
    """(P_c, P_t, the backdoor config) -> the probability that a new episode of the stage is a trojan-env episode"""
    evaluates: bool = False
    """measure P_c and P_t by evaluating the agent on the newest stage after each update (``backdoor.eval_episodes``
    per env type) rather than only from the update's own rollout episodes"""


MIXING_RULES: Registry[MixingRule] = Registry("attack", "mixing")
"""The rules ``backdoor.mixing`` names."""


def trojan_probability(p_clean: float, p_trojan: float, bounds: tuple[float, float] = (0.0, 1.0)) -> float:
    """P(U > 0.5 + (P_t - P_c)) for U ~ U(0, 1), clipped to ``bounds``."""
    p = min(1.0, max(0.0, 0.5 - (p_trojan - p_clean)))
    return min(bounds[1], max(bounds[0], p))


def _algorithm_1(p_clean: float, p_trojan: float, config: BackdoorConfig) -> float:
    return trojan_probability(p_clean, p_trojan, config.probability_bounds)


def _fixed(p_clean: float, p_trojan: float, config: BackdoorConfig) -> float:
    return config.fixed_probability


MIXING_RULES.register(
    "exact", "Algorithm 1, P_c and P_t re-measured by evaluation after each update", MixingRule(_algorithm_1, True)
)
MIXING_RULES.register(
    "running", "Algorithm 1, P_c and P_t from the update's own rollout episodes", MixingRule(_algorithm_1)
)
MIXING_RULES.register("fixed", "a constant trojan-episode probability (backdoor.fixed_probability)", MixingRule(_fixed))


class TrojanMixer:
    """Holds P_c and P_t per grid stage and turns them into per-stage trojan probabilities."""

    def __init__(self, config: BackdoorConfig, num_stages: int) -> None:
        self.config = config
        self.rule = MIXING_RULES.get(config.mixing)
        self.p_clean = [0.0] * num_stages
        self.p_trojan = [0.0] * num_stages  # Algorithm 1 initialises both to 0: P(trojan) starts at 0.5

    def probabilities(self) -> list[float]:
        if not self.config.enabled:
            return [0.0] * len(self.p_clean)
        return [self.rule.probability(c, t, self.config) for c, t in zip(self.p_clean, self.p_trojan)]

    def observe(self, stage: int, p_clean: float | None, p_trojan: float | None) -> None:
        """Record freshly measured success rates (None leaves the previous value)."""
        if p_clean is not None:
            self.p_clean[stage] = p_clean
        if p_trojan is not None:
            self.p_trojan[stage] = p_trojan

    def state_dict(self) -> dict:
        return {"p_clean": list(self.p_clean), "p_trojan": list(self.p_trojan)}

    def load_state_dict(self, state: dict) -> None:
        self.p_clean = [float(x) for x in state["p_clean"]]
        self.p_trojan = [float(x) for x in state["p_trojan"]]
