import dataclasses
from pathlib import Path

import matplotlib.pyplot as plt
import pytest
import torch

from seqtrojan.config import ExperimentConfig
from seqtrojan.serde import from_dict, load_yaml

# One intra-op thread per test process: tests are run in parallel processes (pytest -n 2) and time nothing.
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]


def pytest_collection_modifyitems(config, items):
    if not torch.cuda.is_available():
        skip = pytest.mark.skip(reason="no CUDA device")
        for item in items:
            if "cuda" in item.keywords:
                item.add_marker(skip)


@pytest.fixture
def smoke_config(tmp_path) -> ExperimentConfig:
    """configs/smoke.yaml with its outputs under the test's tmp dir and no progress bar."""
    cfg = from_dict(ExperimentConfig, load_yaml(ROOT / "configs" / "smoke.yaml"), "")
    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, out_dir=str(tmp_path / "runs"), progress=False))


@pytest.fixture
def figures(monkeypatch):
    """Figures the plotting functions close, kept open for inspection."""
    kept, close = [], plt.close
    monkeypatch.setattr(plt, "close", kept.append)
    yield kept
    for fig in kept:
        close(fig)
