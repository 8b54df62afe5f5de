"""Zoo jobs are pure and varied; a build writes models, labels and a manifest, resumes, and runs on Ray."""

from __future__ import annotations

import json

import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.env import GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.zoo.build import ZooConfig, build_zoo, make_jobs

TINY = ZooConfig(
    clean=2, backdoored=2, total_steps=2048, num_envs=32, eval_episodes=16,
    curricula=((GridSpec(5, 0), GridSpec(5, 1)),), lstm_sizes=((8,), (8, 8)),
)  # fmt: skip


def test_jobs_are_a_pure_function_of_the_config(tmp_path):
    a, b = make_jobs(TINY, tmp_path), make_jobs(TINY, tmp_path)
    assert a == b
    assert sorted(j.label for j in a) == ["backdoored", "backdoored", "clean", "clean"]
    big = make_jobs(ZooConfig(clean=10, backdoored=10), tmp_path)
    assert (
        len({j.variation["trigger_value"] for j in big}) >= 2
        and len({tuple(j.variation["lstm_sizes"]) for j in big}) >= 2
    )
    assert len({j.config.run.seed for j in big}) == 20
    with pytest.raises(ConfigError, match="unknown trigger value"):
        ZooConfig(trigger_values=("lava",))


def test_build_writes_models_labels_manifest_and_resumes(tmp_path):
    logs = []
    manifest = build_zoo(TINY, tmp_path / "zoo", workers=1, log=logs.append)
    entries = json.loads(manifest.read_text())
    assert [e["status"] for e in entries] == ["done"] * 4
    for e in entries:
        folder = tmp_path / "zoo" / "models" / e["id"]
        _, cfg, card = load_agent(folder)
        truth = json.loads((folder / "label.json").read_text())
        assert truth["label"] == card["label"] == e["label"] == cfg.label
        assert (truth["trigger"] is None) == (e["label"] == "clean")
        if e["label"] == "backdoored":
            assert truth["attack_success"] == card["metrics"]["trojan_success"] == e["metrics"]["trojan_success"]
            assert truth["functional_backdoor"] == (truth["attack_success"] >= TINY.functional_at)
        else:
            assert truth["attack_success"] is None and truth["functional_backdoor"] is None
    logs.clear()
    build_zoo(TINY, tmp_path / "zoo", workers=1, log=logs.append)
    assert logs[0].startswith("zoo: 4 of 4 models done; training 0")


def test_ray_backend_builds_the_same_jobs(tmp_path):
    pytest.importorskip("ray")
    cfg = ZooConfig(**{**TINY.__dict__, "clean": 1, "backdoored": 1})
    manifest = build_zoo(cfg, tmp_path / "zoo", workers=2, backend="ray", log=lambda *_: None)
    assert [e["status"] for e in json.loads(manifest.read_text())] == ["done", "done"]
