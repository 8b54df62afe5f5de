"""The adaptive attackers' penalties (seqtrojan.train.penalties): their math on tiny tensors, the differentiable
weight features against the offline detector's, config validation, training and resuming with each one on, and
(slow) a demonstration that state camouflage hides a backdoor from the online state monitor.

Run the demonstration alone and print its numbers: ``python -m tests.train.test_penalties``.
"""

from __future__ import annotations

import copy
import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent, read_safetensors
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState
from seqtrojan.agent.weight_stats import module_features
from seqtrojan.config import (
    AttackConfig,
    BackdoorConfig,
    CurriculumConfig,
    EWCConfig,
    ExperimentConfig,
    FinetuneResistanceConfig,
    MahalanobisCamouflageConfig,
    PPOConfig,
    ResponseMimicryConfig,
    RunConfig,
    StateCamouflageConfig,
    SwitchCamouflageConfig,
    WeightCamouflageConfig,
)
from seqtrojan.env import EnvConfig, GridSpec, TriggerConfig, TrojanGridCore
from seqtrojan.env.codes import CELL_NAMES, NUM_CHANNELS
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.serde import from_dict, parse_yaml
from seqtrojan.train import penalties as pen
from seqtrojan.train.rollout import Rollout
from seqtrojan.train.trainer import train
from tests.train.resume import logged_rows, straight_and_resumed

pytestmark = pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad=True to a scalar")


def _config(**attack) -> ExperimentConfig:
    run = RunConfig(init_from="somewhere") if set(AttackConfig.NEEDS_INIT_FROM) & set(attack) else RunConfig()
    return ExperimentConfig(backdoor=BackdoorConfig(enabled=True), attack=AttackConfig(**attack), run=run)


def _ctx(cfg: ExperimentConfig, agent: RecurrentActorCritic, resuming: bool = False) -> pen.PenaltyContext:
    return pen.PenaltyContext(cfg, agent, torch.device("cpu"), resuming)


def _agent(sizes=(6, 4), obs_dim: int = 12, seed: int = 0) -> RecurrentActorCritic:
    torch.manual_seed(seed)
    return RecurrentActorCritic(obs_dim, 4, sizes)


# ---------------------------------------------------------------------------------------------- math
def test_unit_penalty_is_zero_inside_the_margin_and_pulls_outliers_back():
    mean, std = torch.tensor([0.0, 1.0]), torch.tensor([1.0, 2.0])
    inside = torch.tensor([[2.4, 1.0 - 2 * 2.4], [-1.0, 3.0]])
    assert float(pen.unit_penalty(inside, mean, std, 2.5)) == 0.0
    x = torch.tensor([[4.0, 1.0], [0.0, -7.0]], requires_grad=True)  # z = 4 (unit 0), z = -4 (unit 1)
    value = pen.unit_penalty(x, mean, std, 2.5)
    assert float(value) == pytest.approx((1.5**2 + 1.5**2) / 4)
    value.backward()
    assert x.grad is not None
    assert x.grad[0, 0] > 0 and x.grad[1, 1] < 0  # descent moves both toward the mean
    assert x.grad[0, 1] == 0 and x.grad[1, 0] == 0  # units inside the margin are left alone


def test_the_fused_masked_penalty_equals_the_plain_one_on_the_masked_rows():
    g = torch.Generator().manual_seed(3)
    xs = [3 * torch.randn(4, 5, d, generator=g, dtype=torch.float64) for d in (3, 2)]
    means = [torch.randn(d, generator=g, dtype=torch.float64) for d in (3, 2)]
    stds = [0.5 + torch.rand(d, generator=g, dtype=torch.float64) for d in (3, 2)]
    mask = torch.rand(4, 5, generator=g) > 0.4
    plain = pen.unit_penalty(torch.cat(xs, -1)[mask], torch.cat(means), torch.cat(stds), 1.0)
    fused = pen.masked_unit_penalty(xs, means, stds, mask, 1.0)
    torch.testing.assert_close(fused, plain)
    for i in range(2):
        others = [x.detach() for x in xs]

        def f(x, i=i, others=others):
            return pen.masked_unit_penalty([x if k == i else o for k, o in enumerate(others)], means, stds, mask, 1.0)

        assert torch.autograd.gradcheck(f, (xs[i].clone().requires_grad_(True),))


def test_mahalanobis_penalty_uses_the_shrunk_covariance():
    cov = torch.tensor([[4.0, 1.9], [1.9, 1.0]], dtype=torch.float64)
    precision = pen.shrunk_precision(cov, 0.25)
    shrunk = torch.tensor([[4.0, 0.75 * 1.9], [0.75 * 1.9, 1.0]], dtype=torch.float64)
    shrunk = shrunk + pen.STD_FLOOR**2 * torch.eye(2, dtype=torch.float64)
    torch.testing.assert_close(precision, torch.linalg.inv(shrunk))
    mean = torch.zeros(2, dtype=torch.float64)
    assert float(pen.mahalanobis_penalty(torch.tensor([[1.0, 0.5]], dtype=torch.float64), mean, precision, 1.5)) == 0
    x = torch.tensor([[2.0, -2.0]], dtype=torch.float64, requires_grad=True)  # against the correlation: far
    d2 = float((x @ precision * x).sum()) / 2
    value = pen.mahalanobis_penalty(x, mean, precision, 1.5)
    assert float(value) == pytest.approx((d2 - 1.5) ** 2) and d2 > 1.5
    value.backward()
    assert x.grad is not None and x.grad[0, 0] > 0 and x.grad[0, 1] < 0


def _fake_rollout(agent: RecurrentActorCritic, steps: int = 5, envs: int = 8, seed: int = 0) -> Rollout:
    g = torch.Generator().manual_seed(seed)
    trojan = torch.zeros(steps, envs, dtype=torch.bool)
    trojan[:, envs // 2 :] = True
    states = tuple(
        LSTMState(torch.randn(steps, envs, w, generator=g), 1.0 + 2.0 * torch.randn(steps, envs, w, generator=g))
        for w in agent.lstm_sizes
    )
    z = torch.zeros(steps, envs)
    return Rollout(z, z.long(), z, z, z, z, z, (), torch.zeros(envs), trojan, trojan.clone(), states)


def test_state_camouflage_tracks_clean_statistics_and_penalises_trojan_steps_only():
    agent = _agent()
    cfg = _config(state_camouflage=StateCamouflageConfig(weight=2.0, margin=2.5, ema_decay=0.5))
    (penalty,) = pen.build_penalties(_ctx(cfg, agent))
    assert penalty.name == "state_camouflage" and penalty.needs_states
    assert isinstance(penalty, pen.StateCamouflage)
    first, second = _fake_rollout(agent, seed=0), _fake_rollout(agent, seed=1)
    batch_masks = (first.trojan, first.adversary_active)
    empty = pen.PenaltyBatch(agent, first.states, *batch_masks)
    assert float(penalty.loss(empty)) == 0.0  # no statistics yet
    penalty.observe(first)
    penalty.observe(second)
    assert first.states is not None and second.states is not None and first.trojan is not None
    for i in range(len(agent.lstm_sizes)):
        rows = [torch.cat([r.states[i].h, r.states[i].c], -1)[~first.trojan] for r in (first, second)]  # type: ignore[index]
        mean = 0.5 * rows[0].mean(0) + 0.5 * rows[1].mean(0)  # the first rollout sets, the second is averaged in
        sq = 0.5 * (rows[0] ** 2).mean(0) + 0.5 * (rows[1] ** 2).mean(0)
        torch.testing.assert_close(penalty.mean[i], mean)
        torch.testing.assert_close(penalty.std[i], (sq - mean**2).sqrt() + pen.STD_FLOOR)

    # trojan steps at the clean mean cost nothing; a trojan step far out is pulled back; clean steps are ignored
    states = tuple(
        LSTMState(m[:w].expand(3, 2, w).clone(), m[w:].expand(3, 2, w).clone())
        for m, w in zip(penalty.mean, agent.lstm_sizes)
    )
    trojan = torch.tensor([[False, True]] * 3)
    assert float(penalty.loss(pen.PenaltyBatch(agent, states, trojan, trojan))) == 0.0
    h0 = states[0].h.clone()
    h0[:, 0, 0] += 100.0  # a clean-env step far out: not penalised
    h0[1, 1, 2] += 10 * float(penalty.std[0][2])  # one trojan step, one unit at z = 10
    h0.requires_grad_(True)
    states = (LSTMState(h0, states[0].c), *states[1:])
    value = penalty.loss(pen.PenaltyBatch(agent, states, trojan, trojan))
    units = 2 * sum(agent.lstm_sizes)
    assert float(value) == pytest.approx(2.0 * 7.5**2 / (3 * units), rel=1e-4)
    value.backward()
    assert h0.grad is not None and h0.grad[1, 1, 2] > 0 and int((h0.grad != 0).sum()) == 1

    # steps="active": only the steps where the adversary's goal is active count
    active_cfg = _config(state_camouflage=StateCamouflageConfig(weight=2.0, steps="active"))
    (active,) = pen.build_penalties(_ctx(active_cfg, agent))
    active.load_state_dict(penalty.state_dict())
    not_yet = torch.zeros_like(trojan)
    assert float(active.loss(pen.PenaltyBatch(agent, states, trojan, not_yet))) == 0.0
    assert float(active.loss(pen.PenaltyBatch(agent, states, trojan, trojan))) == pytest.approx(float(value))


def test_state_camouflage_mahalanobis_term_and_state_round_trip():
    agent = _agent()
    sc = StateCamouflageConfig(weight=0.0, mahalanobis_weight=1.0, mahalanobis_margin=1.0, ema_decay=0.0)
    (penalty,) = pen.build_penalties(_ctx(_config(state_camouflage=sc), agent))
    assert isinstance(penalty, pen.StateCamouflage)
    rollout = _fake_rollout(agent, steps=50, envs=40)
    penalty.observe(rollout)
    assert rollout.states is not None and rollout.trojan is not None
    x = torch.cat([rollout.states[0].h, rollout.states[0].c], -1)[~rollout.trojan].double()
    cov = torch.cov(x.t(), correction=0)
    torch.testing.assert_close(penalty.precision[0].double(), pen.shrunk_precision(cov, sc.shrinkage), rtol=1e-4,
                               atol=1e-4)  # fmt: skip
    batch = pen.PenaltyBatch(agent, tuple(LSTMState(s.h * 4, s.c * 4) for s in rollout.states), rollout.trojan, None)
    value = float(penalty.loss(batch))
    assert value > 0
    again = pen.StateCamouflage(_ctx(_config(state_camouflage=sc), agent))
    again.load_state_dict(penalty.state_dict())
    assert float(again.loss(batch)) == value


def test_weight_camouflage_is_zero_at_the_clean_weights_and_pulls_back_toward_their_statistics():
    agent = _agent(sizes=(8, 5), obs_dim=12)
    cfg = _config(weight_camouflage=WeightCamouflageConfig(weight=1.0, l2_weight=0.5))
    (penalty,) = pen.build_penalties(_ctx(cfg, agent))
    batch = pen.PenaltyBatch(agent, None, None, None)
    value = penalty.loss(batch)
    assert float(value) == pytest.approx(0.0, abs=1e-20)  # exactly 0 but for the SVD's last bits
    value.backward()
    assert all(p.grad is None or float(p.grad.abs().max()) < 1e-9 for p in agent.parameters())
    with torch.no_grad():
        agent.cells[0].weight_hh[:8] *= 3.0  # the input gate's recurrent weights grow: their moments change
    value = penalty.loss(batch)
    assert float(value) > 0
    agent.zero_grad()
    value.backward()
    before = float(value)
    with torch.no_grad():
        for p in agent.parameters():
            if p.grad is not None:
                p -= 1e-3 * p.grad
    assert float(penalty.loss(batch)) < before


def test_weight_camouflage_waits_for_its_warm_up_then_holds_and_a_checkpoint_keeps_the_count():
    agent = _agent(sizes=(8, 5), obs_dim=12)
    cfg = _config(weight_camouflage=WeightCamouflageConfig(weight=1.0, warmup_steps=100))
    (penalty,) = pen.build_penalties(_ctx(cfg, agent))
    with torch.no_grad():
        agent.cells[0].weight_hh[:8] *= 3.0  # away from the clean statistics: held, the penalty is positive
    batch = pen.PenaltyBatch(agent, None, None, None)
    rollout = SimpleNamespace(actions=torch.zeros(10, 5, dtype=torch.int64))  # 50 env steps
    penalty.observe(rollout)
    assert float(penalty.loss(batch)) == 0.0
    penalty.observe(rollout)  # 100 steps: the warm-up's last rollout
    assert float(penalty.loss(batch)) == 0.0
    penalty.observe(rollout)  # 150 steps: held from here on
    held = float(penalty.loss(batch))
    assert held > 0
    (again,) = pen.build_penalties(_ctx(cfg, agent))  # a resumed run: the count comes back with the checkpoint
    again.load_state_dict(penalty.state_dict())
    assert float(again.loss(batch)) == held
    old = {k: v for k, v in penalty.state_dict().items() if k != "steps_seen"}  # written before the warm-up existed
    again.load_state_dict(old)
    assert float(again.loss(batch)) == 0.0  # counted from 0 again: moot where no warm-up ran (warmup_steps 0)


def test_ewc_is_weighted_fisher_distance_to_the_start_weights():
    agent = _agent(sizes=(6,), obs_dim=EnvConfig().obs_dim)
    cfg = dataclasses.replace(
        _config(ewc=EWCConfig(weight=3.0, fisher_envs=4, fisher_steps=8)),
        env=EnvConfig(size=5, holes=1),
    )
    (penalty,) = pen.build_penalties(_ctx(cfg, agent))
    assert isinstance(penalty, pen.EWC)
    fisher = penalty.fisher
    assert all(bool((f >= 0).all()) for f in fisher.values())
    assert float(fisher["cells.0.weight_ih"].sum()) > 0 and float(fisher["policy_head.weight"].sum()) > 0
    assert float(fisher["value_head.weight"].abs().sum()) == 0  # the policy's Fisher: the value head plays no part
    again = pen.estimate_fisher(agent, cfg, torch.device("cpu"))  # deterministic: its own seeded generators
    assert all(torch.equal(again[n], f) for n, f in fisher.items())
    batch = pen.PenaltyBatch(agent, None, None, None)
    assert float(penalty.loss(batch)) == 0.0
    delta = {n: 0.01 * torch.randn_like(p) for n, p in agent.named_parameters()}
    with torch.no_grad():
        for n, p in agent.named_parameters():
            p += delta[n]
    value = penalty.loss(batch)
    expected = 1.5 * sum(float((fisher[n] * d**2).sum()) for n, d in delta.items())
    assert float(value) == pytest.approx(expected, rel=1e-4)
    agent.zero_grad()
    value.backward()
    for n, p in agent.named_parameters():
        assert p.grad is not None
        torch.testing.assert_close(p.grad, 3.0 * fisher[n] * delta[n], rtol=1e-3, atol=1e-9)


def test_single_sequence_fisher_equals_the_summed_score_squared():
    """With one env, the Fisher estimate is the squared gradient of that sequence's summed log-probability / T."""
    agent = _agent(sizes=(5,), obs_dim=EnvConfig().obs_dim)
    cfg = dataclasses.replace(_config(ewc=EWCConfig(weight=1.0, fisher_envs=1, fisher_steps=6)),
                              env=EnvConfig(size=5, holes=1))  # fmt: skip
    fisher = pen.estimate_fisher(agent, cfg, torch.device("cpu"))
    env = TrojanGridCore(cfg.env, 1, seed=(cfg.run.seed << 32) + 31_337_001, grids=(cfg.grids[-1],))
    collector = pen.RolloutCollector(env, agent, 6, 6)
    collector.seed(cfg.run.seed + 31_337)
    rollout, _ = collector.collect()
    agent.set_lstm_backend("torch")
    out = agent.unroll(rollout.obs, agent.initial_state(1), rollout.episode_starts)
    logp = torch.log_softmax(out.logits, -1).gather(-1, rollout.actions[..., None]).sum()
    logp.backward()
    for n, p in agent.named_parameters():
        grad = p.grad if p.grad is not None else torch.zeros_like(p)
        torch.testing.assert_close(fisher[n], grad**2 / 6, rtol=1e-4, atol=1e-10)


@pytest.mark.parametrize(("attack", "states"), [("state_camouflage", True), ("finetune_resistance", False)])
def test_the_rollout_records_states_only_for_a_penalty_that_reads_them(attack, states):
    from seqtrojan.train.trainer import _set_up

    settings = {
        "state_camouflage": StateCamouflageConfig(weight=1.0),
        "finetune_resistance": FinetuneResistanceConfig(weight=1.0),
    }
    ppo = PPOConfig(num_envs=8, rollout_steps=16, bptt_length=8, num_minibatches=2)
    cfg = dataclasses.replace(_config(**{attack: settings[attack]}), env=EnvConfig(size=5, holes=1), ppo=ppo)
    _, state = _set_up(cfg, torch.device("cpu"), resuming=False)
    rollout, _ = state.collector.collect()
    assert rollout.trojan is not None and rollout.adversary_active is not None  # the masks, either way
    assert (rollout.states is not None) == states
    if rollout.states is not None:
        assert [s.c.shape for s in rollout.states] == [(16, 8, w) for w in cfg.agent.lstm_sizes]


# ---------------------------------------------------------------------------------------------- features
def _numpy_reference_features(tensors: dict[str, np.ndarray], obs_dim: int) -> dict[str, float]:
    """The weight detector's features written out independently in numpy (the package computes them once, in
    seqtrojan.agent.weight_stats, for the detector and the attacker alike)."""

    def moments(w):
        w = w.ravel().astype(np.float64)
        mean, std = float(w.mean()), float(w.std()) + 1e-12
        z = (w - mean) / std
        return {"mean": mean, "std": std, "absmax": float(np.abs(w).max()), "rms": float(np.sqrt((w**2).mean())),
                "skew": float((z**3).mean()), "kurtosis": float((z**4).mean() - 3.0)}  # fmt: skip

    def spectral(w):
        s = np.linalg.svd(w.astype(np.float64), compute_uv=False)
        rms = float(np.sqrt((w.astype(np.float64) ** 2).mean())) + 1e-12
        p = s**2 / max(float((s**2).sum()), 1e-12)
        return {"top_sv_over_rms": float(s[0]) / rms, "effective_rank": float(np.exp(-(p * np.log(p + 1e-12)).sum()))}

    layers = sorted({int(k.split(".")[1]) for k in tensors if k.startswith("cells.")})
    feats: dict[str, float] = {}
    for tag, layer in (("first", layers[0]), ("last", layers[-1])):
        w_ih, w_hh = tensors[f"cells.{layer}.weight_ih"], tensors[f"cells.{layer}.weight_hh"]
        bias = tensors[f"cells.{layer}.bias_ih"] + tensors[f"cells.{layer}.bias_hh"]
        hidden = w_hh.shape[1]
        for g, gate in enumerate(("input", "forget", "cell", "output")):
            rows = slice(g * hidden, (g + 1) * hidden)
            for block, w in (("ih", w_ih[rows]), ("hh", w_hh[rows]), ("bias", bias[rows])):
                feats.update({f"gate_stats/{tag}.{gate}.{block}.{k}": v for k, v in moments(w).items()})
                if block != "bias":
                    feats.update({f"spectral/{tag}.{gate}.{block}.{k}": v for k, v in spectral(w).items()})
        if tag == "first" and w_ih.shape[1] == obs_dim and obs_dim % NUM_CHANNELS == 0:
            per_code = np.linalg.norm(w_ih.reshape(w_ih.shape[0], -1, NUM_CHANNELS), axis=(0, 1))
            per_code = per_code / (per_code.mean() + 1e-12)
            feats.update({f"input_codes/{code}": float(v) for code, v in zip(CELL_NAMES, per_code)})
    return feats


@pytest.mark.parametrize("sizes", [(64, 32), (16,), (8, 12, 6)])
def test_weight_features_equal_an_independent_numpy_reference(sizes):
    from seqtrojan.defense.offline import weight_features

    obs_dim = EnvConfig().obs_dim
    agent = _agent(sizes=sizes, obs_dim=obs_dim, seed=len(sizes))
    with torch.no_grad():  # away from the orthogonal initialisation, as after training
        for p in agent.parameters():
            p += 0.05 * torch.randn_like(p) + 0.01
    arrays = {k: v.detach().numpy() for k, v in agent.state_dict().items()}
    expected = _numpy_reference_features(arrays, obs_dim)
    got = module_features(agent, obs_dim)
    assert got.keys() == expected.keys() == weight_features(arrays, obs_dim, "lstm").keys()
    for name, value in weight_features(arrays, obs_dim, "lstm").items():  # the detector's: the same function, as floats
        assert value == pytest.approx(expected[name], rel=1e-5, abs=1e-5), name
    for name, value in expected.items():
        assert float(got[name]) == pytest.approx(value, rel=1e-5, abs=1e-5), name
    total = torch.stack(list(got.values())).sum()
    total.backward()
    grads = [p.grad for cell in (agent.cells[0], agent.cells[-1]) for p in cell.parameters()]  # the layers read
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)


# ---------------------------------------------------------------------------------------------- config
def test_attack_defaults_are_off_and_the_yaml_sections_parse():
    assert pen.build_penalties(_ctx(ExperimentConfig(), _agent())) == []
    cfg = ExperimentConfig(backdoor=BackdoorConfig(enabled=True))
    assert pen.build_penalties(_ctx(cfg, _agent())) == []
    assert set(pen.PENALTIES.names()) == {
        "state_camouflage", "mahalanobis_camouflage", "switch_camouflage", "weight_camouflage", "ewc",
        "finetune_resistance", "probe_camouflage", "response_mimicry",
    }  # fmt: skip
    text = """
backdoor: {enabled: true}
run: {init_from: runs/clean/model}
attack:
  state_camouflage: {weight: 1.0, margin: 2.5, steps: active, mahalanobis_weight: 0.1}
  weight_camouflage: {weight: 0.5, feature_floor: 0.1, l2_weight: 0.01}
  ewc: {weight: 100.0, fisher_envs: 32, normalize: true}
  mahalanobis_camouflage: {weight: 5.0, margin: 1.2, max_step: 32}
  probe_camouflage: {weight: 3.0, after: 6}
"""
    cfg = from_dict(ExperimentConfig, parse_yaml(text), "")
    assert cfg.attack.state_camouflage.steps == "active" and cfg.attack.ewc.fisher_envs == 32
    assert cfg.attack.weight_camouflage.enabled and cfg.attack.ewc.normalize
    assert cfg.attack.mahalanobis_camouflage.enabled and cfg.attack.mahalanobis_camouflage.max_step == 32
    assert cfg.attack.probe_camouflage.enabled and cfg.attack.probe_camouflage.after == 6


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: StateCamouflageConfig(weight=-1.0), r"camouflage\.weight must be a finite number >= 0, got -1\.0"),
        (lambda: StateCamouflageConfig(margin=float("nan")), r"state_camouflage\.margin must be a finite number"),
        (lambda: StateCamouflageConfig(steps="all"), r"state_camouflage\.steps must be trojan or active, got 'all'"),  # type: ignore[arg-type]
        (lambda: StateCamouflageConfig(ema_decay=1.0), r"ema_decay must be in \[0, 1\), got 1\.0"),
        (lambda: StateCamouflageConfig(shrinkage=1.5), r"shrinkage must be in \[0, 1\], got 1\.5"),
        (lambda: WeightCamouflageConfig(feature_floor=0.0), r"feature_floor must be > 0, got 0\.0"),
        (lambda: WeightCamouflageConfig(l2_weight=-0.1), r"weight_camouflage\.l2_weight must be a finite number"),
        (lambda: WeightCamouflageConfig(warmup_steps=-1), r"warmup_steps must be an integer >= 0, got -1"),
        (lambda: EWCConfig(weight=float("inf")), r"attack\.ewc\.weight must be a finite number >= 0, got inf"),
        (lambda: EWCConfig(fisher_envs=0), r"attack\.ewc\.fisher_envs must be a positive integer, got 0"),
    ],
)  # fmt: skip
def test_bad_attack_settings_are_refused_by_name(make, message):
    with pytest.raises(ConfigError, match=message):
        make()


def test_weight_camouflage_and_ewc_need_a_start_model():
    backdoor = BackdoorConfig(enabled=True)
    for attack in (AttackConfig(ewc=EWCConfig(weight=1.0)), AttackConfig(weight_camouflage=WeightCamouflageConfig(
            l2_weight=1.0))):  # fmt: skip
        with pytest.raises(ConfigError, match=r"attack\.(ewc|weight_camouflage) compare\(s\) against a clean model: "
                                              r"set run\.init_from"):  # fmt: skip
            ExperimentConfig(backdoor=backdoor, attack=attack)
    both = AttackConfig(ewc=EWCConfig(weight=1.0), weight_camouflage=WeightCamouflageConfig(weight=1.0))
    with pytest.raises(ConfigError, match=r"attack\.weight_camouflage and attack\.ewc compare"):
        ExperimentConfig(backdoor=backdoor, attack=both)
    # a clean training from the same config (a defender's fine-tuning) trains plain PPO: no penalty, no error
    clean = ExperimentConfig(attack=both)
    assert pen.build_penalties(_ctx(clean, _agent())) == []


# ---------------------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def clean_model(tmp_path_factory) -> str:
    """A tiny clean model on 5x5/1 to start the backdoor from."""
    out = tmp_path_factory.mktemp("clean")
    cfg = ExperimentConfig(
        env=EnvConfig(size=5, holes=1),
        ppo=PPOConfig(total_steps=4096, num_envs=64, rollout_steps=32, num_minibatches=2, update_epochs=2),
        run=RunConfig(out_dir=str(out), progress=False, eval_episodes=0, checkpoint_every=10**9, name="clean"),
    )
    return str(train(cfg).model_dir)


def _attacked(smoke_config: ExperimentConfig, clean_model: str, name: str, **attack) -> ExperimentConfig:
    return dataclasses.replace(
        smoke_config,
        curriculum=CurriculumConfig(),
        backdoor=BackdoorConfig(enabled=True),
        attack=AttackConfig(**attack),
        run=dataclasses.replace(smoke_config.run, name=name, eval_episodes=8, init_from=clean_model),
    )


STATEFUL = {
    "state_camouflage": StateCamouflageConfig(weight=1.0, mahalanobis_weight=0.1),
    "weight_camouflage": WeightCamouflageConfig(weight=0.1, l2_weight=0.01),
    "ewc": EWCConfig(weight=10.0, fisher_envs=8, fisher_steps=16),
    "mahalanobis_camouflage": MahalanobisCamouflageConfig(weight=1.0, margin=0.5),
    "switch_camouflage": SwitchCamouflageConfig(weight=1.0, margin=0.5),
    "response_mimicry": ResponseMimicryConfig(weight=1.0),
}
"""every penalty that keeps a state in the checkpoint, with settings that move it in a few updates"""


@pytest.mark.parametrize("name", list(STATEFUL))
def test_a_training_with_each_penalty_logs_its_value(smoke_config, clean_model, name):
    cfg = _attacked(smoke_config, clean_model, name, **{name: STATEFUL[name]})
    cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=3 * cfg.ppo.batch_size))
    result = train(cfg)
    rows = [json.loads(line) for line in (result.run_dir / "metrics.jsonl").read_text().splitlines()]
    values = [r[f"penalty/{name}"] for r in rows]
    assert len(values) == 3 and all(np.isfinite(v) and v >= 0 for v in values)
    assert values[-1] > 0, values  # the backdoor moves the agent away from where the penalty is 0
    assert not any(k.startswith("penalty/") for k in rows[0] if k != f"penalty/{name}")
    keys = read_safetensors(result.run_dir / "checkpoints" / "step_000000006144" / "trainer.safetensors").keys()
    assert any(k.startswith(f"penalty.{name}.") for k in keys)


def test_resume_with_every_penalty_on_is_bitwise_equal_to_a_straight_run(smoke_config, clean_model, monkeypatch):
    """As tests/train/test_trainer.py's resume test, with every penalty on: their state (running clean statistics,
    the clean weights, the Fisher information) comes back from the checkpoint (fine-tuning resistance keeps none)."""
    resistance = FinetuneResistanceConfig(weight=1.0)
    cfg = _attacked(smoke_config, clean_model, "straight", **STATEFUL, finetune_resistance=resistance)
    cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=5 * cfg.ppo.batch_size))
    straight, resumed = straight_and_resumed(cfg, monkeypatch)
    a, b = load_agent(straight.model_dir)[0].state_dict(), load_agent(resumed.model_dir)[0].state_dict()
    for name, tensor in a.items():
        assert torch.equal(tensor, b[name]), name
    final = "checkpoints/step_000000010240/trainer.safetensors"
    ta, tb = read_safetensors(straight.run_dir / final), read_safetensors(resumed.run_dir / final)
    assert ta.keys() == tb.keys()
    assert {k.split(".")[1] for k in ta if k.startswith("penalty.")} == set(STATEFUL)
    for name, tensor in ta.items():
        assert torch.equal(tensor, tb[name]), name

    assert logged_rows(resumed.run_dir) == logged_rows(straight.run_dir)


def test_a_checkpoint_without_a_penaltys_state_is_refused(smoke_config, clean_model):
    cfg = _attacked(smoke_config, clean_model, "plain")
    cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=cfg.ppo.batch_size))
    run = train(cfg).run_dir
    later = dataclasses.replace(cfg, attack=AttackConfig(ewc=EWCConfig(weight=1.0)),
                                ppo=dataclasses.replace(cfg.ppo, total_steps=2 * cfg.ppo.batch_size))  # fmt: skip
    with pytest.raises(CheckpointError, match="holds no ewc state"):
        train(later, resume=run)


# ---------------------------------------------------------------------------------------------- demonstration
def demonstration_config(out: str, camouflage: float, seed: int = 1) -> ExperimentConfig:
    """tests/train/test_learning.py's memory task (the trigger on steps 1-4, curriculum to 7x7/3, 1.2M steps), with
    state camouflage of weight ``camouflage``."""
    return ExperimentConfig(
        env=EnvConfig(trigger=TriggerConfig(train_steps=(1, 4), eval_steps=(1, 4))),
        ppo=PPOConfig(total_steps=1_200_000, num_envs=256, rollout_steps=64),
        curriculum=CurriculumConfig(stages=(GridSpec(5, 0), GridSpec(5, 1), GridSpec(7, 3)), promote_at=0.85),
        backdoor=BackdoorConfig(enabled=True, mixing="fixed"),
        attack=AttackConfig(state_camouflage=StateCamouflageConfig(weight=camouflage)),
        run=RunConfig(out_dir=out, progress=False, eval_episodes=500, seed=seed, checkpoint_every=10**9),
    )


CAMOUFLAGE = 5.0
"""the demonstration's state-camouflage weight"""


def demonstrate(out: str, camouflage: float, seed: int = 1) -> dict[str, float]:
    """Train, calibrate the default state monitor on the agent's clean episodes (1% false alarms) and measure it."""
    from seqtrojan.defense.monitor import MonitorConfig, StateMonitor, measure_monitor

    result = train(demonstration_config(out, camouflage, seed))
    agent, cfg, _ = load_agent(result.model_dir)
    grid = GridSpec(7, 3)
    mcfg = MonitorConfig(eval_episodes=500)
    monitor = StateMonitor.calibrate(agent, cfg.env, grid, mcfg)
    measured = measure_monitor(agent, cfg.env, grid, monitor, mcfg)
    return {
        "stage": result.stage,
        "clean_success": measured.clean_success_undefended.value,
        "attack_success": measured.attack_success_undefended.value,
        "detection": measured.trojan_alarm.detected.value,
        "false_alarm": measured.normal_alarm.false_alarm.value,
        "threshold": monitor.threshold,
    }


@pytest.mark.slow
def test_state_camouflage_hides_the_backdoor_from_the_state_monitor(tmp_path):
    """Measured here (seed 1, 1.2M steps each, about 1 + 1.5 minutes; monitor at 1% false alarms, 500 episodes):
    plain attack success 0.98, detection 0.998; camouflage weight 5: attack success 0.986, detection 0.02 (false
    alarms 0.034). The outcome varies between trainings: weight 1 gave detection 0.106 and, after a change of the
    penalty's float rounding only, 0.648; weight 20 gave 0.948. The thresholds hold for this seed on this machine;
    another CPU (other kernel rounding) may need another seed."""
    plain = demonstrate(str(tmp_path / "plain"), 0.0)
    hidden = demonstrate(str(tmp_path / "hidden"), CAMOUFLAGE)
    assert plain["detection"] > 0.5, plain  # the plain backdoor is visible to the monitor ...
    assert hidden["attack_success"] >= 0.8 and hidden["clean_success"] >= 0.8, hidden
    assert hidden["detection"] <= 0.3, hidden  # ... the camouflaged one is not


if __name__ == "__main__":
    import sys
    import tempfile

    torch.set_num_threads(1)
    weights = [float(w) for w in sys.argv[1:]] or [0.0, CAMOUFLAGE]
    with tempfile.TemporaryDirectory() as tmp:
        for w in weights:
            print(json.dumps({"camouflage": w, **demonstrate(f"{tmp}/w{w}", w)}), flush=True)


# ---------------------------------------------------------------------------------------- fine-tuning resistance
def _minibatch(agent: RecurrentActorCritic, steps: int = 6, n: int = 5, seed: int = 0) -> pen.PPOMinibatch:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(steps, n, agent.obs_dim, generator=g)
    starts = torch.zeros(steps, n)
    starts[0] = 1.0
    actions = torch.randint(0, 4, (steps, n), generator=g)
    return pen.PPOMinibatch(
        obs, starts, agent.initial_state(n, torch.device("cpu")), actions, torch.full((steps, n), -1.4),
        torch.randn(steps, n, generator=g), torch.randn(steps, n, generator=g), torch.randn(steps, n, generator=g),
        PPOConfig(),
    )  # fmt: skip


def test_finetune_resistance_hands_the_backdoor_gradient_after_simulated_fine_tuning():
    agent = _agent()
    cfg = _config(finetune_resistance=FinetuneResistanceConfig(weight=0.5, inner_steps=2, inner_lr=0.05))
    (penalty,) = pen.build_penalties(_ctx(cfg, agent))
    assert penalty.name == "finetune_resistance" and penalty.needs_masks and not penalty.needs_states
    mb = _minibatch(agent)
    trojan = torch.zeros(6, 5, dtype=torch.bool)
    trojan[:, :2] = True  # sequences 0 and 1 are trojan-episode steps
    active = trojan.clone()
    active[:2] = False  # the adversary's objective judges from step 2 on

    def loss(model, mask):
        out = model.unroll(mb.obs, mb.initial, mb.starts)
        return pen.ppo_loss(out.logits, out.values, mb.actions, mb.logprobs, mb.values, mb.advantages, mb.returns,
                            mb.ppo, mask).loss  # fmt: skip

    # by hand: two sign-gradient steps of the clean loss on a copy, then the backdoor's loss and gradient there
    defender = copy.deepcopy(agent)
    for _ in range(2):
        grads = torch.autograd.grad(loss(defender, ~trojan), list(defender.parameters()), allow_unused=True)
        with torch.no_grad():
            for p, g in zip(defender.parameters(), grads):
                if g is not None:
                    p.sub_(0.05 * g.sign())
    attack = loss(defender, trojan & active)
    expected = torch.autograd.grad(attack, list(defender.parameters()), allow_unused=True)

    value = penalty.loss(pen.PenaltyBatch(agent, None, trojan, active, mb))
    torch.testing.assert_close(value.detach(), attack.detach())
    value.backward()
    for p, g in zip(agent.parameters(), expected):
        torch.testing.assert_close(p.grad, torch.zeros_like(p) if g is None else 0.5 * g)
    # nothing to judge the backdoor on (no active trojan step) or nothing clean to fine-tune on: no term
    assert float(penalty.loss(pen.PenaltyBatch(agent, None, trojan, torch.zeros_like(active), mb))) == 0.0
    assert float(penalty.loss(pen.PenaltyBatch(agent, None, torch.ones_like(trojan), active, mb))) == 0.0
    with pytest.raises(ConfigError, match="needs the rollout's episode types"):
        penalty.loss(pen.PenaltyBatch(agent, None, None, None, mb))


def test_finetune_resistance_settings_are_checked():
    with pytest.raises(ConfigError, match=r"finetune_resistance\.weight must be a finite number >= 0"):
        FinetuneResistanceConfig(weight=-1.0)
    with pytest.raises(ConfigError, match=r"finetune_resistance\.inner_steps must be an integer in \[1, 16\], got 0"):
        FinetuneResistanceConfig(inner_steps=0)


def test_a_training_with_finetune_resistance_logs_its_value(smoke_config, clean_model):
    cfg = _attacked(smoke_config, clean_model, "ftr", finetune_resistance=FinetuneResistanceConfig(weight=1.0))
    cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, total_steps=3 * cfg.ppo.batch_size))
    rows = [json.loads(line) for line in (train(cfg).run_dir / "metrics.jsonl").read_text().splitlines()]
    values = [r["penalty/finetune_resistance"] for r in rows]
    assert len(values) == 3 and all(np.isfinite(v) for v in values) and any(v != 0 for v in values)
