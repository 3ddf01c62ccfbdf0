"""The report's robot figures drawn with :mod:`.plots`' axes and colours.

- :func:`residual_panels`: the hand-eye residual of every tracker sample over the recording, rotation (degrees) above
  translation (mm), the samples the calibration used in blue and those it left out in red (beyond the scale: a red
  mark on the top edge).
"""

from __future__ import annotations

import cv2
import numpy as np

from . import plots
from .text import put_text


def _panel(time_s: np.ndarray, values: np.ndarray, rejected: np.ndarray, title: str, y_label: str,
           x_label: str, size: tuple[int, int]) -> np.ndarray:
    width, height = size
    canvas = np.full((height, width, 3), plots.WHITE, dtype=np.uint8)
    finite = np.isfinite(values) & np.isfinite(time_s)
    used = finite & ~rejected
    scale = values[used] if np.any(used) else values[finite]
    top = 1.3 * float(np.percentile(scale, 99)) if scale.size else 1.0
    ticks = plots.nice_ticks(0.0, max(top, 1e-3), 5)
    start, end = (float(time_s[finite].min()), float(time_s[finite].max())) if np.any(finite) else (0.0, 1.0)
    end = end if end > start else start + 1.0
    axes = plots.Axes(canvas, 62, 34, width - 20, height - 46, (start, end), ticks)
    put_text(canvas, title, width / 2, 20, 0.5, align="center")
    axes.draw_y_grid(y_label)
    x_ticks = plots.nice_ticks(start, end, 8)
    for tick in x_ticks:
        if start <= tick <= end:
            px = int(round(axes.x(tick)))
            cv2.line(canvas, (px, axes.bottom), (px, axes.bottom + 4), plots.AXIS, 1)
            put_text(canvas, f"{tick:g}", px, axes.bottom + 17, 0.38, align="center")
    put_text(canvas, x_label, (axes.left + axes.right) / 2, height - 8, 0.4, align="center")
    ceiling = float(ticks[-1])
    for keep, color in ((finite & ~rejected, plots.LINE), (finite & rejected, plots.HIGHLIGHT)):
        for t, value in zip(time_s[keep], values[keep], strict=True):
            x = int(round(axes.x(t)))
            if value > ceiling:
                cv2.drawMarker(canvas, (x, axes.top + 4), color, cv2.MARKER_TRIANGLE_UP, 7, 1)
            else:
                cv2.circle(canvas, (x, int(round(axes.y(value)))), 2, color, -1, cv2.LINE_AA)
    return canvas


def residual_panels(time_s: np.ndarray, rotation_deg: np.ndarray, translation_mm: np.ndarray, rejected: np.ndarray,
                    size: tuple[int, int] = (760, 260)) -> np.ndarray:
    """Two panels over the recording's time (s from its first sample): the rotation residual (degrees) and the
    translation residual (mm) of each tracker sample; ``rejected`` (bool) in red. NaN values are left out."""
    time_s = np.asarray(time_s, dtype=float)
    rejected = np.asarray(rejected, dtype=bool)
    start = float(np.nanmin(time_s)) if time_s.size else 0.0
    label = "time from the tracker recording's start (s)"
    return np.vstack([
        _panel(time_s - start, np.asarray(rotation_deg, dtype=float), rejected,
               "Rotation residual per sample (blue: used, red: left out)", "rotation (deg)", label, size),
        _panel(time_s - start, np.asarray(translation_mm, dtype=float), rejected,
               "Translation residual per sample (blue: used, red: left out)", "translation (mm)", label, size)])
