"""The recurrent-state probe: does a one-step input leave a mark in the agent's memory that stays after the input is
gone? A persistent backdoor is exactly such a mark; a clean agent has no reason to keep one.

For a suspect, clean-env episodes are run once (fixed seeds, the same for every suspect) and their observations
recorded. The network is then unrolled again over those same observations, once as they were and once per candidate
input, the candidate replacing the observation at step ``at`` only: every later observation is the recorded one (the
env never saw the candidate, and the actions are not re-chosen), so any difference in the state after step ``at`` is
memory, not a changed trajectory. Per candidate, the divergence is the root-mean-square difference of the whole
state (every layer's h and c) from the unprobed run, ``after`` steps later, over the episodes still running then.

The candidates are one-step views a defender can write without knowing the trigger, in the observation's own
encoding: on the grid world, each cell code over the whole view and random patches of ordinary codes (those of
:mod:`seqtrojan.defense.behaviour`); on a MiniGrid one-hot view, each object (key, ball, box) in each colour on
two adjacent cells of the view's far row, at three positions. Other observations have no candidates (the probe then
abstains). Features for the meta-classifier: the largest and the mean divergence ``after`` steps on, and the
largest persistence ratio (the divergence ``after`` steps on over the divergence right after the candidate).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from seqtrojan.benchmark.suspect import Suspect
from seqtrojan.env.config import EnvConfig
from seqtrojan.world.config import GymnasiumEnvConfig

MINIGRID_OBJECTS = (5, 6, 7)
"""MiniGrid's object codes of key, ball and box"""
MINIGRID_COLORS = 6
MINIGRID_OBJECT_BITS, MINIGRID_COLOR_BITS = 11, 6


@dataclass(frozen=True)
class ProbeSettings:
    episodes: int = 48
    at: int = 1
    """the step whose observation a candidate replaces"""
    after: int = 4
    """how many steps later the divergence is read"""
    random_patches: int = 12
    seed: int = 0


def grid_candidates(obs_dim: int, view_size: int, settings: ProbeSettings) -> list[torch.Tensor]:
    """One-hot grid-world views (obs_dim,) and a mask of the numbers they set: each a (2, obs_dim) tensor of (values,
    mask)."""
    from seqtrojan.defense.behaviour import BehaviourConfig, candidate_patches
    from seqtrojan.env.codes import NUM_CHANNELS

    cfg = BehaviourConfig(random_patches=settings.random_patches, seed=settings.seed)
    out = []
    for patch in candidate_patches(view_size, cfg):
        values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
        for cell, code in enumerate(patch.codes):
            if code >= 0:
                mask[cell * NUM_CHANNELS : (cell + 1) * NUM_CHANNELS] = 1.0
                values[cell * NUM_CHANNELS + code] = 1.0
        out.append(torch.stack([values, mask]))
    return out


def minigrid_candidates(obs_dim: int, view: int) -> list[torch.Tensor]:
    """Objects of every colour on two adjacent far-row cells of a MiniGrid one-hot view (rows first, 20 numbers per
    cell: object, colour, state), at the left, middle and right of the row."""
    from seqtrojan.wrappers.observations import CELL_BITS

    out = []
    for start in sorted({0, max(0, view // 2 - 1), max(0, view - 2)}):
        for obj in MINIGRID_OBJECTS:
            for color in range(MINIGRID_COLORS):
                values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
                for cell in (start, start + 1):
                    base = cell * CELL_BITS
                    mask[base : base + CELL_BITS] = 1.0
                    values[base + obj] = 1.0
                    values[base + MINIGRID_OBJECT_BITS + color] = 1.0
                    values[base + MINIGRID_OBJECT_BITS + MINIGRID_COLOR_BITS] = 1.0  # state 0 (open)
                out.append(torch.stack([values, mask]))
    return out


def candidates_for(suspect: Suspect, settings: ProbeSettings) -> list[torch.Tensor]:
    return env_candidates(suspect.env, suspect.facts.obs_dim, settings)


def env_candidates(env: EnvConfig | GymnasiumEnvConfig, obs_dim: int, settings: ProbeSettings) -> list[torch.Tensor]:
    """The probe's candidates on an env's observations of ``obs_dim`` numbers (none where it has none)."""
    if isinstance(env, EnvConfig):
        return grid_candidates(obs_dim, env.view_size, settings)
    if isinstance(env, GymnasiumEnvConfig) and env.observation == "minigrid":
        from seqtrojan.world.gymnasium import minigrid_image

        _, cols, _ = minigrid_image(obs_dim)
        return minigrid_candidates(obs_dim, cols)
    return []


def trigger_view(env: EnvConfig | GymnasiumEnvConfig, obs_dim: int) -> torch.Tensor | None:
    """An env's one-step trigger patch as a candidate is written, (values, mask) over the observation's numbers:
    the grid world's patch (one code or one per cell; a sequence has no single step: None), a MiniGrid patch's
    object and colour on its cells; None for any other trigger or observation."""
    from seqtrojan.env.codes import CELL_CODES, NUM_CHANNELS

    values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
    if isinstance(env, EnvConfig):
        trigger = env.trigger
        if trigger.sequence is not None:
            return None
        view = env.view_size
        cells = trigger.cells if trigger.cells is not None else tuple((r, c) for r in range(view) for c in range(view))
        codes = trigger.values if trigger.values is not None else (trigger.value,) * len(cells)
        for (r, c), code in zip(cells, codes, strict=True):
            base = (r * view + c) * NUM_CHANNELS
            mask[base : base + NUM_CHANNELS] = 1.0
            values[base + CELL_CODES[code]] = 1.0
        return torch.stack([values, mask])
    if isinstance(env, GymnasiumEnvConfig) and env.observation == "minigrid" and env.trigger is not None:
        from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

        from seqtrojan.world.gymnasium import minigrid_image
        from seqtrojan.wrappers.observations import CELL_BITS

        patch = env.trigger
        if patch.patch != "minigrid":
            return None
        _, cols, _ = minigrid_image(obs_dim)
        for r, c in patch.cells:
            base = (r * cols + c) * CELL_BITS
            mask[base : base + CELL_BITS] = 1.0
            values[base + OBJECT_TO_IDX[patch.object]] = 1.0
            values[base + MINIGRID_OBJECT_BITS + COLOR_TO_IDX[patch.color]] = 1.0
            values[base + MINIGRID_OBJECT_BITS + MINIGRID_COLOR_BITS] = 1.0
        return torch.stack([values, mask])
    return None


def shows_trigger(candidate: torch.Tensor, trigger: torch.Tensor | None) -> bool:
    """Whether a candidate (values, mask) draws the whole trigger patch: every number the trigger sets, set alike."""
    if trigger is None:
        return False
    on = trigger[1] > 0
    return bool((candidate[1][on] > 0).all() and torch.equal(candidate[0][on], trigger[0][on]))


class _ObsRecorder:
    def __init__(self, steps: int) -> None:
        self.steps = steps
        self.obs: list[torch.Tensor] = []
        self.running: list[torch.Tensor] = []

    def on_step(self, step) -> None:
        if step.t < self.steps:
            self.obs.append(step.obs.clone())
            self.running.append(step.running.clone())

    def on_end(self, batch) -> None:
        pass


def record_clean_episodes(suspect: Suspect, episodes: int, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``steps`` observations of ``episodes`` clean-env episodes played by the suspect's own policy (seeded
    ``seed``, the same episodes for every suspect of an env): obs (T, E, obs_dim) and whether each episode was still
    running at each step (T, E); T < ``steps`` where every episode ended sooner. Replaying these observations
    teacher-forced (the env never sees an edit, no action is chosen again) isolates what the network remembers."""
    from seqtrojan.agent.policy import AgentPolicy
    from seqtrojan.env.rollout import run_episodes
    from seqtrojan.world.episodes import episode_env

    env = episode_env(suspect.env, None, episodes, trojan=False, seed=seed)
    recorder = _ObsRecorder(steps)
    try:
        policy = AgentPolicy(suspect.agent, seed=seed)
        run_episodes(env, policy, seed=seed, recorders=[recorder], max_steps=steps)
    finally:
        close = getattr(env, "close", None)
        if close is not None:
            close()
    return torch.stack(recorder.obs), torch.stack(recorder.running)


@torch.no_grad()
def probe_features(suspect: Suspect, settings: ProbeSettings) -> dict[str, float]:
    """The probe's features of one suspect (empty where it has no candidates or no episode lasts long enough)."""
    candidates = candidates_for(suspect, settings)
    if not candidates:
        return {}
    steps = settings.at + settings.after + 1
    obs, running = record_clean_episodes(suspect, settings.episodes, steps, settings.seed)  # (T, E, obs_dim), (T, E)
    if obs.shape[0] < steps:
        return {}
    keep = running[steps - 1]  # episodes still running at the read-out step
    if not bool(keep.any()):
        return {}
    obs = obs[:, keep]
    n, arms = obs.shape[1], len(candidates) + 1
    batch = obs.repeat(1, arms, 1)  # arm a's episodes at columns a * n ... (a + 1) * n
    for a, candidate in enumerate(candidates, start=1):
        values, mask = candidate
        view = batch[settings.at, a * n : (a + 1) * n]
        batch[settings.at, a * n : (a + 1) * n] = view * (1 - mask) + values * mask
    agent = suspect.agent
    starts = torch.zeros(steps, arms * n, dtype=torch.bool)
    starts[0] = True
    out = agent.unroll(batch, agent.initial_state(arms * n), starts, return_states=True)
    assert out.states is not None
    state = torch.cat([torch.cat([layer.h, layer.c], -1) for layer in out.states], -1)  # (T, arms * n, S)
    state = state.view(steps, arms, n, -1)
    diff = (state[:, 1:] - state[:, :1]).pow(2).mean(-1).sqrt().mean(-1)  # (T, candidates)
    right_after, later = diff[settings.at], diff[steps - 1]
    ratio = later / right_after.clamp_min(1e-6)
    return {
        "divergence_max": float(later.max()), "divergence_mean": float(later.mean()),
        "persistence_max": float(ratio.max()), "persistence_of_largest": float(ratio[int(later.argmax())]),
    }  # fmt: skip
