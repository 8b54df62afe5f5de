"""The early-stopping rule (:class:`seqtrojan.config.StopConfig`): stop once the last curriculum stage is learned,
as seen in a streak of updates and confirmed on fresh episodes."""

from __future__ import annotations

from typing import Any

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.evaluation.batched import evaluate_on_env


class StopRule:
    """Counts the updates in a row that meet the target on the last stage; at ``stop.updates`` of them, checks on
    fresh episodes. :meth:`after_update` says whether to stop."""

    def __init__(self, cfg: ExperimentConfig, device: torch.device) -> None:
        self.cfg = cfg
        self.device = device
        self.kinds = ("normal", "trojan") if cfg.backdoor.enabled else ("normal",)
        self.streak = 0
        self.checks = 0
        """held-out checks run so far (each uses fresh episodes: its seed depends on this count)"""
        self.confirmed: dict[str, float] = {}
        """the passing check's success per env type"""

    @staticmethod
    def applies(cfg: ExperimentConfig) -> bool:
        """Whether ``cfg``'s run may stop early: ``stop.enabled``, unless its attack follows a schedule over the whole
        budget (the weight camouflage's warm-up: the backdoor is planted, then hidden; a stop once it works would
        cut the hiding short), which then trains every step."""
        scheduled = cfg.backdoor.enabled and cfg.attack.weight_camouflage.enabled
        return cfg.stop.enabled and not (scheduled and cfg.attack.weight_camouflage.warmup_steps > 0)

    def _meets_target(self, scalars: dict[str, Any], stage: int) -> bool:
        stop = self.cfg.stop
        for kind in self.kinds:
            n = scalars.get(f"stages/{stage}/{kind}_count", 0)
            rate = scalars.get(f"stages/{stage}/{kind}_success", 0.0)
            if n < stop.min_episodes or rate < stop.success:
                return False
        return True

    def after_update(self, scalars: dict[str, Any], stage: int, agent: RecurrentActorCritic) -> bool:
        """Whether to stop after this update (``stage``: the curriculum's current stage)."""
        last = self.cfg.num_stages - 1  # the curriculum's last grid, or the one stage of a Gymnasium env
        if stage != last or not self._meets_target(scalars, last):
            self.streak = 0
            return False
        self.streak += 1
        if self.streak < self.cfg.stop.updates:
            return False
        self.streak = 0
        self.checks += 1
        rates = {kind: self._held_out(agent, kind == "trojan") for kind in self.kinds}
        if all(rate >= self.cfg.stop.success for rate in rates.values()):
            self.confirmed = rates
            return True
        return False

    def _held_out(self, agent: RecurrentActorCritic, trojan: bool) -> float:
        seed = (self.cfg.run.seed << 32) + 7_777_777 + self.checks  # not the final evaluation's episodes
        was_training = agent.training
        batch = evaluate_on_env(  # the last grid's episodes, or the Gymnasium env's
            agent, self.cfg, trojan=trojan, episodes=self.cfg.stop.confirm_episodes, seed=seed, device=self.device
        )
        agent.train(was_training)
        return batch.success_rate
