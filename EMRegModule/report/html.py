"""HTML building blocks of the report page: escaping, numbers, tables, figures, the style sheet.

Cells handed to :func:`table` are HTML already (escaped with :func:`esc` or made by :func:`num`).
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..rendering.images import png_data_uri
from .derived import finite_or_none

DASH = "&ndash;"

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;background:#f4f5f7;color:#222}
main{max-width:1100px;margin:0 auto;padding:24px}
h1{font-size:24px;margin:0 0 4px} h2{font-size:19px;margin:28px 0 10px;border-bottom:1px solid #ccc;padding-bottom:4px}
h3{font-size:16px;margin:18px 0 6px}
table{border-collapse:collapse;margin:8px 0 12px;background:#fff;font-size:13px}
th,td{border:1px solid #d6d6d6;padding:4px 8px;text-align:right} th{background:#eceef2}
td.l,th.l{text-align:left}
figure{margin:10px 0 18px;background:#fff;padding:8px;border:1px solid #ddd}
figure img{max-width:100%;height:auto;display:block}
figcaption{font-size:13px;color:#444;margin-top:6px}
.warn{background:#fff5db;border-left:4px solid #e0a800;padding:6px 10px;margin:4px 0}
.refused{background:#fde2e1;border-left:4px solid #c62828;padding:6px 10px;margin:4px 0}
.note{background:#e8f1fb;border-left:4px solid #5b8def;padding:6px 10px;margin:4px 0}
.ok{background:#e5f5e8;border-left:4px solid #2e7d32;padding:6px 10px;margin:4px 0}
.muted{color:#666;font-size:13px}
"""


def esc(value: Any) -> str:
    """``value`` as escaped HTML text."""
    return html.escape(str(value), quote=True)


def num(value: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals, or a dash when missing or not finite."""
    number = finite_or_none(value)
    return DASH if number is None else f"{number:.{digits}f}"


def vec(values: Any, digits: int = 2) -> str:
    """A vector as comma-separated numbers."""
    return ", ".join(f"{x:.{digits}f}" for x in np.asarray(values, dtype=float))


def table(header: Sequence[str], rows: Sequence[Sequence[str]], left_columns: int | Sequence[int] = 1) -> str:
    """An HTML table; cells are already-escaped HTML; ``left_columns`` (count or indices) are left-aligned."""
    left = set(range(left_columns)) if isinstance(left_columns, int) else set(left_columns)
    head = "".join(f"<th class=\"l\">{esc(h)}</th>" if i in left else f"<th>{esc(h)}</th>"
                   for i, h in enumerate(header))
    body = "".join("<tr>" + "".join(f"<td class=\"l\">{c}</td>" if i in left else f"<td>{c}</td>"
                                    for i, c in enumerate(row)) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def figure_html(figure) -> str:
    """A ``<figure>`` with the PNG embedded (the page stays self-contained)."""
    return (f"<figure id=\"fig-{esc(figure.name)}\"><img src=\"{png_data_uri(figure.png)}\" "
            f"alt=\"{esc(figure.title)}\"><figcaption><b>{esc(figure.title)}.</b> {esc(figure.caption)}"
            "</figcaption></figure>")


def note(text: str) -> str:
    """A blue note box (``text`` is HTML)."""
    return f"<div class=\"note\">{text}</div>"
