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
