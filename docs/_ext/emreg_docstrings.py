"""Docstrings as the API reference reads them: EMReg's docstrings write norms as ``|x|`` in prose.

reStructuredText would take ``|x|`` for a substitution and fail the build; EMReg's docstrings never use
substitutions, so a bar outside an inline literal is kept as a plain bar.
"""

from __future__ import annotations

import re

_LITERAL = re.compile(r"(``.*?``)")


def _plain_bars(line: str) -> str:
    parts = _LITERAL.split(line)
    return "".join(part if i % 2 else part.replace("|", r"\|") for i, part in enumerate(parts))


def process_docstring(app, what, name, obj, options, lines: list[str]) -> None:
    lines[:] = [_plain_bars(line) for line in lines]


def setup(app):
    app.connect("autodoc-process-docstring", process_docstring)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
