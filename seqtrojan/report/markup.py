"""The report's HTML pieces: its style sheet, embedded figures, and rates with their intervals."""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from pathlib import Path

from seqtrojan.stats import Rate

CSS = """
body { font-family: system-ui, -apple-system, Segoe UI, sans-serif; margin: 2em auto; max-width: 1100px;
       color: #222; line-height: 1.45; padding: 0 1em; }
h1 { font-size: 1.7em; margin-bottom: 0.2em; } h2 { margin-top: 1.8em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 4px 8px; text-align: right; }
th { background: #f4f4f4; } td.l, th.l { text-align: left; }
td.paper { color: #666; } td.differs { background: #fff1e6; }
.note { color: #555; font-size: 0.92em; } img { max-width: 100%; border: 1px solid #eee; }
pre { background: #f7f7f7; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
details { margin: 0.5em 0; }
"""


def img(path: Path) -> str:
    """The PNG at ``path`` embedded in the page (a note where it was not produced)."""
    if not path.exists():
        return "<p class='note'>(figure not produced)</p>"
    data = base64.b64encode(path.read_bytes()).decode()
    return f"<img src='data:image/png;base64,{data}' alt='{html.escape(path.name)}'>"


def ci(pair: Sequence[float]) -> str:
    """An interval, as a note: ``[0.050, 0.281]``."""
    return f"<span class='note'>[{pair[0]:.3f}, {pair[1]:.3f}]</span>"


def rate(r: Rate, digits: int = 3) -> str:
    """A rate and its 95% Wilson interval: ``0.125 [0.050, 0.281]``, the interval as a note."""
    return f"{r.value:.{digits}f} {ci(r.interval)}"
