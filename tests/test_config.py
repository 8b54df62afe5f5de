"""Typed configs from YAML: YAML 1.2 reading (``off:`` is a key, 1e-3 a number), round trips, clear errors."""

from __future__ import annotations

import pytest
import yaml

from seqtrojan.config import AgentConfig, ExperimentConfig, RunConfig
from seqtrojan.errors import ConfigError
from seqtrojan.serde import from_dict, load_yaml, parse_yaml, to_dict
from tests.conftest import ROOT


def test_yaml_is_read_the_yaml_1_2_way():
    data = parse_yaml("off: {probability: 0.5}\non: yes\nflag: true\nlr: 3e-4\nbig: 1E+6\nn: 12\nx: 0.5\n")
    assert data == {"off": {"probability": 0.5}, "on": "yes", "flag": True, "lr": 3e-4, "big": 1e6, "n": 12, "x": 0.5}
    assert isinstance(data["n"], int)


def test_the_on_off_preset_loads_with_its_off_trigger():
    cfg = from_dict(ExperimentConfig, load_yaml(ROOT / "configs" / "onoff_7x7.yaml"), "")
    assert cfg.env.trigger.off.probability == 0.5 and cfg.env.trigger.off.value == "wall"
    assert cfg.env.trigger.delay == 2 and cfg.backdoor.enabled


def test_a_config_round_trips_through_yaml():
    cfg = from_dict(ExperimentConfig, load_yaml(ROOT / "configs" / "onoff_7x7.yaml"), "")
    text = yaml.safe_dump(to_dict(cfg), sort_keys=False)  # what a run directory's config.yaml holds
    assert from_dict(ExperimentConfig, parse_yaml(text), "") == cfg


def test_a_yes_no_value_for_a_boolean_is_a_named_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("backdoor: {enabled: yes}\n")
    with pytest.raises(ConfigError, match=r"backdoor\.enabled must be true or false, got 'yes'"):
        from_dict(ExperimentConfig, load_yaml(bad), "")


BILLION_LAUGHS = """\
a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]
b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]
c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]
d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]
e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]
f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]
g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f]
h: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g]
ppo: {total_steps: *h}
"""


def test_yaml_aliases_are_refused_so_an_alias_bomb_cannot_hang(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BILLION_LAUGHS)
    with pytest.raises(ConfigError, match=r"found alias \*a: aliases are not allowed in config files \(line 2"):
        load_yaml(bomb)
    merge = tmp_path / "merge.yaml"
    merge.write_text("base: &base {size: 5}\nenv:\n  <<: *base\n  holes: 0\n")
    with pytest.raises(ConfigError, match=r"alias \*base"):
        load_yaml(merge)
    with pytest.raises(yaml.YAMLError, match="aliases are not allowed"):
        parse_yaml("x: &x [1]\ny: *x\n")
    assert parse_yaml("env: &e {size: 5}\n") == {"env": {"size": 5}}  # an anchor alone is harmless


def _shared_nest(levels: int) -> list:
    """10**levels leaves in a few hundred objects: what an alias bomb expands to."""
    value: list = [0] * 10
    for _ in range(levels - 1):
        value = [value] * 10
    return value


@pytest.mark.parametrize(
    "data",
    [
        {"ppo": {"total_steps": "BIG"}},  # int
        {"ppo": {"learning_rate": "BIG"}},  # float
        {"ppo": {"bptt_length": "BIG"}},  # int | None
        {"ppo": {"lr_schedule": "BIG"}},  # Literal
        {"run": {"device": "BIG"}},  # str
        {"backdoor": {"enabled": "BIG"}},  # bool
        {"env": {"trigger": {"train_steps": "BIG"}}},  # tuple of fixed length
        {"agent": "BIG"},  # a section must be a mapping
    ],
)
def test_error_messages_show_a_large_value_truncated(data):
    def fill(d):
        return {k: fill(v) if isinstance(v, dict) else (_shared_nest(6) if v == "BIG" else v) for k, v in d.items()}

    with pytest.raises(ConfigError) as info:
        from_dict(ExperimentConfig, fill(data), "")
    message = str(info.value)
    assert len(message) < 250 and "\n" not in message, message
    assert "..." in message


def test_run_device_is_checked_when_the_config_is_built():
    with pytest.raises(ConfigError, match=r"run\.device='tpu:7' is not a device; use cpu, cuda or cuda:N"):
        from_dict(ExperimentConfig, parse_yaml("run: {device: 'tpu:7'}"), "")
    for bad in ("tpu:7", "cuda:", "cuda:x", "CPU", "cuda:0 ", "mps"):
        with pytest.raises(ConfigError, match="is not a device"):
            RunConfig(device=bad)
    for good in ("cpu", "cuda", "cuda:0", "cuda:12"):
        assert RunConfig(device=good).device == good


@pytest.mark.parametrize("value", [0, -5, 2.5, True])
def test_checkpoint_every_must_be_a_positive_integer(value):
    with pytest.raises(ConfigError, match=r"run\.checkpoint_every must be a positive integer"):
        RunConfig(checkpoint_every=value)
    assert RunConfig(checkpoint_every=1).checkpoint_every == 1


def test_serde_names_are_still_importable_from_config():
    import seqtrojan.config as config
    import seqtrojan.serde as serde

    for name in ("from_dict", "to_dict", "load_yaml", "parse_yaml"):
        assert getattr(config, name) is getattr(serde, name)


@pytest.mark.parametrize("sizes", [(4097,), (8,) * 9])
def test_lstm_sizes_beyond_what_a_model_card_accepts_are_refused_before_training(sizes):
    with pytest.raises(ConfigError, match="1 to 8 layers of at most 4096 units"):
        AgentConfig(lstm_sizes=sizes)
    AgentConfig(lstm_sizes=(4096,))  # the largest width still builds a config


@pytest.mark.parametrize(
    ("section", "key", "path"),
    [("ppo", "ent_coef", "ppo.ent_coef"), ("ppo", "learning_rate", "ppo.learning_rate"),
     ("agent", "forget_bias", "agent.forget_bias")],
)  # fmt: skip
@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_numbers_are_refused_with_their_path(section, key, path, value):
    from seqtrojan.config import ExperimentConfig
    from seqtrojan.errors import ConfigError
    from seqtrojan.serde import from_dict

    with pytest.raises(ConfigError, match=path.replace(".", r"\.")):
        from_dict(ExperimentConfig, {section: {key: value}})
    with pytest.raises(ConfigError, match=r"env\.rewards\.goal must be a finite number"):
        from_dict(ExperimentConfig, {"env": {"rewards": {"goal": value}}})


RANGE_REFUSALS = {
    "clip_coef 0": ({"ppo": {"clip_coef": 0.0}}, r"ppo\.clip_coef must be a number > 0, got 0\.0"),
    "clip_coef < 0": ({"ppo": {"clip_coef": -0.2}}, r"ppo\.clip_coef must be a number > 0"),
    "max_grad_norm 0": ({"ppo": {"max_grad_norm": 0.0}}, r"ppo\.max_grad_norm must be a number > 0"),
    "adam_eps 0": ({"ppo": {"adam_eps": 0}}, r"ppo\.adam_eps must be a number > 0"),
    "ent_coef < 0": ({"ppo": {"ent_coef": -0.01}}, r"ppo\.ent_coef must be a finite number >= 0"),
    "vf_coef < 0": ({"ppo": {"vf_coef": -1.0}}, r"ppo\.vf_coef must be a finite number >= 0"),
    "target_kl 0": ({"ppo": {"target_kl": 0.0}}, r"ppo\.target_kl must be a number > 0 or null"),
    "num_envs": ({"ppo": {"num_envs": 1 << 20}}, r"ppo\.num_envs must be at most 65536, got 1048576"),
    "rollout_steps": ({"ppo": {"rollout_steps": 1 << 20}}, r"ppo\.rollout_steps must be at most 65536"),
    "total_steps": ({"ppo": {"total_steps": 10**30}}, r"ppo\.total_steps must be at most 9007199254740992"),
    "rollout memory": (
        {"ppo": {"num_envs": 65536, "rollout_steps": 4096}, "env": {"view_size": 5}},
        r"65536 x 150 x 4 bytes = 150\.0 GiB\) exceeds the 8 GiB a rollout buffer may take",
    ),
    "seed < 0": ({"run": {"seed": -1}}, r"run\.seed must be an integer in \[0, 1073741823\], got -1"),
    "seed too large": ({"run": {"seed": 2**63}}, r"run\.seed must be an integer in \[0, 1073741823\]"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(RANGE_REFUSALS))
def test_out_of_range_numbers_are_refused_in_one_line(case):
    data, message = RANGE_REFUSALS[case]
    with pytest.raises(ConfigError, match=message) as info:
        from_dict(ExperimentConfig, data)
    assert "\n" not in str(info.value)


def test_the_range_limits_admit_their_edges():
    from seqtrojan.config import MAX_SEED, PPOConfig

    RunConfig(seed=0), RunConfig(seed=MAX_SEED)
    PPOConfig(num_envs=65536, rollout_steps=16, num_minibatches=1, clip_coef=1e-9, max_grad_norm=1e-9, adam_eps=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [("ppo:\n  clip_coef: 0.1\n  clip_coef: 0.3\n", r"duplicate key 'clip_coef' \(line 3, column 3\)"),
     ("run: {seed: 1, seed: 2}\n", "duplicate key 'seed'"),
     ("ppo:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(200)), "nested more than 64 deep"),
     ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nested more than 64 deep")],
    ids=["duplicate key", "duplicate flow key", "deep mapping", "deep list"],
)  # fmt: skip
def test_yaml_with_duplicate_keys_or_deep_nesting_is_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_yaml(path)
    assert "\n" not in str(info.value) and "not valid YAML" in str(info.value)
    assert parse_yaml("a: 1\nb: {<<: {c: 2}, c: 3}\n") == {"a": 1, "b": {"c": 3}}  # a merge still overrides


@pytest.mark.parametrize("steps", ["12", (1.7, 3.2), (1, True), (1, 2, 3), 12, None])
def test_trigger_step_ranges_are_two_integers_never_digits_of_a_string(steps):
    from seqtrojan.minigrid.tasks import two_goals_trigger

    with pytest.raises(ConfigError, match=r"trigger_steps must be an inclusive range \[lo, hi\] of integer steps"):
        two_goals_trigger(trigger_steps=steps)
    assert two_goals_trigger(trigger_steps=[1, 2]).trigger_steps == (1, 2)
