"""The sequence-model comparison (seqtrojan cells) end to end on a tiny budget, and its pieces."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from seqtrojan.cell_types import cell_names
from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.errors import ConfigError
from seqtrojan.experiment_results import CELLS_FILE, CellsResult, Rate, UnitsToSwitch
from seqtrojan.experiments.cells import CellsConfig, assemble, load_cells_config, persistence, run_cells
from seqtrojan.serde import from_dict, load_json, parse_yaml

TINY = """
backdoor:
  preset: smoke
  set:
    backdoor: {enabled: true, mixing: running}
    env: {trigger: {train_steps: [1, 4], eval_steps: [1, 4]}}
    ppo: {total_steps: 4096}
    run: {eval_episodes: 10, progress: false, checkpoint_every: 100000}
clean:
  preset: smoke
  set:
    ppo: {total_steps: 4096}
    run: {eval_episodes: 10, progress: false, checkpoint_every: 100000}
window: 3
seeds: 1
episodes: 30
persistence_bins: [[1, 2], [3, 100]]
trigger_steps: [1, 3]
sweep: "5x5/1,7x7/3"
monitor: {calibration_episodes: 60, eval_episodes: 30, false_alarm_target: 0.05}
trace_episodes: 60
units_trigger_step: 2
unit_counts: [1, 4]
rule: {response_window: 1, late_start: 2, late_end: 5, min_episodes: 5}
settle_grid: {size: 5, holes: 1}
settle_trigger_steps: [1, 2]
zoo: {clean: 1, backdoored: 1, total_steps: 2048, num_envs: 32, eval_episodes: 10, lstm_sizes: [[16]],
      curricula: [[{size: 5, holes: 1}]]}
jobs: {backend: serial}
"""


def test_every_cell_is_trained_measured_and_reported(tmp_path):
    cfg = from_dict(CellsConfig, parse_yaml(TINY), "")
    result = run_cells(cfg, tmp_path, scale="tiny", log=lambda _: None)
    assert [s.cell for s in result.summaries] == list(cell_names())
    assert load_json(CellsResult, tmp_path / CELLS_FILE) == result
    for a in result.agents:
        assert a.clean_success.n == 30 and a.attack_success.n == 30
        assert [p.grid for p in a.sweep] == ["5x5/1", "7x7/3"]
        assert set(a.monitor) == {"state_monitor", "multivariate_monitor"}
        assert (a.settling is not None) == (a.label == "backdoored")
        assert a.offline_score is not None and 0 <= a.offline_score <= 1
    for s in result.summaries:
        assert s.auc is not None and len(s.units_needed) == 1
    # a seed counts in a persistence bin only with enough episodes there; the pooled rate keeps them all
    strict = assemble(dataclasses.replace(cfg, min_bin_episodes=10**6), result.agents, "tiny")
    loose = assemble(dataclasses.replace(cfg, min_bin_episodes=1), result.agents, "tiny")
    assert all(not s.persistence for s in strict.summaries)
    for s in loose.summaries:
        mine = [a for a in result.agents if a.cell == s.cell and a.label == "backdoored"]
        for lo, hi, _, pooled in s.persistence:
            i = cfg.persistence_bins.index((lo, hi))
            assert pooled.n == sum(a.persistence[i].adversary.n for a in mine) > 0
    gru = next(a for a in result.agents if a.agent == "gru_backdoored_s0")
    assert gru.units is None or gru.units.which == "h"  # a GRU has only h
    page = (tmp_path / "report.html").read_text()
    assert "lstm_peephole" in page and "transformer" in page and (tmp_path / "cells.png").stat().st_size > 10_000
    # resumable: nothing is trained or measured again
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "measured").iterdir()}
    logs: list[str] = []
    assert run_cells(cfg, tmp_path, scale="tiny", log=logs.append) == result
    assert not any(line.startswith(("measuring", "training")) or " done in " in line for line in logs), logs
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "measured").iterdir()} == before


def test_persistence_bins_count_goals_by_steps_after_the_trigger():
    adv, user, hole = (OUTCOME_NAMES.index(n) for n in ("adversary_goal", "user_goal", "hole"))
    trace = types.SimpleNamespace(
        length=np.array([3, 4, 10, 12, 12, 5]),
        trigger_step=np.array([1, 1, 1, 1, 1, 1]),
        outcome=np.array([adv, user, adv, adv, user, hole]),
    )
    bins = persistence(trace, ((1, 3), (4, 20)))
    assert bins[0].adversary == Rate(1, 2)  # 2 and 3 steps after: one adversary, one user (the hole is no goal)
    assert bins[1].adversary == Rate(2, 3)


def test_units_needed_is_the_first_count_that_switches_half():
    u = UnitsToSwitch(0, "c", (3, 1, 2), (1, 2, 3), (Rate(1, 10), Rate(5, 10), Rate(9, 10)), (Rate(0, 10),) * 3)
    assert u.needed() == 2 and u.needed(0.95) is None


@pytest.mark.parametrize(
    ("text", "message"),
    [("cells: [lstm, mamba]", "cells must name one or more of"), ("seeds: 0", "cells.seeds"),
     ("monitors: [nope]", "nope"), ("sweep: '4x4/1'", "size=4")],
)  # fmt: skip
def test_bad_cells_configs_are_refused(text, message):
    with pytest.raises(ConfigError, match=message):
        from_dict(CellsConfig, parse_yaml(text), "")


def test_shipped_scales_load():
    for scale in ("smoke", "paper"):
        cfg = load_cells_config(scale)
        assert cfg.cells == cell_names() and cfg.seeds >= 3
