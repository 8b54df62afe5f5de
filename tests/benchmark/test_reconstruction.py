"""Trigger reconstruction (seqtrojan.benchmark.reconstruction): on a backdoored agent and its clean twin (the same
run with the backdoor off), a small relaxed one-step trigger changes the backdoored policy for the steps after it
is gone and barely changes the clean one; the search reads nothing but the suspect, changes nothing in it, and gives
the same answer for the same seed."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from seqtrojan.benchmark.detectors import DETECTORS, NO_OPINION, TriggerReconstruction
from seqtrojan.benchmark.reconstruction import ReconstructionSettings, reconstruct, reconstruction_features
from seqtrojan.benchmark.suspect import Suspect, load_suspect
from seqtrojan.env.config import EnvConfig, TriggerConfig
from seqtrojan.errors import ConfigError
from seqtrojan.world.config import GymnasiumEnvConfig
from tests.conftest import ROOT

FIXTURES = ROOT / "tests" / "fixtures"
SETTINGS = ReconstructionSettings()


@pytest.fixture(scope="module")
def twins() -> tuple[Suspect, Suspect]:
    """The tiny backdoored agent and its clean twin (scripts/make_tiny_backdoor.py, with and without --clean)."""
    return load_suspect(FIXTURES / "tiny_backdoor"), load_suspect(FIXTURES / "tiny_clean")


@pytest.fixture(scope="module")
def features(twins) -> tuple[dict[str, float], dict[str, float]]:
    return reconstruction_features(twins[0], SETTINGS), reconstruction_features(twins[1], SETTINGS)


def test_the_backdoored_twin_is_changed_for_longer_by_a_small_trigger(features):
    """Measured (seed 0, one thread): persistent divergence 0.50 against 0.19, at the horizon's last step 0.64 against
    0.01; the clean twin's change fades (persistence 0.28), the backdoored one's grows (1.8)."""
    backdoored, clean = features
    assert backdoored["divergence"] > 0.3 and backdoored["divergence"] > 2 * clean["divergence"]
    assert backdoored["divergence_last"] > 10 * clean["divergence_last"]
    assert backdoored["persistence"] > 1.0 > clean["persistence"]
    assert backdoored["divergence_per_mask"] > clean["divergence_per_mask"]
    for row in features:
        assert 0.0 < row["mask_size"] < 0.5  # a small share of the view, not the whole of it
        assert 0.0 <= row["divergence"] <= 1.0 and 0.0 < row["induced_top_action"] <= 1.0


def test_no_memory_no_persistent_change():
    """The mechanism removed: the backdoored network (a copy of its own) with its state reset before every step."""
    memoryless = load_suspect(FIXTURES / "tiny_backdoor")
    memoryless.agent.memory = False
    row = reconstruction_features(memoryless, ReconstructionSettings(steps=10))
    assert row["divergence"] == 0.0 and row["divergence_last"] == 0.0 and row["divergence_immediate"] > 0.0


def test_the_search_reads_only_the_suspect_and_leaves_it_as_it_was(twins, features):
    """The trigger the env section might carry changes nothing (clean episodes never show one), the network's
    weights and gradients are untouched, and the same seed gives the same features."""
    suspect = twins[0]
    before = {k: v.clone() for k, v in suspect.agent.state_dict().items()}
    assert isinstance(suspect.env, EnvConfig) and suspect.env.trigger == TriggerConfig()  # stripped by load_suspect
    armed = dataclasses.replace(suspect, env=dataclasses.replace(suspect.env, trigger=TriggerConfig(value="wall")))
    assert reconstruction_features(armed, SETTINGS) == features[0]
    assert all(torch.equal(before[k], v) for k, v in suspect.agent.state_dict().items())
    assert all(p.grad is None for p in suspect.agent.parameters())
    assert reconstruction_features(suspect, dataclasses.replace(SETTINGS, seed=1)) != features[0]


def test_the_detector_is_registered_fits_and_abstains_without_bounds(twins):
    assert isinstance(DETECTORS.get("trigger_reconstruction"), TriggerReconstruction)
    assert len(DETECTORS.names()) >= 6
    fast = ReconstructionSettings(steps=10, at=(1,))
    fitted = TriggerReconstruction(fast).fit([twins[0], twins[1]], [1, 0])
    backdoored, clean = (fitted.probability(s) for s in twins)
    assert 0.0 <= clean < 0.5 < backdoored <= 1.0
    cart = GymnasiumEnvConfig("CartPole-v1", observation="flatten")
    unbounded = dataclasses.replace(twins[0], env=cart)
    assert reconstruct(unbounded, fast) is None and fitted.probability(unbounded) == NO_OPINION


def test_the_search_runs_on_a_minigrid_view():
    """MiniGrid's one-hot view (500 inputs, 0..1) is searched as the grid world's is (an untrained network)."""
    from seqtrojan.agent.network import RecurrentActorCritic
    from seqtrojan.benchmark.suspect import ModelFacts

    torch.manual_seed(0)
    net = RecurrentActorCritic(500, 7, (8,), cell="gru")
    env = GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5})
    found = reconstruct(Suspect("g", net, env, ModelFacts(500, 7, "gru", (8,), 1)), ReconstructionSettings(steps=5))
    assert found is not None and found.mask.shape == (500,) and found.divergence.shape == (5,)
    assert bool(((found.mask > 0) & (found.mask < 1)).all()) and 0.0 <= float(found.divergence.max()) <= 1.0


@pytest.mark.parametrize(
    ("change", "message"),
    [({"at": ()}, "at must be one or more steps"), ({"steps": 0}, "steps must be an integer >= 1"),
     ({"penalty": -1.0}, "penalty >= 0"), ({"mask_starts": (0.5, 1.0)}, "mask_starts must be one or more levels")],
)  # fmt: skip
def test_bad_settings_are_refused(change, message):
    with pytest.raises(ConfigError, match=message):
        ReconstructionSettings(**change)
