"""A griffe extension for the docs site (mkdocs.yml): the docstrings' reST roles and literal blocks as Markdown.

The code's docstrings use Sphinx roles (:class:`~seqtrojan.stats.Rate`) and ``::`` literal blocks; mkdocstrings
reads docstrings as Markdown, where those would show as written. Each role becomes a code span of its target (the
last dotted part where the target starts with ``~``), and a paragraph ending in ``::`` ends in ``:`` (the indented
block after it is a code block in Markdown too).
"""

from __future__ import annotations

import re
from typing import Any

from griffe import Extension

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|obj|exc|const|type):`(~?)([^`]+)`")


def _role(match: re.Match[str]) -> str:
    target = match.group(2)
    if match.group(1):
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def rst_to_markdown(text: str) -> str:
    text = _ROLE.sub(_role, text)
    return re.sub(r"(\S)::[ \t]*$", r"\1:", text, flags=re.MULTILINE)


class RstRoles(Extension):
    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
