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


@pytest.fixture(scope="session")
def tiny_two_goals_model(tmp_path_factory):
    """A backdoored agent on MiniGrid's two-goal room after 512 env steps (barely trained: for plumbing, not
    figures): (agent, its config as loaded, its model folder)."""
    from seqtrojan.agent.checkpoint import load_agent
    from seqtrojan.config import BackdoorConfig, PPOConfig, RunConfig
    from seqtrojan.train.trainer import train
    from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig

    ppo = PPOConfig(total_steps=512, num_envs=8, rollout_steps=64, bptt_length=16, num_minibatches=4)
    cfg = ExperimentConfig(
        env=GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5},
                               trigger=WrapperTriggerConfig()),
        ppo=ppo, backdoor=BackdoorConfig(enabled=True),
        run=RunConfig(out_dir=str(tmp_path_factory.mktemp("gym")), name="run", eval_episodes=4, lstm_backend="torch",
                      progress=False),
    )  # fmt: skip
    model_dir = train(cfg).model_dir
    agent, loaded, _ = load_agent(model_dir)
    return agent, loaded, model_dir
