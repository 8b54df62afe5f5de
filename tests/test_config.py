"""Typed configs from YAML: YAML 1.2 reading (``off:`` is a key, 1e-3 a number), round trips, clear errors."""

from __future__ import annotations

import pytest
import yaml

from seqtrojan.config import ExperimentConfig, from_dict, load_yaml, parse_yaml, to_dict
from seqtrojan.errors import ConfigError
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
