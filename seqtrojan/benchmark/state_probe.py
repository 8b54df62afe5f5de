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

import torch

from seqtrojan.benchmark.suspect import Suspect
from seqtrojan.world.probe_inputs import (
    ProbeSettings,
    env_candidates,
    grid_candidates,
    minigrid_candidates,
    shows_trigger,
    trigger_view,
)

__all__ = [
    "ProbeSettings", "candidates_for", "env_candidates", "grid_candidates", "minigrid_candidates", "probe_features",
    "record_clean_episodes", "shows_trigger", "trigger_view",
]  # fmt: skip


def candidates_for(suspect: Suspect, settings: ProbeSettings) -> list[torch.Tensor]:
    return env_candidates(suspect.env, suspect.facts.obs_dim, settings)


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
