"""Presets are package data found by name from any folder; a path still works; an unknown name fails clearly."""

from __future__ import annotations

from pathlib import Path

import pytest

import seqtrojan
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments import reproduce
from seqtrojan.presets import list_presets, resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from tests.conftest import ROOT

PACKAGE_PRESETS = Path(seqtrojan.__file__).resolve().parent / "presets"
TRAINING = ["clean_7x7", "clean_s17_h30", "onoff_7x7", "smoke", "trojan_s17_h30"]


def test_presets_are_found_by_name_in_the_package_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no ./configs here
    assert {*TRAINING, "reproduce_paper", "reproduce_smoke"} <= set(list_presets())
    for name in TRAINING:
        for spelling in (name, f"{name}.yaml"):
            path = resolve_preset(spelling)
            assert path == PACKAGE_PRESETS / f"{name}.yaml" and path.is_file()
        from_dict(ExperimentConfig, load_yaml(resolve_preset(name)), "")  # every training preset is valid
    for scale in ("smoke", "paper"):
        config = reproduce.load_reproduce_config(scale)
        for role, spec in (("clean", config.clean), ("backdoor", config.backdoor)):
            reproduce.experiment_from_spec(spec, tmp_path, role, "cpu")  # the scales' presets resolve by name
    assert reproduce.resolve_preset is resolve_preset  # still importable from reproduce


def test_a_path_still_works_and_wins_over_a_name(tmp_path, monkeypatch):
    own = tmp_path / "smoke.yaml"
    own.write_text("env: {size: 9, holes: 4}\n")
    assert resolve_preset(str(own)) == own and resolve_preset(own) == own
    monkeypatch.chdir(tmp_path)
    assert resolve_preset("smoke.yaml") == Path("smoke.yaml")  # a file in the working folder is a path
    assert resolve_preset("smoke") == PACKAGE_PRESETS / "smoke.yaml"  # no file named 'smoke': the shipped preset


def test_the_repository_configs_folder_is_the_package_presets():
    for name in list_presets():
        assert (ROOT / "configs" / f"{name}.yaml").samefile(PACKAGE_PRESETS / f"{name}.yaml")


@pytest.mark.parametrize("name", ["clean_7x7x", "configs/nothing.yaml", "/no/such/file.yaml", ""])
def test_an_unknown_preset_is_a_clear_error_listing_the_shipped_ones(name):
    with pytest.raises(ConfigError) as err:
        resolve_preset(name)
    message = str(err.value)
    assert "\n" not in message and f"preset {name!r} not found: that file does not exist" in message
    assert f"(shipped: {', '.join(list_presets())})" in message
    assert all(name in message for name in ("clean_7x7", "clean_s17_h30", "onoff_7x7", "matrix_smoke"))
