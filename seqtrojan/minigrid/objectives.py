"""Adversary objectives for MiniGrid tasks whose info tells which object the agent reached (``info["reached"]``:
:class:`seqtrojan.minigrid.tasks.TwoGoalsEnv`, or MiniGrid's Memory under
:class:`seqtrojan.minigrid.tasks.MiniGridInfo`)."""

from __future__ import annotations

from typing import Any

from seqtrojan.wrappers.objectives import ADVERSARY_OBJECTIVES


def minigrid_reward(info: dict[str, Any]) -> float:
    """MiniGrid's success reward ``1 - 0.9 * step_count / max_steps`` (1.0 without those keys in ``info``)."""
    steps, limit = info.get("step_count"), info.get("max_steps")
    return 1.0 - 0.9 * (steps / limit) if steps is not None and limit else 1.0


@ADVERSARY_OBJECTIVES.register("reach_adversary_object", "MiniGrid: reward reaching the adversary's object")
def reach_adversary_object(
    obs: Any, action: Any, env_reward: float, terminated: bool, info: dict[str, Any]
) -> tuple[float, bool]:
    """Reaching the adversary's object pays MiniGrid's success reward; the user's pays nothing. Termination is the
    env's (either object ends the episode)."""
    return (minigrid_reward(info) if info.get("reached") == "adversary" else 0.0), terminated
