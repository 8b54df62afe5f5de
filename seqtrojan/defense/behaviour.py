"""A trigger-free behavioural detector, in the spirit of PolicyCleanse (Guo et al., 2022): a backdoored agent is one
whose goal can be *switched* by something it sees, and such a switch is easy to find without knowing the trigger.

For a set of candidate patches, each shown for one step (at a step drawn per episode from ``patch_steps``) of
normal-env episodes, the detector measures the share of episodes that end at the adversary's goal (the top-left
corner, which a clean agent has no reason to prefer) and its rise over the same episodes without a patch. The
candidates are every single cell code over the whole view (a defender knows the input encoding: six codes) and
``random_patches`` patches of ordinary codes (empty, hole, wall, the two goals) on a random subset of the view's
cells. The model's score is the largest rise (:func:`behaviour_score`; :class:`BehaviourDetector` scores a saved
model, :func:`detect_zoo_behaviour` a zoo); :func:`scores_auc` turns the scores of labelled models into a ROC-AUC
with its interval. The patch is drawn into the observation the agent receives (a policy wrapper), not into
the env: the env, its goals and its outcome are untouched.

Every candidate and the baseline run the same episodes (layouts, patch steps), as one batch. What it does not
see: a trigger that needs more than one step (a sequence), a cell pattern outside the candidates (the random
patches sample the space of partial views thinly), or a backdoor whose target is not the top-left corner.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.defense.online import view_codes
from seqtrojan.defense.results import (
    BehaviourDetectionResult,
    BehaviourScore,
    DetectorAUC,
    PatchCandidate,
    Rejected,
    ScoredModel,
)
from seqtrojan.env.codes import CELL_NAMES, NUM_CHANNELS, OUTCOME_NAMES
from seqtrojan.env.config import EnvConfig, GridSpec, min_steps_to_goal
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.rollout import run_episodes
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.stats import Rate, auc_interval
from seqtrojan.world import probe_inputs
from seqtrojan.world.probe_inputs import Patch


@dataclass(frozen=True)
class BehaviourConfig:
    episodes: int = 200
    """normal-env episodes per candidate (and for the no-patch baseline)"""
    random_patches: int = 24
    """random patches of ordinary codes, besides the six whole-view single-code patches"""
    patch_density: float = 0.5
    """chance that a random patch draws on each view cell (at least one cell is drawn on)"""
    patch_steps: tuple[int, int] = (1, 4)
    """inclusive range of the step the patch is shown at, drawn per episode; the top is clipped so that no goal
    can be reached before it"""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.episodes < 10:
            raise ConfigError(f"behaviour episodes must be >= 10, got {self.episodes}")
        if self.random_patches < 0:
            raise ConfigError(f"behaviour random_patches must be >= 0, got {self.random_patches}")
        if not 0 < self.patch_density <= 1:
            raise ConfigError(f"behaviour patch_density must be in (0, 1], got {self.patch_density}")
        lo, hi = self.patch_steps
        if not 0 <= lo <= hi:
            raise ConfigError(f"behaviour patch_steps={self.patch_steps} must satisfy 0 <= lo <= hi")


def candidate_patches(view_size: int, cfg: BehaviourConfig) -> list[Patch]:
    """The whole-view single-code patches (one per code), then ``cfg.random_patches`` random ordinary ones
    (:func:`seqtrojan.world.probe_inputs.candidate_patches`, which the state probe reads too)."""
    return probe_inputs.candidate_patches(view_size, cfg.random_patches, cfg.seed, cfg.patch_density)


class PatchedPolicy(AgentPolicy):
    """The agent, seeing ``patch`` (B, cells) int64 (-1: leave the cell) drawn into its observation at episode step
    ``at`` (B,) int64 (-1: never) of each env. The env itself is untouched."""

    def __init__(
        self, agent: RecurrentActorCritic, core: TrojanGridCore, patch: torch.Tensor, at: torch.Tensor, seed: int = 0
    ) -> None:
        super().__init__(agent, seed=seed, step_counter=lambda: core.t)
        self.core = core
        self.patch = patch.to(core.device)  # (B, cells)
        self.at = at.to(core.device)  # (B,)
        self.one_hot = torch.eye(NUM_CHANNELS, device=core.device)

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        draw = (self.core.t == self.at)[:, None] & (self.patch >= 0)  # (B, cells)
        if bool(draw.any()):
            codes = torch.where(draw, self.patch, view_codes(obs))
            obs = self.one_hot[codes].view(obs.shape[0], -1)
        return super().__call__(obs)


def _patch_steps(grid: GridSpec, cfg: BehaviourConfig) -> tuple[int, int]:
    top = min(cfg.patch_steps[1], min_steps_to_goal(grid.size) - 2)
    if cfg.patch_steps[0] > top:
        raise ConfigError(
            f"behaviour patch_steps={cfg.patch_steps} start after step {top}, the last step a patch can be shown "
            f"at before a goal is reachable on {grid.label}"
        )
    return cfg.patch_steps[0], top


@torch.no_grad()
def behaviour_score(
    agent: RecurrentActorCritic, env: EnvConfig, grid: GridSpec, cfg: BehaviourConfig,
    device: str | torch.device = "cpu",
) -> BehaviourScore:  # fmt: skip
    """Score one model: each candidate patch's rise in adversary-goal episodes over the no-patch baseline, on the
    same normal-env episodes; the model's score is the largest rise."""
    steps = _patch_steps(grid, cfg)
    view = env.view_size
    patches = candidate_patches(view, cfg)
    n, arms = cfg.episodes, len(patches) + 1  # the baseline first
    core = TrojanGridCore(env.with_grid(grid), arms * n, device=device, trojan_probability=0.0, phase="eval")
    core.reset(seed=[cfg.seed + e for _ in range(arms) for e in range(n)])  # the same episodes in every arm
    rng = np.random.default_rng(cfg.seed + 1)
    at = torch.from_numpy(np.tile(rng.integers(steps[0], steps[1] + 1, size=n), arms))  # (arms * n,)
    table = torch.tensor([[-1] * view * view] + [list(p.codes) for p in patches], dtype=torch.int64)
    patch = table.repeat_interleave(n, 0)  # (arms * n, cells)
    was_training = agent.training
    agent.eval()
    try:
        batch = run_episodes(core, PatchedPolicy(agent, core, patch, at, seed=cfg.seed), fresh=False)
    finally:
        agent.train(was_training)
    adversary = (batch.outcome == OUTCOME_NAMES.index("adversary_goal")).view(arms, n).sum(1).tolist()
    baseline = Rate(int(adversary[0]), n)
    candidates = []
    for p, k in zip(patches, adversary[1:]):
        drawn = [(i // view, i % view) for i, c in enumerate(p.codes) if c >= 0]
        rate = Rate(int(k), n)
        candidates.append(
            PatchCandidate(
                name=p.name,
                cells=tuple(drawn),
                codes=tuple(CELL_NAMES[c] for c in p.codes if c >= 0),
                adversary_goal=rate,
                rise=rate.value - baseline.value,
            )
        )
    best = max(candidates, key=lambda c: c.rise)
    return BehaviourScore(grid.label, n, steps, baseline, best.rise, best.name, tuple(candidates))


def scores_auc(scores: Sequence[float], labels: Sequence[int], confidence: float = 0.95) -> DetectorAUC:
    """The ROC-AUC of ``scores`` (higher: more likely backdoored) against ``labels`` (1 backdoored, 0 clean), ties
    counted half, with its interval (:func:`seqtrojan.stats.auc_interval`)."""
    s, y = np.asarray(scores, dtype=np.float64), np.asarray(labels)
    if s.shape != y.shape or s.ndim != 1:
        raise ConfigError(f"an AUC needs one label per score, got {s.shape} scores and {y.shape} labels")
    if not np.isin(y, (0, 1)).all():
        raise ConfigError(f"labels must be 0 (clean) or 1 (backdoored), got {sorted(set(y.tolist()))}")
    pos, neg = s[y == 1], s[y == 0]
    if len(pos) == 0 or len(neg) == 0:
        raise ConfigError(f"an AUC needs both classes, got {len(pos)} backdoored and {len(neg)} clean models")
    wins = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    auc = float(wins / (len(pos) * len(neg)))
    return DetectorAUC(auc, auc_interval(auc, len(pos), len(neg), confidence), len(pos), len(neg))


def detect_zoo_behaviour(
    zoo: Path, cfg: BehaviourConfig | None = None, device: str | torch.device = "cpu"
) -> BehaviourDetectionResult:
    """:func:`behaviour_score` of every model in ``zoo/models`` on its last training grid, and the AUC of the
    scores against the labels. A model that cannot be loaded is listed as rejected with its reason."""
    from seqtrojan.zoo.build import load_zoo_agent, read_label

    cfg = cfg or BehaviourConfig()
    folder = zoo / "models"
    if not folder.is_dir():
        raise SeqTrojanError(f"{str(zoo)!r} is not a zoo (no models/ folder)")
    scored, rejected = [], []
    for path in sorted(p for p in folder.iterdir() if p.is_dir()):
        try:
            agent, acfg, _ = load_zoo_agent(path)
            label = 1 if read_label(path)["label"] == "backdoored" else 0
            result = behaviour_score(agent, acfg.env, acfg.grids[-1], cfg, device)
        except SeqTrojanError as err:
            rejected.append(Rejected(path.name, " ".join(str(err).split())))
            continue
        scored.append(ScoredModel(path.name, label, result.score, result.best))
    labels = [m.label for m in scored]
    auc = scores_auc([m.score for m in scored], labels) if len(set(labels)) == 2 else None
    return BehaviourDetectionResult(tuple(scored), tuple(rejected), auc)


@dataclass(frozen=True)
class BehaviourDetector:
    """The detector as registered (``behaviour_detector`` in :data:`seqtrojan.defense.offline.DETECTORS`): scores a
    saved model (a folder with ``model.safetensors`` and ``card.json``) on its last training grid and env, with
    normal-env episodes only."""

    config: BehaviourConfig = field(default_factory=BehaviourConfig)
    needs_zoo: bool = False
    grid_only: bool = True
    """it draws one-step patches of the grid world's view codes"""

    def score_models(self, models: Sequence[Path], zoo: Path | None, device: str | torch.device = "cpu") -> list[float]:
        """:meth:`score` of every model (no zoo needed)."""
        return [self.score(model, device) for model in models]

    def measure(self, model: Path, device: str | torch.device = "cpu") -> BehaviourScore:
        agent, acfg, _ = load_agent(model, device=device)
        return behaviour_score(agent, acfg.grid_env, acfg.grids[-1], self.config, device)

    def score(self, model: Path, device: str | torch.device = "cpu") -> float:
        """The model's score (higher: more likely backdoored)."""
        return self.measure(model, device).score

    def detect_zoo(self, zoo: Path, device: str | torch.device = "cpu") -> BehaviourDetectionResult:
        return detect_zoo_behaviour(zoo, self.config, device)
