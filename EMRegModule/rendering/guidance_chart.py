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


def plan_ct_views(sample, entry_mm: np.ndarray, target_mm: np.ndarray, tips_mm: np.ndarray,
                  closest_mm: np.ndarray | None = None, mm_per_px: float = 0.5, half_width_mm: float = 60.0,
                  near_mm: float = 3.0) -> np.ndarray:
    """Two CT planes containing the planned line (image LPS mm), side by side: the line (red, Entry to Target), the tip
    positions within ``near_mm`` of each plane (blue) and the closest approach (yellow). ``sample(points (..., 3))``
    gives the CT's values there (NaN outside). Each plane runs along the plan from 30 mm before the Entry to 30 mm
    beyond the Target (vertical, Entry at the top) and ``half_width_mm`` to each side; ``mm_per_px`` per pixel."""
    entry, target = np.asarray(entry_mm, dtype=float), np.asarray(target_mm, dtype=float)
    length = float(np.linalg.norm(target - entry))
    u = (target - entry) / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    across_1 = np.cross(u, helper)
    across_1 /= np.linalg.norm(across_1)
    across_2 = np.cross(u, across_1)
    down = np.arange(-30.0, length + 30.0, mm_per_px)
    side = np.arange(-half_width_mm, half_width_mm, mm_per_px)
    tips = np.asarray(tips_mm, dtype=float).reshape(-1, 3)
    panels = []
    for name, across, normal in (("plane 1", across_1, across_2), ("plane 2", across_2, across_1)):
        points = entry + down[:, None, None] * u + side[None, :, None] * across
        values = np.asarray(sample(points), dtype=float)
        finite = values[np.isfinite(values)]
        low, high = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
        grey = np.clip((np.nan_to_num(values, nan=low) - low) / max(high - low, 1e-6) * 255, 0, 255).astype(np.uint8)
        panel = np.repeat(grey[:, :, None], 3, axis=2).copy()

        def pixel(p: np.ndarray, across: np.ndarray = across) -> tuple[int, int]:
            d = p - entry
            return (int(round((d @ across + half_width_mm) / mm_per_px)), int(round((d @ u + 30.0) / mm_per_px)))

        cv2.line(panel, pixel(entry), pixel(target), plots.HIGHLIGHT, 2,
                 cv2.LINE_AA)
        offsets = (tips - entry) @ normal
        for tip in tips[np.abs(offsets) <= near_mm]:
            cv2.circle(panel, pixel(tip), 1, (80, 160, 255), -1)
        if closest_mm is not None:
            cv2.circle(panel, pixel(np.asarray(closest_mm, dtype=float)), 4, (255, 220, 0), -1, cv2.LINE_AA)
        for where, label in ((entry, "Entry"), (target, "Target")):
            x, y = pixel(where)
            put_text(panel, label, x + 8, y + 4, 0.4, (255, 255, 255))
        cv2.rectangle(panel, (0, 0), (60, 22), (32, 32, 36), -1)
        put_text(panel, name, 6, 16, 0.4, (255, 255, 255))
        panels.append(panel)
    gap = np.full((panels[0].shape[0], 6, 3), 255, dtype=np.uint8)
    return np.concatenate([panels[0], gap, panels[1]], axis=1)
