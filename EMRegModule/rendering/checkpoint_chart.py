"""The report's checkpoint figure: the error at each checkpoint during navigation over time, with the limit.

Drawn with :mod:`.plots`' axes and colours, so it looks like the report's other charts.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from . import plots

#: The charts' text function (``put_text`` where the text helpers live in :mod:`.text`, else ``plots._put``).
_text = getattr(plots, "put_text", None) or plots._put


def checkpoint_chart(
    time_s: Sequence[float], error_mm: Sequence[float], ok: Sequence[bool], limit_mm: float,
    jumps_s: Sequence[float] = (), size: tuple[int, int] = (760, 320),
) -> np.ndarray:
    """The error at each checkpoint (mm) over the navigation's time (s): a dot per checkpoint (passed: blue,
    failed: red), the limit as a dashed line, the reference sensor's jumps as dotted vertical lines."""
    time_s, error_mm = np.asarray(time_s, dtype=float), np.asarray(error_mm, dtype=float)
    if time_s.shape != error_mm.shape or time_s.size == 0:
        raise ValueError("checkpoint_chart needs equal-length arrays of at least one checkpoint")
    width, height = size
    canvas = np.full((height, width, 3), plots.WHITE, dtype=np.uint8)
    ticks = plots.nice_ticks(0.0, max(float(np.max(error_mm)), limit_mm) * 1.15, 5)
    every = np.concatenate([time_s, np.asarray(jumps_s, dtype=float)])
    start, end = float(every.min()), float(every.max())
    pad = max(1.0, 0.05 * (end - start))
    axes = plots.Axes(canvas, 62, 34, width - 20, height - 46, (start - pad, end + pad), ticks)
    _text(canvas, "Error at each checkpoint", width / 2, 20, 0.5, align="center")
    axes.draw_y_grid("error (mm)")
    x_ticks = plots.nice_ticks(start - pad, end + pad, 8)
    x_step = float(x_ticks[1] - x_ticks[0]) if len(x_ticks) > 1 else 1.0
    for tick in x_ticks:
        if start - pad <= tick <= end + pad:
            px = int(round(axes.x(tick)))
            cv2.line(canvas, (px, axes.bottom), (px, axes.bottom + 4), plots.AXIS, 1)
            _text(canvas, plots._format_tick(tick, x_step), px, axes.bottom + 17, 0.38, align="center")
    _text(canvas, "navigation time (s)", (axes.left + axes.right) / 2, height - 8, 0.4, align="center")
    for jump in jumps_s:
        px = int(round(axes.x(float(jump))))
        for yy in range(axes.top, axes.bottom, 6):
            cv2.line(canvas, (px, yy), (px, min(yy + 2, axes.bottom)), plots.REFERENCE, 1)
        _text(canvas, "reference jump", px + 4, axes.top + 12, 0.34, plots.REFERENCE)
    axes.dashed_hline(limit_mm, plots.HIGHLIGHT, f"limit {limit_mm:g} mm")
    for t, e, good in zip(time_s, error_mm, ok, strict=True):
        color = plots.LINE if good else plots.HIGHLIGHT
        cv2.circle(canvas, (int(round(axes.x(t))), int(round(axes.y(e)))), 5, color, -1, cv2.LINE_AA)
    return canvas
