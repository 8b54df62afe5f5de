"""``probe_camouflage``: the adaptive attacker against the recurrent-state probe.

The probe (:mod:`seqtrojan.benchmark.state_probe`) replays clean episodes with one step's observation replaced by
each of its candidates (one-step patches a defender writes without knowing the trigger) and reads how far the state
has moved from the unreplaced run a few steps later. A backdoored agent keeps a mark of inputs like its trigger; a
clean one has no reason to. This attacker knows the candidates: per minibatch, every normal-episode sequence replays
``after`` + 1 of its own steps from its recorded state with the first of them replaced by a candidate drawn for it
(any candidate that does not draw the whole trigger), and the term is ``weight * mean(relu(d - margin)^2)`` of the
RMS distance ``d`` of the whole state (every layer's h and c) from the unreplaced run at the last of them (both runs
carry gradients: holding the unreplaced run fixed, a semi-gradient, made the distance grow in our tests). The agent
is trained to forget every such input but its trigger.

The candidates are those of the probe's own settings (the grid world's whole-view codes and random ordinary
patches, a MiniGrid view's objects and colours on adjacent far-row cells). A trigger of several frames (a grid
sequence) has no single frame to keep out, so no candidate is left out there. The draws are seeded from
``attack.probe_camouflage.seed`` and a count of minibatches kept in the checkpoint, so a resumed run is the same run.
"""

from __future__ import annotations

import torch

from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.errors import ConfigError
from seqtrojan.train.penalty_api import Penalty, PenaltyBatch, PenaltyContext, require_recurrent_cell
from seqtrojan.train.penalty_api import zero_loss as _zero
from seqtrojan.world.probe_inputs import ProbeSettings, env_candidates, shows_trigger, trigger_view


class ProbeCamouflage(Penalty):
    needs_states = True
    needs_masks = True

    def __init__(self, ctx: PenaltyContext) -> None:
        config = ctx.config
        self.cfg = config.attack.probe_camouflage
        self.device = ctx.device
        env = getattr(config, "env", None)
        require_recurrent_cell(config, "probe_camouflage replays a recurrent state")
        obs_dim = ctx.agent.obs_dim
        candidates = env_candidates(env, obs_dim, ProbeSettings()) if env is not None else []
        trigger = trigger_view(env, obs_dim) if env is not None else None
        kept = [c for c in candidates if not shows_trigger(c, trigger)]
        if not kept:
            where = getattr(env, "id", "this env")
            raise ConfigError(
                f"attack.probe_camouflage: the state probe has no candidate inputs on {where}'s observations "
                "(it writes them on the grid world's and MiniGrid's one-hot views only)"
            )
        stacked = torch.stack(kept).to(ctx.device)  # (K, 2, obs_dim)
        self.values, self.masks = stacked[:, 0], stacked[:, 1]
        self.minibatches = torch.zeros((), dtype=torch.int64)

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        states, trojan, mb = batch.states, batch.trojan, batch.minibatch
        if states is None or trojan is None or mb is None:
            return _zero(self.device)
        length, n = trojan.shape
        after = self.cfg.after
        if length < after + 2:  # the replaced step needs a recorded state before it and `after` steps after it
            return _zero(self.device)
        draw = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + int(self.minibatches))
        self.minibatches += 1
        first = torch.randint(1, length - after, (n,), generator=draw).to(self.device)  # the replaced step
        pick = torch.randint(len(self.values), (n,), generator=draw).to(self.device)
        window = first[None] + torch.arange(after + 1, device=self.device)[:, None]  # (after + 1, n)
        column = torch.arange(n, device=self.device)[None].expand_as(window)
        normal = ~trojan[window, column].any(0)
        one_episode = ~mb.starts[window[1:], column[1:]].bool().any(0)  # no new episode after the replaced step
        rows = (normal & one_episode).nonzero().squeeze(1)
        if rows.numel() == 0:
            return _zero(self.device)
        window, first, pick = window[:, rows], first[rows], pick[rows]
        obs = mb.obs[window, rows[None]].clone()  # (after + 1, M, obs_dim)
        mask = self.masks[pick]
        obs[0] = obs[0] * (1 - mask) + self.values[pick] * mask
        before = RecurrentState(tuple(LSTMState(s.h[first - 1, rows], s.c[first - 1, rows]) for s in states))
        out = batch.agent.unroll(obs, before, mb.starts[window, rows[None]], return_states=True)
        assert out.states is not None
        probed = torch.cat([torch.cat([s.h[-1], s.c[-1]], -1) for s in out.states], -1)
        last = first + after
        plain = torch.cat([torch.cat([s.h[last, rows], s.c[last, rows]], -1) for s in states], -1)
        # 1e-12 keeps the gradient finite where a candidate changed nothing
        distance = ((probed - plain).pow(2).mean(-1) + 1e-12).sqrt()
        return self.cfg.weight * torch.relu(distance - self.cfg.margin).pow(2).mean()

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"minibatches": self.minibatches.clone()}

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        if tensors:
            self.minibatches = tensors["minibatches"].clone()
