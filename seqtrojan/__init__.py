"""seqtrojan: persistent backdoors in recurrent agents -- build, measure, look inside, defend."""

from __future__ import annotations

from seqtrojan.env.registration import register_envs

__version__ = "0.1.0"

register_envs()

__all__ = ["__version__", "register_envs"]
