"""The paper's reported numbers (Yang et al. 2019, section 5), shipped with the package so that every result can
be shown beside them. Source: ``shared/paper/paper-results.json`` of the project, copied verbatim."""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from typing import Any


@lru_cache(maxsize=1)
def paper_results() -> dict[str, Any]:
    return json.loads(resources.files(__package__).joinpath("paper_results.json").read_text())


def paper_configs() -> list[tuple[int, int]]:
    """The 14 (size, holes) configs of the paper's Tables 1 and 2."""
    return [tuple(c) for c in paper_results()["table1_normal_env_success"]["configs"]]


def paper_success(agent: str, env: str, size: int, holes: int) -> float | None:
    """The paper's success rate for ``agent`` ("clean"/"backdoored") in ``env`` ("normal"/"trojan"), if reported."""
    if agent not in ("clean", "backdoored"):
        return None  # a model of unknown lineage: the paper has no figure for it
    results = paper_results()
    if (size, holes) == tuple(results["agents"]["training_config"].values()):
        key = {
            ("clean", "normal"): "clean_agent_normal_env",
            ("backdoored", "normal"): "backdoor_agent_normal_env",
            ("backdoored", "trojan"): "backdoor_agent_trojan_env",
        }.get((agent, env))
        return results["training_config_success"][key] if key else None
    table = results["table1_normal_env_success" if env == "normal" else "table2_trojan_env_success"]
    column = {"clean": "clean_agent", "backdoored": "backdoor_agent"}[agent]
    configs = [tuple(c) for c in table["configs"]]
    if column not in table or (size, holes) not in configs:
        return None
    return table[column][configs.index((size, holes))]
