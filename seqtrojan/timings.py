"""Wall seconds per pipeline stage or step, kept in a JSON file that every record rewrites, so that a stopped
pipeline keeps the timings of what it finished. Used by the reproduction's stage runner and the analysis steps."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


class Timings:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.times: dict[str, float] = json.loads(path.read_text()) if path.exists() else {}

    def record(self, key: str, seconds: float) -> None:
        self.times[key] = seconds
        self.path.write_text(json.dumps(self.times, indent=2))

    def timed(self, key: str, fn: Callable[[], T]) -> T:
        """``fn()``, its wall time recorded under ``key``."""
        t0 = time.perf_counter()
        value = fn()
        self.record(key, time.perf_counter() - t0)
        return value
