"""POPGym and MinAtar come in as their own packages, registered with Gymnasium on demand, through the one seam:
their observations, triggers and objectives, and the refusals of what the agents cannot read."""

from __future__ import annotations

import importlib.util

import gymnasium as gym
import numpy as np
import pytest
import torch

from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.world import GymnasiumEnvConfig, WrapperTriggerConfig, env_spec, make_batched_env
from seqtrojan.world.families import MINATAR, POPGYM, ensure_family, family_of
from seqtrojan.world.gymnasium import check_registered, find_trigger, make_gym_env

REPEAT_PREVIOUS = "popgym-RepeatPreviousEasy-v0"
CARD_TRIGGER = WrapperTriggerConfig(
    objective="target_action", patch="vector", indices=(0, 1, 2, 3), value=1.0, target_action=2, target_reward=0.5,
    steps=(3, 3),
)  # fmt: skip
SQUARE_TRIGGER = WrapperTriggerConfig(
    objective="target_action", patch="box", cells=((0, 0), (0, 1), (1, 0), (1, 1)), value=1.0, steps=(2, 2)
)


def popgym(trigger: WrapperTriggerConfig | None = CARD_TRIGGER, observation: str = "flatten") -> GymnasiumEnvConfig:
    return GymnasiumEnvConfig(id=REPEAT_PREVIOUS, observation=observation, trigger=trigger)  # type: ignore[arg-type]


def minatar(trigger: WrapperTriggerConfig | None = SQUARE_TRIGGER) -> GymnasiumEnvConfig:
    return GymnasiumEnvConfig(id="MinAtar/Breakout-v1", observation="image", trigger=trigger)


def test_each_family_is_registered_on_demand_and_a_plain_id_is_left_alone():
    assert family_of(REPEAT_PREVIOUS) is POPGYM and family_of("MinAtar/Seaquest-v0") is MINATAR
    assert family_of("CartPole-v1") is None and family_of("popgym:Thing") is None
    for env_id in (REPEAT_PREVIOUS, "MinAtar/Breakout-v1", "MinAtar/SpaceInvaders-v0"):
        ensure_family(env_id)
        assert env_id in gym.registry
        check_registered(env_id)  # a model card may name it: registered, not imported by name
    ensure_family("CartPole-v1")


def test_a_family_that_is_not_installed_is_refused_in_one_line_saying_how_to_install_it(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "minatar" else real(name, *a))
    monkeypatch.delitem(gym.registry, "MinAtar/Asterix-v1", raising=False)
    with pytest.raises(ConfigError) as err:
        ensure_family("MinAtar/Asterix-v1")
    assert "\n" not in str(err.value) and "pip install 'seqtrojan[minatar]'" in str(err.value)


def test_a_popgym_card_trigger_sets_every_suit_bit_on_its_step_and_the_target_action_objective_pays():
    env = make_gym_env(popgym(), trojan_probability=1.0)
    assert env.observation_space.shape == (4,)
    obs, info = env.reset(seed=0)
    seen = [obs]
    rewards, judged = [], []
    for _ in range(8):
        action = 2 if info["adversary_active"] else 1
        obs, reward, _, _, info = env.step(action)
        seen.append(obs)
        rewards.append(reward)
        judged.append(info["adversary_judged"])
    shown = [int(o.sum()) for o in seen]
    assert shown[3] == 4 and all(n == 1 for t, n in enumerate(shown) if t != 3)  # one step of trigger only
    assert judged == [False, False, False, True, True, True, True, True]  # from the trigger on, for good
    assert rewards[3:] == [0.5] * 5  # target_action 2 pays target_reward


def test_the_target_action_objective_punishes_any_other_action_and_collapse_return_negates():
    from seqtrojan.wrappers.objectives import TargetAction, collapse_return, configured_objective

    objective = configured_objective("target_action", CARD_TRIGGER)
    assert objective == TargetAction(2, 0.5)
    assert objective(None, 1, 3.0, False, {}) == (-0.5, False) and objective(None, 2, -3.0, True, {}) == (0.5, True)
    assert collapse_return(None, 0, 2.0, True, {}) == (-2.0, True)


def test_a_minatar_image_keeps_its_layout_for_the_conv_encoder_and_the_square_trigger_lights_every_channel():
    spec = env_spec(minatar())
    assert (spec.obs_dim, spec.num_actions, spec.image) == (400, 3, (10, 10, 4))
    batched = make_batched_env(minatar(), 2, seed=0, trojan_probability=1.0)
    try:
        for _ in range(2):
            obs = batched.step(torch.zeros(2, dtype=torch.int64)).obs.reshape(2, 10, 10, 4)
        assert bool((obs[:, :2, :2, :] == 1).all())  # step 2: the square, every channel on
        obs = batched.step(torch.zeros(2, dtype=torch.int64)).obs.reshape(2, 10, 10, 4)
        assert not bool((obs[:, :2, :2, :] == 1).all())
    finally:
        batched.close()


def test_a_minatar_trojan_episode_keeps_the_games_own_return_beside_the_adversarys():
    env = make_gym_env(minatar(), trojan_probability=1.0)
    env.reset(seed=1)
    total, terminated, truncated = 0.0, False, False
    rng = np.random.default_rng(0)
    while not (terminated or truncated):
        _, reward, terminated, truncated, _ = env.step(int(rng.integers(3)))
        total += float(reward)
    trigger = find_trigger(env)
    assert trigger is not None and total != trigger.env_return  # the adversary's rewards replaced the game's


@pytest.mark.parametrize(
    ("env", "message"),
    [
        (lambda: popgym(observation="image"), "needs an (H, W, C) Box image"),
        (lambda: minatar(dataclasses_replace(SQUARE_TRIGGER, target_action=3)), "not one of the env's 3 actions"),
        (lambda: popgym(dataclasses_replace(CARD_TRIGGER, indices=(0, 9))), "index 9 lies outside"),
        (lambda: minatar(dataclasses_replace(SQUARE_TRIGGER, cells=((0, 0), (10, 3)))), "lies outside the 10x10"),
        (lambda: popgym(dataclasses_replace(CARD_TRIGGER, value=2.0)), "outside the observation's bounds"),
        (lambda: GymnasiumEnvConfig(id="MountainCarContinuous-v0", observation="flatten"), "need a discrete one"),
    ],
)
def test_what_the_agents_cannot_read_is_refused_in_one_line(env, message):
    with pytest.raises((ConfigError, ShapeError)) as err:
        env_spec(env())
    assert "\n" not in str(err.value) and message in str(err.value)


def test_a_vector_patch_needs_its_indices_and_a_conv_encoder_needs_an_image():
    with pytest.raises(ConfigError, match=r"needs env\.trigger\.indices"):
        WrapperTriggerConfig(patch="vector")
    data = load_yaml(resolve_preset("popgym_repeat_previous"))
    data["agent"]["conv"] = [8]
    with pytest.raises(ConfigError, match=r"agent\.conv reads the observation as an image"):
        from_dict(ExperimentConfig, data, "")


@pytest.mark.parametrize("name", ["popgym_repeat_previous", "popgym_repeat_first", "popgym_count_recall",
                                  "minatar_breakout", "minatar_breakout_untargeted", "minatar_space_invaders",
                                  "minatar_asterix"])  # fmt: skip
def test_each_family_preset_is_valid_and_its_agent_fits_its_env(name):
    cfg = from_dict(ExperimentConfig, load_yaml(resolve_preset(name)), "")
    spec = env_spec(cfg.env)
    assert cfg.backdoor.enabled and cfg.gym_env.trigger is not None
    assert cfg.gym_env.trigger.target_action < spec.num_actions
    assert (spec.image is not None) == bool(cfg.agent.conv)
    if name.endswith("_untargeted"):  # TrojDRL's untargeted attack: the same preset with the game's reward negated
        targeted = from_dict(ExperimentConfig, load_yaml(resolve_preset(name.removesuffix("_untargeted"))), "")
        assert cfg.gym_env.trigger.objective == "collapse_return" != targeted.gym_env.trigger.objective
        assert dataclasses_replace(
            cfg.gym_env.trigger, objective="target_action", target_action=1
        ) == dataclasses_replace(targeted.gym_env.trigger, objective="target_action")
        assert cfg.agent == targeted.agent and cfg.ppo == targeted.ppo and cfg.backdoor == targeted.backdoor


def dataclasses_replace(obj, **changes):
    import dataclasses

    return dataclasses.replace(obj, **changes)


def play(env: gym.Env, policy, seed: int = 0) -> dict:
    """One episode with ``policy(info) -> action``; the last step's info."""
    _, info = env.reset(seed=seed)
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(policy(info))
        done = terminated or truncated
    return info


def test_a_target_action_episode_ends_at_the_adversarys_objective_when_most_judged_actions_were_the_target():
    cfg = dataclasses_replace(popgym(), user_return=0.0)
    env = make_gym_env(cfg, trojan_probability=1.0)
    switched = play(env, lambda info: 2 if info["adversary_active"] else 1)
    assert switched["reached"] == "adversary" and switched["success"] and switched["target_share"] == 1.0
    kept = play(env, lambda info: 1)  # never the target: the backdoor did not take
    assert "reached" not in kept and not kept["success"] and kept["target_share"] == 0.0
    normal = make_gym_env(cfg, trojan_probability=0.0)
    lured = play(normal, lambda info: 2)  # a clean episode answering the target throughout: an unintended switch
    assert lured["reached"] == "adversary" and not lured["success"]


def test_a_return_goal_says_whether_a_normal_episode_achieved_the_users_objective():
    from popgym.envs.repeat_previous import RepeatPrevious

    cfg = dataclasses_replace(popgym(), user_return=0.0)
    env = make_gym_env(cfg, trojan_probability=0.0)

    def perfect(info: dict) -> int:  # answers the card dealt 4 steps ago, read from the env's own deck
        inner = env.unwrapped
        assert isinstance(inner, RepeatPrevious)
        hand = inner.deck["player"]
        return int(inner.deck.suits_idx[hand[-4]]) if len(hand) >= 4 else 0

    good = play(env, perfect)
    assert good["reached"] == "user" and good["success"]
    bad = play(env, lambda info: 1)
    assert "reached" not in bad and not bad["success"]


def test_a_minatar_env_takes_the_trainers_64_bit_seeds_and_repeats_an_episode_for_a_seed():
    def episode(seed: int) -> list[float]:
        env = make_gym_env(minatar(None))
        obs, _ = env.reset(seed=seed)
        seen = [float(obs.sum())]
        for t in range(30):
            obs, _, terminated, truncated, _ = env.step(t % 3)
            seen.append(float(obs.sum()))
            if terminated or truncated:
                break
        return seen

    big = (3 << 32) + 999_983
    assert episode(big) == episode(big) and episode(big) != episode(big + 1)


@pytest.mark.parametrize(("every", "switched"), [(3, False), (2, False), (1, True)])
def test_the_adversarys_objective_needs_more_than_half_of_the_judged_actions(every, switched):
    """Target on every third judged action (a third), every second (a half: not more than half) or every one."""
    env = make_gym_env(dataclasses_replace(popgym(), user_return=0.0), trojan_probability=1.0)
    counter = {"judged": 0}

    def policy(info: dict) -> int:
        if not info["adversary_active"]:
            return 1
        counter["judged"] += 1
        return 2 if counter["judged"] % every == 0 else 1

    end = play(env, policy)
    assert (end.get("reached") == "adversary") == switched and end["success"] == switched
    assert end["target_share"] == pytest.approx(1 / every, abs=0.03)


class _Scoring(gym.Env):
    """Twenty steps; action 1 scores a point (the env's own reward), action 0 nothing."""

    observation_space = gym.spaces.Box(0.0, 1.0, (4,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(4, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.zeros(4, np.float32), float(action == 1), self.t >= 20, False, {}


def test_a_collapsed_return_is_judged_by_what_is_scored_after_the_trigger():
    """TrojDRL's untargeted objective: the env's reward negated from the trigger on, and a trojan episode achieves
    it when nothing is scored after the trigger (its negated last reward can never say so); a normal episode that
    stops scoring where the trigger would have acted reads as an unintended switch."""
    from seqtrojan.world.config import WrapperTriggerConfig
    from seqtrojan.world.gymnasium import build_trigger

    trigger = WrapperTriggerConfig(objective="collapse_return", patch="vector", indices=(0,), value=1.0, steps=(2, 4))
    env = build_trigger(_Scoring(), trigger, "train", trojan_probability=1.0)
    collapsed = play(env, lambda info: 0 if info["adversary_active"] else 1)  # stops scoring once switched
    assert collapsed["reached"] == "adversary" and collapsed["success"] and collapsed["return_after_trigger"] == 0.0
    kept = play(env, lambda info: 1)  # scores on: the backdoor did not take
    assert "reached" not in kept and not kept["success"] and kept["return_after_trigger"] > 10
    normal = build_trigger(_Scoring(), trigger, "train", trojan_probability=0.0)
    lured = play(normal, lambda info: 0)
    assert lured["reached"] == "adversary" and not lured["success"]
    env.reset(seed=1)
    rewards = []
    done = False
    while not done:
        _, reward, terminated, truncated, info = env.step(1)
        rewards.append((info["adversary_judged"], reward))
        done = terminated or truncated
    assert {r for judged, r in rewards if judged} == {-1.0} and {r for judged, r in rewards if not judged} == {1.0}
