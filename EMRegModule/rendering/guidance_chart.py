"""The report's guidance figures: the tip's approach to the planned target.

- :func:`approach_chart`: the tip's distance to the target and its lateral offset from the planned line over the
  navigation's time (s, mm), the closest approach marked, the predicted 95 % radius at the target dashed;
- :func:`plan_view_chart`: the tip path in the plan's own frame, a side view of the planned line: depth along the
  plan from the Entry (mm) against the distance from the line (mm), the line from Entry (0) to Target (its length).

Drawn with :mod:`.plots`' axes and colours, as the report's other charts.
"""

from __future__ import annotations

import cv2
import numpy as np

from . import plots
from .text import put_text

_text = put_text


def _x_axis(canvas: np.ndarray, axes: plots.Axes, low: float, high: float, label: str, height: int) -> None:
    ticks = plots.nice_ticks(low, high, 8)
    step = float(ticks[1] - ticks[0]) if len(ticks) > 1 else 1.0
    for tick in ticks:
        if low <= tick <= high:
            px = int(round(axes.x(tick)))
            cv2.line(canvas, (px, axes.bottom), (px, axes.bottom + 4), plots.AXIS, 1)
            _text(canvas, plots._format_tick(tick, step), px, axes.bottom + 17, 0.38, align="center")
    _text(canvas, label, (axes.left + axes.right) / 2, height - 8, 0.4, align="center")


def _polyline(canvas: np.ndarray, axes: plots.Axes, x: np.ndarray, y: np.ndarray, color) -> None:
    finite = np.isfinite(x) & np.isfinite(y)
    points = np.stack([[axes.x(a), axes.y(b)] for a, b in zip(x[finite], y[finite], strict=True)]) \
        if finite.any() else np.zeros((0, 2))
    if len(points) > 1:
        cv2.polylines(canvas, [np.round(points).astype(np.int32)], False, color, 1, cv2.LINE_AA)


def approach_chart(time_s: np.ndarray, distance_mm: np.ndarray, lateral_mm: np.ndarray, closest_s: float | None,
                   radius_95_mm: float | None, size: tuple[int, int] = (760, 320)) -> np.ndarray:
    """Distance to the target (blue) and from the planned line (grey) over time; the closest approach (red dot);
    the predicted 95 % radius at the target (dashed). Arrays (N,), mm and s; NaN lateral (a target alone) left out."""
    time_s, distance_mm = np.asarray(time_s, dtype=float), np.asarray(distance_mm, dtype=float)
    lateral_mm = np.asarray(lateral_mm, dtype=float)
    if time_s.size == 0 or time_s.shape != distance_mm.shape:
        raise ValueError("approach_chart needs equal-length arrays of at least one sample")
    width, height = size
    canvas = np.full((height, width, 3), plots.WHITE, dtype=np.uint8)
    top = float(np.nanmax(np.concatenate([distance_mm, lateral_mm, [radius_95_mm or 0.0]])))
    ticks = plots.nice_ticks(0.0, max(top, 1.0) * 1.05, 5)
    start, end = float(time_s.min()), float(time_s.max())
    pad = max(0.5, 0.02 * (end - start))
    axes = plots.Axes(canvas, 62, 34, width - 20, height - 46, (start - pad, end + pad), ticks)
    _text(canvas, "Tip to target (blue) and to the planned line (grey)", width / 2, 20, 0.5, align="center")
    axes.draw_y_grid("distance (mm)")
    _x_axis(canvas, axes, start - pad, end + pad, "navigation time (s)", height)
    _polyline(canvas, axes, time_s, lateral_mm, plots.REFERENCE)
    _polyline(canvas, axes, time_s, distance_mm, plots.LINE)
    if radius_95_mm is not None and np.isfinite(radius_95_mm):
        axes.dashed_hline(radius_95_mm, plots.HIGHLIGHT, f"predicted 95 % at the target: {radius_95_mm:.1f} mm")
    if closest_s is not None:
        k = int(np.argmin(np.abs(time_s - closest_s)))
        cv2.circle(canvas, (int(round(axes.x(time_s[k]))), int(round(axes.y(distance_mm[k])))), 5, plots.HIGHLIGHT,
                   -1, cv2.LINE_AA)
    return canvas


def plan_view_chart(depth_mm: np.ndarray, lateral_mm: np.ndarray, length_mm: float,
                    size: tuple[int, int] = (760, 320)) -> np.ndarray:
    """The tip path beside the planned line: depth along the plan from the Entry (mm; the Target at ``length_mm``)
    against the distance from the line (mm). The line is drawn on the x axis from 0 to ``length_mm``."""
    depth_mm, lateral_mm = np.asarray(depth_mm, dtype=float), np.asarray(lateral_mm, dtype=float)
    width, height = size
    canvas = np.full((height, width, 3), plots.WHITE, dtype=np.uint8)
    near = np.isfinite(depth_mm) & (depth_mm > -0.5 * length_mm) & (depth_mm < 1.5 * length_mm)
    top = float(np.max(lateral_mm[near])) if near.any() else 1.0
    ticks = plots.nice_ticks(0.0, max(top, 1.0) * 1.05, 5)
    low, high = -0.25 * length_mm, 1.25 * length_mm
    axes = plots.Axes(canvas, 62, 34, width - 20, height - 46, (low, high), ticks)
    _text(canvas, "Tip path beside the planned line (Entry at 0, Target at its length)", width / 2, 20, 0.5,
          align="center")
    axes.draw_y_grid("off the line (mm)")
    _x_axis(canvas, axes, low, high, "depth along the plan from the Entry (mm)", height)
    y0 = int(round(axes.y(0.0)))
    cv2.line(canvas, (int(round(axes.x(0.0))), y0), (int(round(axes.x(length_mm))), y0), plots.HIGHLIGHT, 3)
    for where, name in ((0.0, "Entry"), (length_mm, "Target")):
        px = int(round(axes.x(where)))
        cv2.circle(canvas, (px, y0), 5, plots.HIGHLIGHT, -1, cv2.LINE_AA)
        _text(canvas, name, px, y0 - 10, 0.38, plots.HIGHLIGHT, align="center")
    inside = near & np.isfinite(lateral_mm) & (lateral_mm <= ticks[-1])
    for a, b in zip(depth_mm[inside], lateral_mm[inside], strict=True):
        cv2.circle(canvas, (int(round(axes.x(a))), int(round(axes.y(b)))), 1, plots.LINE, -1)
    return canvas
