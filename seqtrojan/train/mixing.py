"""Which new episodes are trojan-env episodes: the paper's Algorithm 1 and its cheaper variant.

Algorithm 1 (Yang et al. 2019): an episode uses Env_T when U(0,1) > 0.5 + (P_t - P_c), where P_c and P_t are the
agent's success rates in the normal and the trojan env, re-measured after each policy update. So

    P(trojan) = clip(0.5 - (P_t - P_c), 0, 1)

and the env the agent is worse at is sampled more often. ``exact`` measures P_c and P_t by evaluating the agent
after each update; ``running`` uses the success rates of the update's own rollout episodes (no extra episodes).
"""

from __future__ import annotations

from seqtrojan.config import BackdoorConfig


def trojan_probability(p_clean: float, p_trojan: float, bounds: tuple[float, float] = (0.0, 1.0)) -> float:
    """P(U > 0.5 + (P_t - P_c)) for U ~ U(0, 1), clipped to ``bounds``."""
    p = min(1.0, max(0.0, 0.5 - (p_trojan - p_clean)))
    return min(bounds[1], max(bounds[0], p))


class TrojanMixer:
    """Holds P_c and P_t per grid stage and turns them into per-stage trojan probabilities."""

    def __init__(self, config: BackdoorConfig, num_stages: int) -> None:
        self.config = config
        self.p_clean = [0.0] * num_stages
        self.p_trojan = [0.0] * num_stages  # Algorithm 1 initialises both to 0: P(trojan) starts at 0.5

    def probabilities(self) -> list[float]:
        if not self.config.enabled:
            return [0.0] * len(self.p_clean)
        if self.config.mixing == "fixed":
            return [self.config.fixed_probability] * len(self.p_clean)
        return [trojan_probability(c, t, self.config.probability_bounds) for c, t in zip(self.p_clean, self.p_trojan)]

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
