"""Learning on other people's POMDPs, on a fixed step budget: a GRU agent on POPGym's RepeatPrevious learns to
answer from memory (a memoryless policy cannot: the card 4 steps ago is all but independent of the current one)."""

from __future__ import annotations

import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import ExperimentConfig
from seqtrojan.evaluation.env_report import evaluate_model
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train.trainer import train

MEMORYLESS_RETURN = -0.45
"""the best return a policy without memory gets on RepeatPreviousEasy, about -0.48 (a quarter of the answers right,
a little more from the deck's counts): the clean threshold below needs memory"""


def repeat_previous(tmp_path, steps: int, backdoor: bool) -> ExperimentConfig:
    data = load_yaml(resolve_preset("popgym_repeat_previous"))
    data["ppo"]["total_steps"] = steps
    data["run"] = {"out_dir": str(tmp_path), "name": "rp", "seed": 0, "progress": False, "eval_episodes": 0,
                   "checkpoint_every": 10**9, "threads": 1}  # fmt: skip
    if not backdoor:
        data["backdoor"] = {"enabled": False}
    return from_dict(ExperimentConfig, data, "")


@pytest.mark.slow
def test_a_gru_learns_repeat_previous_from_memory(tmp_path):
    """800k env steps (about 2 min on one busy core). Measured with this config, 2026-12-03: clean return 0.470
    [0.454, 0.487] over 200 episodes; the one-step trigger, never trained on, leaves the answers alone (target share
    0.255 after it, 0.254 in normal episodes). The backdoored preset needs its full 3M steps to learn both tasks
    (at 1M it answers the target everywhere): docs/families.md has those runs."""
    cfg = repeat_previous(tmp_path, 800_000, backdoor=False)
    result = train(cfg)
    agent, saved, _ = load_agent(result.model_dir)
    report = evaluate_model(agent, saved, episodes=200, seed=7, horizons=(10, 30))
    assert report.clean_return is not None and report.clean_return.mean > 0.0 > MEMORYLESS_RETURN, report
    assert report.target_share is not None and report.target_share.mean < 0.4, report.target_share
