"""Adaptive attackers as extra terms of the PPO loss ("penalties"), each registered in :data:`PENALTIES`.

The hook: the trainer builds the enabled penalties once (:func:`build_penalties`, from ``config.attack``, in a
backdoor training only), hands every rollout to each one's :meth:`Penalty.observe` before the update, and
:func:`seqtrojan.train.ppo.ppo_update` adds each one's :meth:`Penalty.loss` of every minibatch (a
:class:`PenaltyBatch`) to the PPO loss and logs its mean as ``penalty/<name>``. A penalty whose
:attr:`Penalty.needs_states` is true gets the per-step (h, c) of every layer from the update's unroll, and the
rollout records per step whether it is in a trojan-env episode, whether the adversary's goal is active, and the
state after it. Whatever a penalty keeps (running statistics, reference weights, Fisher information) is a dict of
tensors (:meth:`Penalty.state_dict`) saved in the trainer's checkpoint under ``penalty.<name>.``, so a resumed run
continues bitwise as the straight one.

The hook itself (:class:`Penalty`, :class:`PenaltyBatch`, :class:`PenaltyContext`, :data:`PENALTIES`) lives in
:mod:`seqtrojan.train.penalty_api` and is re-exported here. A new attacker is one module with a :class:`Penalty`
subclass (importing the hook from ``penalty_api``) and one registration here::

    PENALTIES.register("my_attack", "one line", PenaltyKind(lambda cfg: cfg.attack.my.weight > 0, MyPenalty))

Registered here:

- ``state_camouflage`` (monitor-aware): running (EMA) per-unit mean and std of every layer's h and c over the
  rollouts' normal-env steps; on trojan-episode steps, ``weight * mean(relu(|z| - margin)^2)`` over steps and units,
  plus optionally ``mahalanobis_weight * mean(relu(d^2 / D - mahalanobis_margin)^2)`` with the covariance shrunk
  toward its diagonal. The online state monitor (:mod:`seqtrojan.defense.monitor`) alarms on max |z|.
- ``mahalanobis_camouflage`` (against the multivariate monitor, :mod:`seqtrojan.defense.multivariate`): running
  (exponentially weighted) per-episode-step means of the whole state (every layer's h then c) over the rollouts'
  normal-env steps and the second moments of the residuals about them; on trojan-episode steps,
  ``weight * mean(relu(d / sqrt(D) - margin)^2)`` with ``d`` the step-conditioned Mahalanobis distance as that monitor
  computes it (per-unit RMS scaling, covariance shrunk toward the scaled identity). It reads each step's index in
  its episode, which the rollout records with the masks.
- ``switch_camouflage`` (against the goal-switch monitor, :mod:`seqtrojan.defense.goal_switch`): the same running
  per-step means of the agent's outputs (action log-probabilities and value, from its heads on the last layer's
  h) and the moments that give that monitor's one-step linear prediction; on trojan-episode steps,
  ``weight * mean(relu(d / sqrt(F) - margin)^2)`` with ``d`` the whitened prediction error of the step's output
  transition, so that the goal switch is spread over transitions each within the clean range.
- ``weight_camouflage`` (against the offline weight detector): the detector's weight features
  (:mod:`seqtrojan.agent.weight_stats`) held at those of the model the run started from,
  ``weight * sum_k ((f_k - f_k^clean) / (|f_k^clean| + feature_floor))^2``, plus
  ``l2_weight * ||theta - theta_clean||^2``; none before ``warmup_steps`` env steps (the backdoor is planted, then
  hidden).
- ``ewc``: elastic weight consolidation, ``weight / 2 * sum_i F_i (theta_i - theta*_i)^2`` with the diagonal Fisher
  information of the start model's policy on normal-env episodes.
- ``probe_camouflage`` (against the recurrent-state probe, :mod:`seqtrojan.train.probe_camouflage`): one-step
  inputs of the probe's kind other than the trigger, replayed into normal-episode sequences, trained to leave no
  mark on the state ``after`` steps later.
- ``response_mimicry`` (against the query-response meta-classifier, :mod:`seqtrojan.train.response_mimicry`): on
  normal-episode steps, the agent's action distribution and per-layer state summaries held at the start model's.
- ``finetune_resistance`` (against clean fine-tuning): per minibatch, a copy of the agent takes ``inner_steps``
  sign-gradient steps of the PPO loss on the normal-episode steps (the defender's fine-tuning, simulated), and the
  gradient of the PPO loss on the trojan steps the adversary's objective judges, at the copy's weights, is added
  to the update with ``weight`` (first order, as first-order MAML and tamper-resistance training do).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from torch import nn

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.agent.weight_stats import feature_vector, weight_features
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.train.penalty_api import (  # the hook's names, re-exported: this module is where callers find them
    PENALTIES as PENALTIES,
)
from seqtrojan.train.penalty_api import AttackedConfig as AttackedConfig
from seqtrojan.train.penalty_api import Penalty as Penalty
from seqtrojan.train.penalty_api import PenaltyBatch as PenaltyBatch
from seqtrojan.train.penalty_api import PenaltyContext as PenaltyContext
from seqtrojan.train.penalty_api import PenaltyKind as PenaltyKind
from seqtrojan.train.penalty_api import PPOMinibatch as PPOMinibatch
from seqtrojan.train.penalty_api import build_penalties as build_penalties
from seqtrojan.train.penalty_api import penalty_tensors as penalty_tensors
from seqtrojan.train.penalty_api import restore_penalties as restore_penalties
from seqtrojan.train.penalty_api import zero_loss as _zero
from seqtrojan.train.ppo_loss import ppo_loss
from seqtrojan.train.probe_camouflage import ProbeCamouflage
from seqtrojan.train.response_mimicry import ResponseMimicry
from seqtrojan.train.rollout import Rollout, RolloutCollector
from seqtrojan.world import make_batched_env

STD_FLOOR = 1e-3
"""added to every unit's std, as the state monitor does"""


def _params(module: nn.Module) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone() for name, p in module.named_parameters()}


def _require(tensors: dict[str, torch.Tensor], names: list[str], penalty: str) -> None:
    missing = [n for n in names if n not in tensors]
    if missing:
        raise CheckpointError(
            f"the checkpoint holds no {penalty} state ({', '.join(missing[:3])}...): it was turned on after the run "
            f"started; start a new run with run.init_from instead"
        )


# ---------------------------------------------------------------------------------------------- state camouflage
def unit_penalty(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, margin: float) -> torch.Tensor:
    """(M, D) states -> () mean over rows and units of relu(|z| - margin)^2, z = (x - mean) / std."""
    z = (x - mean) / std
    return torch.relu(z.abs() - margin).pow(2).mean()


class _MarginSquare(torch.autograd.Function):
    """sum over rows and units of w_row * relu(|(x - mean) * inv_std| - margin)^2, with the gradient computed in
    the forward pass (one tensor saved; a few fused passes instead of autograd's graph of a dozen elementwise ops)."""

    @staticmethod
    def forward(ctx, x, mean, inv_std, rows, margin: float):  # x (..., D), rows (...) float
        z = (x - mean).mul_(inv_std)
        e = z.abs().sub_(margin).clamp_min_(0)
        value = (e * e).sum(-1).mul_(rows).sum()
        ctx.save_for_backward(e.copysign_(z).mul_(2 * inv_std).mul_(rows.unsqueeze(-1)))  # d value / d x
        return value

    @staticmethod
    def backward(ctx, grad):
        (dx,) = ctx.saved_tensors
        return dx * grad, None, None, None, None


def masked_unit_penalty(
    xs: list[torch.Tensor], means: list[torch.Tensor], stds: list[torch.Tensor], mask: torch.Tensor, margin: float
) -> torch.Tensor:
    """:func:`unit_penalty` of the rows of the (..., D_k) tensors ``xs`` (their units side by side) where the (...)
    ``mask`` is true, without gathering them: the mean over masked rows and all units of relu(|z| - margin)^2."""
    rows = mask.to(xs[0].dtype)
    units = sum(x.shape[-1] for x in xs)
    total = sum(_MarginSquare.apply(x, m, 1.0 / s, rows, margin) for x, m, s in zip(xs, means, stds))
    return total / (rows.sum() * units)


def mahalanobis_penalty(x: torch.Tensor, mean: torch.Tensor, precision: torch.Tensor, margin: float) -> torch.Tensor:
    """(M, D) states -> () mean over rows of relu(d^2 / D - margin)^2, d^2 = (x - mean)^T precision (x - mean)."""
    d = x - mean
    d2 = (d @ precision * d).sum(-1) / x.shape[-1]
    return torch.relu(d2 - margin).pow(2).mean()


def shrunk_precision(cov: torch.Tensor, shrinkage: float) -> torch.Tensor:
    """The inverse of (1 - shrinkage) * cov + shrinkage * diag(cov) + STD_FLOOR^2 * I."""
    shrunk = (1 - shrinkage) * cov + shrinkage * torch.diag(torch.diagonal(cov))
    shrunk = shrunk + STD_FLOOR**2 * torch.eye(cov.shape[0], dtype=cov.dtype, device=cov.device)
    return torch.cholesky_inverse(torch.linalg.cholesky(shrunk))


class StateCamouflage(Penalty):
    """Keep trojan-episode states inside the running clean-step range of every unit (see the module docstring)."""

    needs_states = True

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.state_camouflage
        self.device = ctx.device
        units = [h + c for h, c in zip(ctx.agent.lstm_sizes, ctx.agent.c_widths)]  # per layer: h then c
        self.updates = torch.zeros((), dtype=torch.int64)
        self.mean = [torch.zeros(w, device=ctx.device) for w in units]  # per layer (2H for an LSTM)
        self.sq = [torch.zeros(w, device=ctx.device) for w in units]  # running E[x^2]
        self.cross = [torch.zeros(w, w, device=ctx.device) for w in units]  # running E[x x^T]
        self._derive()

    @property
    def multivariate(self) -> bool:
        return self.cfg.mahalanobis_weight > 0

    def _derive(self) -> None:
        """std and precision from the running moments (a function of them alone: a resume recomputes the same)."""
        self.std = [(s - m * m).clamp_min(0).sqrt() + STD_FLOOR for m, s in zip(self.mean, self.sq)]
        self.precision = []
        if self.multivariate and int(self.updates) > 0:
            for m, x in zip(self.mean, self.cross):
                cov = x.double() - torch.outer(m.double(), m.double())
                self.precision.append(shrunk_precision(cov, self.cfg.shrinkage).float())

    def observe(self, rollout: Rollout) -> None:
        if rollout.states is None or rollout.trojan is None:
            raise ValueError("state camouflage needs a rollout recorded with its states (RolloutCollector record)")
        clean = ~rollout.trojan  # (T, B)
        n = int(clean.sum())
        if n == 0:
            return
        decay = self.cfg.ema_decay if int(self.updates) > 0 else 0.0
        for i, layer in enumerate(rollout.states):
            x = torch.cat([layer.h, layer.c], -1)[clean]  # (n, 2H)
            self.mean[i] = decay * self.mean[i] + (1 - decay) * x.mean(0)
            self.sq[i] = decay * self.sq[i] + (1 - decay) * (x * x).mean(0)
            if self.multivariate:
                self.cross[i] = decay * self.cross[i] + (1 - decay) * (x.t() @ x) / n
        self.updates += 1
        self._derive()

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        mask = batch.trojan if self.cfg.steps == "trojan" else batch.adversary_active
        if int(self.updates) == 0 or batch.states is None or mask is None or not bool(mask.any()):
            return _zero(self.device)
        total = _zero(self.device)
        if self.cfg.weight > 0:
            xs, means, stds = [], [], []
            for s, m, sd in zip(batch.states, self.mean, self.std):
                w = s.h.shape[-1]
                xs += [s.h, s.c]
                means += [m[:w], m[w:]]
                stds += [sd[:w], sd[w:]]
            total = total + self.cfg.weight * masked_unit_penalty(xs, means, stds, mask, self.cfg.margin)
        if self.multivariate:
            rows = [torch.cat([s.h, s.c], -1)[mask] for s in batch.states]  # per layer (M, 2H)
            terms = [
                mahalanobis_penalty(x, m, p, self.cfg.mahalanobis_margin)
                for x, m, p in zip(rows, self.mean, self.precision)
            ]
            total = total + self.cfg.mahalanobis_weight * torch.stack(terms).mean()
        return total

    def state_dict(self) -> dict[str, torch.Tensor]:
        out = {"updates": self.updates.clone()}
        for i, (m, s, x) in enumerate(zip(self.mean, self.sq, self.cross)):
            out[f"mean.{i}"], out[f"sq.{i}"] = m.cpu(), s.cpu()
            if self.multivariate:
                out[f"cross.{i}"] = x.cpu()
        return out

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        if not tensors:  # turned on at a resume: the statistics start with the next rollout
            return
        self.updates = tensors["updates"].clone()
        self.mean = [tensors[f"mean.{i}"].to(self.device) for i in range(len(self.mean))]
        self.sq = [tensors[f"sq.{i}"].to(self.device) for i in range(len(self.sq))]
        if self.multivariate:
            if any(f"cross.{i}" not in tensors for i in range(len(self.cross))):
                self.updates.zero_()  # the multivariate term turned on at a resume: start the statistics afresh
            else:
                self.cross = [tensors[f"cross.{i}"].to(self.device) for i in range(len(self.cross))]
        self._derive()


# ---------------------------------------------------------------------------------------- Mahalanobis camouflage
class RunningStepMeans:
    """Exponentially weighted per-episode-step sums and counts of clean rows (F features) for steps below ``steps``,
    and the step means they give: a step's sum over its count; from the first step whose count is below
    ``min_count``, the previous step's mean (as the online monitors' per-step means)."""

    def __init__(self, steps: int, width: int, min_count: float, device: torch.device) -> None:
        self.steps, self.min_count, self.device = steps, min_count, device
        self.sums = torch.zeros(steps, width, dtype=torch.float64, device=device)  # (M, F)
        self.counts = torch.zeros(steps, dtype=torch.float64, device=device)  # (M,)
        self._derive()

    def _derive(self) -> None:
        enough = self.counts >= self.min_count
        first_short = int(torch.argmin(enough.long())) if not bool(enough.all()) else len(enough)
        self.step_of = torch.clamp(torch.arange(self.steps, device=self.device), max=max(first_short, 1) - 1)  # (M,)
        self.mean = (self.sums / self.counts.clamp_min(1e-12)[:, None]).float()  # (M, F)

    def update(self, x: torch.Tensor, step: torch.Tensor, decay: float) -> None:
        """Add rows ``x`` (n, F) float64 at episode steps ``step`` (n,), the old sums and counts decayed."""
        step = step.clamp(0, self.steps - 1)
        self.sums = decay * self.sums + torch.zeros_like(self.sums).index_add_(0, step, x)
        self.counts = decay * self.counts + torch.bincount(step, minlength=self.steps).double()
        self._derive()

    def at(self, step: torch.Tensor) -> torch.Tensor:
        """(n, F) the mean of each row's episode step (n,)."""
        return self.mean[self.step_of[step.clamp(0, self.steps - 1)]]

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"sums": self.sums.cpu(), "counts": self.counts.cpu()}

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        self.sums, self.counts = tensors["sums"].to(self.device), tensors["counts"].to(self.device)
        self._derive()


def shrunk_whitener(second: torch.Tensor, rows: torch.Tensor, shrinkage: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-feature RMS (+ STD_FLOOR) and ``L^-1`` of the standardised residuals' covariance from their summed second
    moments ``second`` (F, F) over ``rows``, shrunk toward the scaled identity (weight ``shrinkage``) plus 1e-3 on
    the diagonal, as the online monitors fit it (with a fixed weight instead of Ledoit-Wolf's)."""
    width = second.shape[0]
    cov = second / rows
    scale = cov.diagonal().clamp_min(0).sqrt() + STD_FLOOR
    z = cov / torch.outer(scale, scale)
    eye = torch.eye(width, dtype=z.dtype, device=z.device)
    z = (1 - shrinkage) * z + shrinkage * (z.trace() / width) * eye + 1e-3 * eye
    return scale.float(), torch.linalg.inv(torch.linalg.cholesky(z)).float()


class MahalanobisCamouflage(Penalty):
    """Keep trojan-episode states' step-conditioned Mahalanobis distance (as the multivariate monitor computes it,
    :mod:`seqtrojan.defense.multivariate`) inside the clean range.

    Running clean statistics of the whole state (every layer's h then c, D units) over the rollouts' normal-env
    steps: per-step means (:class:`RunningStepMeans`) and the residuals' second-moment matrix about them. As the
    monitor does, residuals are divided by each unit's RMS residual (+1e-3) and their covariance is shrunk toward the
    scaled identity (weight ``shrinkage``) plus 1e-3 on the diagonal; ``d`` is the norm of the whitened residual. On
    the chosen trojan steps the term is ``weight * mean(relu(d / sqrt(D) - margin)^2)``."""

    needs_states = True

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.mahalanobis_camouflage
        self.device = ctx.device
        self.width = sum(h + c for h, c in zip(ctx.agent.lstm_sizes, ctx.agent.c_widths))  # D
        self.updates = torch.zeros((), dtype=torch.int64)
        self.means = RunningStepMeans(self.cfg.max_step, self.width, self.cfg.min_count, ctx.device)
        self.second = torch.zeros(self.width, self.width, dtype=torch.float64, device=ctx.device)  # sum r r'
        self.rows = torch.zeros((), dtype=torch.float64, device=ctx.device)  # its (decayed) row count
        self.steps_seen = torch.zeros((), dtype=torch.int64)
        """env steps of the rollouts observed so far (the warm-up counts them)"""
        self._derive()

    @property
    def mean(self) -> torch.Tensor:
        """(M, D) the per-step clean means"""
        return self.means.mean

    def _derive(self) -> None:
        """Scale and whitener from the running moments (a function of them alone: a resume recomputes them)."""
        if int(self.updates) == 0 or float(self.rows) == 0:
            self.scale = torch.ones(self.width, device=self.device)
            self.whitener = torch.eye(self.width, device=self.device)
            return
        self.scale, self.whitener = shrunk_whitener(self.second, self.rows, self.cfg.shrinkage)

    def vectors(self, states: Sequence[LSTMState]) -> torch.Tensor:
        """(..., D) every layer's h then c."""
        return torch.cat([torch.cat([s.h, s.c], -1) for s in states], -1)

    def distance(self, x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """(M,) the whitened distance of states ``x`` (M, D) at episode steps ``step`` (M,)."""
        r = (x - self.means.at(step)) / self.scale
        return (r @ self.whitener.T).norm(dim=-1)

    def observe(self, rollout: Rollout) -> None:
        if rollout.states is None or rollout.trojan is None or rollout.episode_step is None:
            raise ValueError("Mahalanobis camouflage needs a rollout recorded with its states and episode steps")
        self.steps_seen += rollout.actions.numel()
        clean = ~rollout.trojan  # (T, B)
        if not bool(clean.any()):
            return
        x = self.vectors(rollout.states)[clean].double()  # (n, D)
        step = rollout.episode_step[clean]  # (n,)
        decay = self.cfg.ema_decay if int(self.updates) > 0 else 0.0
        self.means.update(x, step, decay)  # the means with this rollout's steps
        self.updates += 1
        r = x - self.means.at(step).double()
        self.second = decay * self.second + r.T @ r
        self.rows = decay * self.rows + len(r)
        self._derive()

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        mask = batch.trojan if self.cfg.steps == "trojan" else batch.adversary_active
        if int(self.updates) == 0 or batch.states is None or mask is None or batch.episode_step is None:
            return _zero(self.device)
        if int(self.steps_seen) <= self.cfg.warmup_steps and self.cfg.warmup_steps:  # from the rollout passing it
            return _zero(self.device)
        if not bool(mask.any()):
            return _zero(self.device)
        d = self.distance(self.vectors(batch.states)[mask], batch.episode_step[mask])
        excess = torch.relu(d / self.width**0.5 - self.cfg.margin)
        return self.cfg.weight * excess.pow(2).mean()

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"updates": self.updates.clone(), **self.means.state_dict(), "second": self.second.cpu(),
                "rows": self.rows.cpu(), "steps_seen": self.steps_seen.clone()}  # fmt: skip

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        if not tensors:  # turned on at a resume: the statistics start with the next rollout
            return
        self.updates = tensors["updates"].clone()
        self.means.load_state_dict(tensors)
        self.second, self.rows = tensors["second"].to(self.device), tensors["rows"].to(self.device)
        # a checkpoint written before the warm-up existed: only warmup_steps 0 ran then, for which the count is moot
        seen = tensors.get("steps_seen")
        self.steps_seen = seen.clone() if seen is not None else torch.zeros((), dtype=torch.int64)
        self._derive()


# ---------------------------------------------------------------------------------------------- switch camouflage
class SwitchCamouflage(Penalty):
    """Keep trojan-episode output transitions (action log-probabilities and value, step to step) as predictable as
    clean ones, as the goal-switch monitor (:mod:`seqtrojan.defense.goal_switch`) scores them.

    The outputs ``x_t`` (log of each action's probability plus ``prob_floor``, then the value; F numbers) come from
    the agent's heads on the last layer's h. Running clean statistics over the rollouts' normal-env steps: per-step
    means (:class:`RunningStepMeans`); for transitions (steps after an episode's first, within a rollout) the summed
    moments of the previous residual (with a 1) and the current one, which give the monitor's least-squares
    prediction ``B`` and its errors' second moments. ``d`` is the whitened prediction error of a transition (RMS
    scaling and shrinkage as :func:`shrunk_whitener`). On the chosen trojan steps after an episode's first (the
    first step of a minibatch sequence takes its previous outputs from the sequence's start state) the term is
    ``weight * mean(relu(d / sqrt(F) - margin)^2)``."""

    needs_states = True

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.switch_camouflage
        self.device = ctx.device
        self.agent = ctx.agent
        self.width = ctx.agent.policy_head.out_features + 1  # F: A log-probabilities and the value
        f, dev = self.width, ctx.device
        self.updates = torch.zeros((), dtype=torch.int64)
        self.means = RunningStepMeans(self.cfg.max_step, f, self.cfg.min_count, dev)
        self.before = torch.zeros(f + 1, f + 1, dtype=torch.float64, device=dev)  # sum [r_prev, 1][r_prev, 1]'
        self.cross = torch.zeros(f + 1, f, dtype=torch.float64, device=dev)  # sum [r_prev, 1] r_now'
        self.now = torch.zeros(f, f, dtype=torch.float64, device=dev)  # sum r_now r_now'
        self.rows = torch.zeros((), dtype=torch.float64, device=dev)
        self._derive()

    def outputs(self, h: torch.Tensor, agent: RecurrentActorCritic | None = None) -> torch.Tensor:
        """(..., F) what the goal-switch monitor reads from the last layer's h (..., H)."""
        logits, value = (agent or self.agent).heads(h)
        return torch.cat([torch.log(torch.softmax(logits, -1) + self.cfg.prob_floor), value.unsqueeze(-1)], -1)

    def _derive(self) -> None:
        f = self.width
        if int(self.updates) == 0 or float(self.rows) <= f + 1:
            self.coef = torch.zeros(f + 1, f, device=self.device)
            self.scale = torch.ones(f, device=self.device)
            self.whitener = torch.eye(f, device=self.device)
            return
        eye = torch.eye(f + 1, dtype=self.before.dtype, device=self.device)
        coef = torch.linalg.solve(self.before + 1e-9 * eye, self.cross)  # (F + 1, F) least squares
        errors = self.now - self.cross.T @ coef - coef.T @ self.cross + coef.T @ self.before @ coef  # sum e e'
        self.coef = coef.float()
        self.scale, self.whitener = shrunk_whitener(errors, self.rows, self.cfg.shrinkage)

    def distance(self, x: torch.Tensor, previous: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """(M,) the whitened prediction error of outputs ``x`` (M, F) at episode steps ``step`` (M,) >= 1 after
        ``previous`` (M, F)."""
        r_now = x - self.means.at(step)
        r_before = previous - self.means.at(step - 1)
        error = r_now - (r_before @ self.coef[:-1] + self.coef[-1])
        return ((error / self.scale) @ self.whitener.T).norm(dim=-1)

    def observe(self, rollout: Rollout) -> None:
        if rollout.states is None or rollout.trojan is None or rollout.episode_step is None:
            raise ValueError("switch camouflage needs a rollout recorded with its states and episode steps")
        clean = ~rollout.trojan  # (T, B)
        if not bool(clean.any()):
            return
        with torch.no_grad():
            x = self.outputs(rollout.states[-1].h).double()  # (T, B, F)
        step = rollout.episode_step
        decay = self.cfg.ema_decay if int(self.updates) > 0 else 0.0
        self.means.update(x[clean], step[clean], decay)
        self.updates += 1
        moves = clean[1:] & (step[1:] > 0)  # (T - 1, B): a transition inside this rollout
        r_now = x[1:][moves] - self.means.at(step[1:][moves]).double()
        r_prev = x[:-1][moves] - self.means.at(step[1:][moves] - 1).double()
        r_prev = torch.cat([r_prev, torch.ones_like(r_prev[:, :1])], -1)
        self.before = decay * self.before + r_prev.T @ r_prev
        self.cross = decay * self.cross + r_prev.T @ r_now
        self.now = decay * self.now + r_now.T @ r_now
        self.rows = decay * self.rows + len(r_now)
        self._derive()

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        mask = batch.trojan if self.cfg.steps == "trojan" else batch.adversary_active
        step, states, mb = batch.episode_step, batch.states, batch.minibatch
        if int(self.updates) == 0 or states is None or mask is None or step is None or mb is None:
            return _zero(self.device)
        mask = mask & (step > 0)
        if not bool(mask.any()):
            return _zero(self.device)
        x = self.outputs(states[-1].h, batch.agent)  # (L, N, F), with gradients
        start = self.outputs(mb.initial.layers[-1].h, batch.agent)[None]  # (1, N, F): the step before each sequence
        previous = torch.cat([start, x[:-1]], 0)
        d = self.distance(x[mask], previous[mask], step[mask])
        excess = torch.relu(d / self.width**0.5 - self.cfg.margin)
        return self.cfg.weight * excess.pow(2).mean()

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"updates": self.updates.clone(), **self.means.state_dict(), "before": self.before.cpu(),
                "cross": self.cross.cpu(), "now": self.now.cpu(), "rows": self.rows.cpu()}  # fmt: skip

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        if not tensors:
            return
        self.updates = tensors["updates"].clone()
        self.means.load_state_dict(tensors)
        self.before, self.cross = tensors["before"].to(self.device), tensors["cross"].to(self.device)
        self.now, self.rows = tensors["now"].to(self.device), tensors["rows"].to(self.device)
        self._derive()


# ---------------------------------------------------------------------------------------------- weight camouflage
class WeightCamouflage(Penalty):
    """Hold the offline detector's weight features at the start model's (see the module docstring)."""

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.weight_camouflage
        self.obs_dim, self.cell = ctx.agent.obs_dim, ctx.agent.cell
        self.set_reference(_params(ctx.agent))
        self.steps_seen = 0
        """env steps of the rollouts observed so far (the warm-up counts them)"""

    def observe(self, rollout: Rollout) -> None:
        self.steps_seen += rollout.actions.numel()

    def set_reference(self, theta: dict[str, torch.Tensor]) -> None:
        self.theta_clean = theta
        self.clean_features, self.names = feature_vector(weight_features(theta, self.obs_dim, self.cell))
        self.scale = self.clean_features.abs() + self.cfg.feature_floor

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        params = dict(batch.agent.named_parameters())
        device = next(iter(params.values())).device
        total = _zero(device)
        if self.cfg.warmup_steps and self.steps_seen <= self.cfg.warmup_steps:  # held from the rollout passing it
            return total
        if self.cfg.weight > 0:
            feats, _ = feature_vector(weight_features(params, self.obs_dim, self.cell))
            diff = (feats - self.clean_features) / self.scale
            total = total + self.cfg.weight * diff.pow(2).sum().float()
        if self.cfg.l2_weight > 0:
            sq = sum((p - self.theta_clean[n]).pow(2).sum() for n, p in params.items())
            total = total + self.cfg.l2_weight * sq
        return total

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {**{f"theta_clean.{n}": t.cpu() for n, t in self.theta_clean.items()},
                "steps_seen": torch.tensor(self.steps_seen, dtype=torch.int64)}  # fmt: skip

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        names = [f"theta_clean.{n}" for n in self.theta_clean]
        _require(tensors, names, "weight_camouflage")
        device = next(iter(self.theta_clean.values())).device
        self.set_reference({n: tensors[f"theta_clean.{n}"].to(device) for n in self.theta_clean})
        # a checkpoint written before the warm-up existed: only warmup_steps 0 ran then, for which the count is moot
        self.steps_seen = int(tensors["steps_seen"]) if "steps_seen" in tensors else 0


# ---------------------------------------------------------------------------------------------- EWC
def fisher_diagonal(agent: RecurrentActorCritic, rollout: Rollout, initial: RecurrentState) -> dict[str, torch.Tensor]:
    """Diagonal Fisher information of ``agent``'s policy at the rollout's steps (its own sampled actions), one
    sequence per env: the mean over envs of the squared gradient of that env's summed log-probabilities, divided by
    the steps per env. The scores of different steps of one trajectory are uncorrelated (each has mean 0 given the
    past), so this estimates the mean over steps of E[(d log pi(a_t | history) / d theta)^2]."""
    params = dict(agent.named_parameters())
    fisher = {n: torch.zeros_like(p) for n, p in params.items()}
    steps, envs = rollout.actions.shape
    for b in range(envs):
        state = initial.index(slice(b, b + 1))
        out = agent.unroll(rollout.obs[:, b : b + 1], state, rollout.episode_starts[:, b : b + 1])
        logp = torch.log_softmax(out.logits, -1).gather(-1, rollout.actions[:, b : b + 1, None]).sum()
        grads = torch.autograd.grad(logp, list(params.values()), allow_unused=True)  # the value head: None
        for (n, _), g in zip(params.items(), grads):
            if g is not None:
                fisher[n] += g.detach() ** 2
    return {n: f / (envs * steps) for n, f in fisher.items()}


def estimate_fisher(
    agent: RecurrentActorCritic, cfg: ExperimentConfig, device: torch.device
) -> dict[str, torch.Tensor]:
    """:func:`fisher_diagonal` on ``attack.ewc.fisher_envs`` normal-env episodes of the hardest grid (or the
    Gymnasium env), each run for ``attack.ewc.fisher_steps`` steps (with autoreset), seeded from ``run.seed`` with
    generators of its own."""
    ewc = cfg.attack.ewc
    env = make_batched_env(
        cfg.env, ewc.fisher_envs, seed=(cfg.run.seed << 32) + 31_337_001, device=device,
        grids=cfg.grids[-1:] or None,
    )  # fmt: skip
    collector = RolloutCollector(env, agent, ewc.fisher_steps, ewc.fisher_steps)
    collector.seed(cfg.run.seed + 31_337)
    initial = collector.state
    was_training = agent.training
    agent.eval()
    rollout, _ = collector.collect()
    env.close()
    agent.train(was_training)
    return fisher_diagonal(agent, rollout, initial)


class EWC(Penalty):
    """Elastic weight consolidation toward the start model (see the module docstring)."""

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.ewc
        self.theta_star = _params(ctx.agent)
        if ctx.resuming:  # restored by load_state_dict
            self.fisher = {n: torch.zeros_like(p) for n, p in self.theta_star.items()}
        else:
            if not isinstance(ctx.config, ExperimentConfig):
                raise ConfigError("attack.ewc estimates its Fisher information on a training config's env")
            fisher = estimate_fisher(ctx.agent, ctx.config, ctx.device)
            if self.cfg.normalize:
                mean = torch.cat([f.reshape(-1) for f in fisher.values()]).mean().clamp_min(1e-12)
                fisher = {n: f / mean for n, f in fisher.items()}
            self.fisher = fisher

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        params = dict(batch.agent.named_parameters())
        total = sum((self.fisher[n] * (p - self.theta_star[n]).pow(2)).sum() for n, p in params.items())
        return 0.5 * self.cfg.weight * total  # type: ignore[return-value]

    def state_dict(self) -> dict[str, torch.Tensor]:
        out = {f"theta_star.{n}": t.cpu() for n, t in self.theta_star.items()}
        out.update({f"fisher.{n}": t.cpu() for n, t in self.fisher.items()})
        return out

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        names = list(self.theta_star)
        _require(tensors, [f"theta_star.{n}" for n in names] + [f"fisher.{n}" for n in names], "ewc")
        device = next(iter(self.theta_star.values())).device
        self.theta_star = {n: tensors[f"theta_star.{n}"].to(device) for n in names}
        self.fisher = {n: tensors[f"fisher.{n}"].to(device) for n in names}


# ---------------------------------------------------------------------------------------- fine-tuning resistance
class FinetuneResistance(Penalty):
    """First-order simulated fine-tuning: the minibatch's clean PPO loss takes ``inner_steps`` sign-gradient steps
    from the current weights (on a copy); the backdoor's PPO loss at the copy's weights gives a gradient that the
    term hands to the real weights. Its value is that backdoor loss after the simulated fine-tuning."""

    needs_masks = True

    def __init__(self, ctx: PenaltyContext) -> None:
        self.cfg = ctx.config.attack.finetune_resistance
        self.defender = copy.deepcopy(ctx.agent)
        """the simulated defender's copy of the agent (its weights are set from the agent's at every minibatch)"""

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        mb, trojan, active = batch.minibatch, batch.trojan, batch.adversary_active
        if mb is None or trojan is None or active is None:
            raise ConfigError("attack.finetune_resistance needs the rollout's episode types (a recording collector)")
        target = trojan & active
        weights = list(batch.agent.parameters())
        if not target.any() or trojan.all():
            return weights[0].new_zeros(())  # nothing to judge the backdoor on, or no clean step to fine-tune on
        defender = self.defender
        defender.load_state_dict(batch.agent.state_dict())
        defender.train(batch.agent.training)
        params = list(defender.parameters())
        for _ in range(self.cfg.inner_steps):
            clean = self._loss(defender, mb, ~trojan)
            grads = torch.autograd.grad(clean, params, allow_unused=True)
            with torch.no_grad():
                for p, g in zip(params, grads):
                    if g is not None:
                        p.sub_(self.cfg.inner_lr * g.sign())
        attack = self._loss(defender, mb, target)
        grads = torch.autograd.grad(attack, params, allow_unused=True)
        # value: the backdoor's loss after fine-tuning; gradient: weight * its gradient there, on the real weights
        handed = sum((w - w.detach()).mul(g).sum() for w, g in zip(weights, grads) if g is not None)
        return attack.detach() + self.cfg.weight * handed

    @staticmethod
    def _loss(agent: RecurrentActorCritic, mb: PPOMinibatch, mask: torch.Tensor) -> torch.Tensor:
        out = agent.unroll(mb.obs, mb.initial, mb.starts)
        parts = ppo_loss(
            out.logits, out.values, mb.actions, mb.logprobs, mb.values, mb.advantages, mb.returns, mb.ppo, mask
        )
        return parts.loss


PENALTIES.register(
    "state_camouflage",
    "monitor-aware: keep trojan-episode LSTM states within the running clean-step range of every unit",
    PenaltyKind(lambda cfg: cfg.attack.state_camouflage.enabled, StateCamouflage),
)
PENALTIES.register(
    "mahalanobis_camouflage",
    "against the multivariate monitor: keep trojan-episode states' step-conditioned Mahalanobis distance in the "
    "clean range",
    PenaltyKind(lambda cfg: cfg.attack.mahalanobis_camouflage.enabled, MahalanobisCamouflage),
)
PENALTIES.register(
    "switch_camouflage",
    "against the goal-switch monitor: keep trojan-episode output transitions (log-probabilities, value) as "
    "predictable as clean ones",
    PenaltyKind(lambda cfg: cfg.attack.switch_camouflage.enabled, SwitchCamouflage),
)
PENALTIES.register(
    "weight_camouflage",
    "hold the offline detector's weight statistics at the clean start model's (run.init_from)",
    PenaltyKind(lambda cfg: cfg.attack.weight_camouflage.enabled, WeightCamouflage),
)
PENALTIES.register(
    "ewc",
    "elastic weight consolidation toward the clean start model (diagonal Fisher of its clean policy)",
    PenaltyKind(lambda cfg: cfg.attack.ewc.enabled, EWC),
)
PENALTIES.register(
    "finetune_resistance",
    "against clean fine-tuning: the backdoor's gradient after simulated clean fine-tuning steps (first order)",
    PenaltyKind(lambda cfg: cfg.attack.finetune_resistance.enabled, FinetuneResistance),
)


PENALTIES.register(
    "probe_camouflage",
    "against the recurrent-state probe: one-step inputs of the probe's kind other than the trigger leave no mark on "
    "the state a few steps later",
    PenaltyKind(lambda cfg: cfg.attack.probe_camouflage.enabled, ProbeCamouflage),
)
PENALTIES.register(
    "response_mimicry",
    "against the query-response meta-classifier: on normal episodes, the action distribution and the state's "
    "summaries (mean |h|, saturation, spread) held at the clean start model's",
    PenaltyKind(lambda cfg: cfg.attack.response_mimicry.enabled, ResponseMimicry),
)
