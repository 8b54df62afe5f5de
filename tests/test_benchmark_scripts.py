"""What the benchmark scripts compute beyond printing a saved run (their tables: tests/test_docs_data.py)."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_zoo_rate_reads_when_a_backdoor_formed_from_a_kept_training_curve(tmp_path):
    steps_to_form = runpy.run_path(str(ROOT / "benchmarks" / "zoo_rate.py"))["steps_to_form"]
    rows = [(2048, 0.95, 0.50), (4096, 0.85, 0.95), (6144, 0.92, 0.93), (8192, 1.0, 1.0)]
    curve = tmp_path / "m0001.jsonl"
    keys = ("env_steps", "episodes/normal_success", "episodes/trojan_success")
    lines = [json.dumps(dict(zip(keys, row))) for row in rows]
    curve.write_text('{"env_steps": 1024, "episodes/norm\n' + "\n".join(lines) + "\n")  # a line cut short, skipped
    assert steps_to_form(curve) == 6144  # the first update with both envs at 0.9 or more
    never = tmp_path / "m0002.jsonl"
    never.write_text("\n".join(lines[:2]) + "\n" + json.dumps({"env_steps": 9000, "episodes/normal_success": 1.0}))
    assert steps_to_form(never) is None  # a clean run's rows have no trojan success
    assert steps_to_form(tmp_path / "absent.jsonl") is None


def test_a_composition_of_recipes_applies_each_in_order_and_sets_the_last_ones_knob():
    """``A+B+C`` in the defense benchmarks: the first recipe's trigger, every recipe's training terms, the last one's
    knob, from the clean agent when one of them starts from one; an unknown name is refused in one line."""
    import pytest

    from seqtrojan.config import BackdoorConfig, ExperimentConfig, RunConfig
    from seqtrojan.errors import ConfigError

    composition = runpy.run_path(str(ROOT / "benchmarks" / "state_bounds.py"))["Composition"]
    triple = composition.parse("search_decoys+weight_camouflage+response_mimicry/10")
    assert triple.folder(2) == "search_decoys_weight_camouflage_response_mimicry_w10_s2" and triple.from_clean
    base = ExperimentConfig(backdoor=BackdoorConfig(enabled=True), run=RunConfig(init_from="clean"))
    cfg = triple.configure(base)
    assert cfg.env.trigger.sequence and cfg.env.trigger.decoys.probability == 0.3  # search_decoys' trigger
    assert cfg.attack.weight_camouflage.weight == 0.5 and cfg.attack.response_mimicry.weight == 10.0
    assert cfg.backdoor.mixing == "fixed"
    plain = composition.parse("in_distribution_patch+mahalanobis_camouflage")
    assert not plain.from_clean and plain.folder(0) == "in_distribution_patch_mahalanobis_camouflage_s0"
    assert plain.configure(base).attack.mahalanobis_camouflage.weight == 5.0
    with pytest.raises(ConfigError) as err:
        composition.parse("search_decoy+from_clean")
    assert "\n" not in str(err.value)
