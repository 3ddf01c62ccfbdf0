"""Small, clean plots drawn with OpenCV (matplotlib is not a dependency).

- :func:`bar_chart`: one bar per item (FRE per marker, TRE per target) with optional error
  bars, per-bar colours and dashed reference lines;
- :func:`line_chart`: a curve (FRE(l) over the pinhole range) with a marked x (the chosen l).

Output: RGB ``uint8`` images on a white background; drawing is deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .text import INK, put_text, put_vertical_text, text_size

WHITE = (255, 255, 255)
BLACK = INK
GRID = (225, 225, 225)
AXIS = (90, 90, 90)
BAR = (70, 120, 200)
LINE = (40, 90, 180)
HIGHLIGHT = (220, 60, 40)
REFERENCE = (120, 120, 120)


def nice_ticks(low: float, high: float, count: int = 5) -> np.ndarray:
    """Round tick values covering [low, high] with about ``count`` steps of 1, 2, 2.5 or 5 x 10^k."""
    if not np.isfinite(low) or not np.isfinite(high) or high <= low:
        high = low + 1.0
    raw = (high - low) / max(1, count)
    magnitude = 10.0 ** np.floor(np.log10(raw))
    step = next(m * magnitude for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * magnitude >= raw)
    start = np.floor(low / step + 1e-9) * step
    stop = np.ceil(high / step - 1e-9) * step
    return np.round(np.arange(start, stop + step / 2, step), 10)


def fit_text(text: str, max_width_px: float, scale: float = 0.38) -> str:
    """``text`` as it fits in ``max_width_px`` pixels at font ``scale``: whole when it fits, else cut and ended
    with "..." (so that a cut shows; the report's tables hold the whole text). A user's label (a target's, a
    pinhole's) of any length then never runs over its neighbours or squeezes a plot to nothing."""
    if text_size(text, scale)[0] <= max_width_px:
        return text
    low, high = 0, len(text)  # the longest prefix that fits with the ellipsis: text[:low]
    while low < high:
        middle = (low + high + 1) // 2
        if text_size(text[:middle].rstrip() + "...", scale)[0] <= max_width_px:
            low = middle
        else:
            high = middle - 1
    return text[:low].rstrip() + "..."


def _format_tick(value: float, step: float) -> str:
    decimals = max(0, int(np.ceil(-np.log10(step) + 1e-9))) if step < 1 else 0
    if step < 1 and abs(step * 10 ** decimals - round(step * 10 ** decimals)) > 1e-6:
        decimals += 1
    return f"{value:.{decimals}f}"


class Axes:
    """Maps data coordinates to pixels inside a plot rectangle and draws the frame and grid."""

    def __init__(self, canvas: np.ndarray, left: int, top: int, right: int, bottom: int,
                 x_range: tuple[float, float], y_ticks: np.ndarray) -> None:
        self.canvas, self.left, self.top, self.right, self.bottom = canvas, left, top, right, bottom
        self.x_range = x_range
        self.y_ticks = y_ticks
        self.y_range = (float(y_ticks[0]), float(y_ticks[-1]))

    def x(self, value: float) -> float:
        lo, hi = self.x_range
        return self.left + (value - lo) / (hi - lo) * (self.right - self.left)

    def y(self, value: float) -> float:
        lo, hi = self.y_range
        return self.bottom - (value - lo) / (hi - lo) * (self.bottom - self.top)

    def draw_y_grid(self, y_label: str) -> None:
        step = float(self.y_ticks[1] - self.y_ticks[0]) if len(self.y_ticks) > 1 else 1.0
        for tick in self.y_ticks:
            y = int(round(self.y(tick)))
            cv2.line(self.canvas, (self.left, y), (self.right, y), GRID, 1)
            put_text(self.canvas, _format_tick(tick, step), self.left - 6, y + 4, 0.38, align="right")
        cv2.line(self.canvas, (self.left, self.top), (self.left, self.bottom), AXIS, 1)
        cv2.line(self.canvas, (self.left, self.bottom), (self.right, self.bottom), AXIS, 1)
        if y_label:
            put_vertical_text(self.canvas, y_label, 14, (self.top + self.bottom) / 2, 0.4, align="center")

    def dashed_hline(self, value: float, color, label: str = "") -> None:
        y = int(round(self.y(value)))
        for x in range(self.left, self.right, 10):
            cv2.line(self.canvas, (x, y), (min(x + 5, self.right), y), color, 1, cv2.LINE_AA)
        if label:
            text_width, text_height = text_size(label, 0.36)
            x1 = self.right - 4
            cv2.rectangle(self.canvas, (x1 - text_width - 3, y - text_height - 7), (x1 + 2, y - 2), WHITE, -1)
            put_text(self.canvas, label, x1, y - 5, 0.36, color, align="right")


def bar_chart(
    labels: Sequence[str], values: Sequence[float], errors: Sequence[float] | None = None, title: str = "",
    y_label: str = "", colors: Sequence[tuple[int, int, int]] | None = None,
    reference_lines: Sequence[tuple[float, str]] = (), size: tuple[int, int] = (760, 360),
    value_format: str = "{:.2f}", overlay: Sequence[float] | None = None, overlay_label: str = "",
) -> np.ndarray:
    """A bar chart: one bar per label, optional symmetric error bars and dashed reference lines.

    ``colors`` are RGB per bar; values are written above the bars when there is room.
    ``overlay`` draws a second value per bar as a red tick (e.g. a prediction), named in a legend.
    """
    values = np.asarray(values, dtype=float)
    if len(labels) != len(values):
        raise ValueError("bar_chart needs one value per label")
    width, height = size
    canvas = np.full((height, width, 3), WHITE, dtype=np.uint8)
    errors_arr = np.zeros_like(values) if errors is None else np.nan_to_num(np.asarray(errors, dtype=float))
    overlay_arr = None if overlay is None else np.asarray(overlay, dtype=float)
    top_value = max([0.0, *np.nan_to_num(values + errors_arr).tolist(), *(v for v, _ in reference_lines),
                     *(np.nan_to_num(overlay_arr).tolist() if overlay_arr is not None else [])])
    ticks = nice_ticks(0.0, top_value * 1.12 if top_value > 0 else 1.0, 5)
    labels = [fit_text(str(lab), height / 3) for lab in labels]  # a vertical label takes at most a third
    longest = max((text_size(lab, 0.38)[0] for lab in labels), default=0)
    n = max(1, len(labels))
    slot = (width - 70 - 20) / n
    vertical_labels = longest > slot - 4
    bottom_margin = (longest + 14) if vertical_labels else 26
    axes = Axes(canvas, 62, 34, width - 20, height - bottom_margin, (0.0, float(n)), ticks)
    if title:
        put_text(canvas, title, width / 2, 20, 0.5, align="center")
    axes.draw_y_grid(y_label)
    bar_width = max(2.0, slot * 0.7)
    for i, value in enumerate(values):
        centre = axes.x(i + 0.5)
        color = tuple(int(c) for c in colors[i]) if colors is not None else BAR
        if np.isfinite(value):
            x0, x1 = int(round(centre - bar_width / 2)), int(round(centre + bar_width / 2))
            y0, y1 = int(round(axes.y(value))), int(round(axes.y(0.0)))
            cv2.rectangle(canvas, (x0, min(y0, y1)), (x1, max(y0, y1)), color, -1)
            if errors is not None and errors_arr[i] > 0:
                cx = int(round(centre))
                ya, yb = int(round(axes.y(value - errors_arr[i]))), int(round(axes.y(value + errors_arr[i])))
                cv2.line(canvas, (cx, ya), (cx, yb), BLACK, 1)
                cv2.line(canvas, (cx - 4, ya), (cx + 4, ya), BLACK, 1)
                cv2.line(canvas, (cx - 4, yb), (cx + 4, yb), BLACK, 1)
            text = value_format.format(value)
            if text_size(text, 0.34)[0] < slot:
                label_y = axes.y(value + errors_arr[i]) - 5
                put_text(canvas, text, centre, label_y, 0.34, align="center")
        label = str(labels[i])
        if vertical_labels:
            put_vertical_text(canvas, label, centre, axes.bottom + 6, 0.38)
        else:
            put_text(canvas, label, centre, axes.bottom + 17, 0.38, align="center")
    if overlay_arr is not None:
        for i, value in enumerate(overlay_arr):
            if np.isfinite(value):
                centre = axes.x(i + 0.5)
                y = int(round(axes.y(value)))
                cv2.line(canvas, (int(round(centre - bar_width * 0.45)), y), (int(round(centre + bar_width * 0.45)), y),
                         HIGHLIGHT, 3)
        if overlay_label:
            cv2.line(canvas, (axes.left + 10, axes.top + 8), (axes.left + 34, axes.top + 8), HIGHLIGHT, 3)
            put_text(canvas, overlay_label, axes.left + 40, axes.top + 12, 0.38, HIGHLIGHT)
    for value, text in reference_lines:
        axes.dashed_hline(value, REFERENCE, text)
    return canvas


def line_chart(
    x: Sequence[float], y: Sequence[float], title: str = "", x_label: str = "", y_label: str = "",
    marker_x: float | None = None, marker_label: str = "", size: tuple[int, int] = (760, 360),
) -> np.ndarray:
    """A curve y(x) with an optional marked abscissa (vertical line and a dot on the curve)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.shape != y.shape or x.size < 2:
        raise ValueError("line_chart needs two equal-length arrays of at least 2 values")
    width, height = size
    canvas = np.full((height, width, 3), WHITE, dtype=np.uint8)
    finite = np.isfinite(y)
    y_low, y_high = (float(np.min(y[finite])), float(np.max(y[finite]))) if finite.any() else (0.0, 1.0)
    pad = 0.08 * (y_high - y_low) if y_high > y_low else 0.5
    ticks = nice_ticks(max(0.0, y_low - pad) if y_low >= 0 else y_low - pad, y_high + pad, 5)
    axes = Axes(canvas, 62, 34, width - 20, height - 46, (float(x.min()), float(x.max())), ticks)
    if title:
        put_text(canvas, title, width / 2, 20, 0.5, align="center")
    axes.draw_y_grid(y_label)
    x_ticks = nice_ticks(float(x.min()), float(x.max()), 8)
    x_step = float(x_ticks[1] - x_ticks[0]) if len(x_ticks) > 1 else 1.0
    for tick in x_ticks:
        if x.min() - 1e-9 <= tick <= x.max() + 1e-9:
            px = int(round(axes.x(tick)))
            cv2.line(canvas, (px, axes.bottom), (px, axes.bottom + 4), AXIS, 1)
            put_text(canvas, _format_tick(tick, x_step), px, axes.bottom + 17, 0.38, align="center")
    if x_label:
        put_text(canvas, x_label, (axes.left + axes.right) / 2, height - 8, 0.4, align="center")
    points = np.stack([[axes.x(a), axes.y(b)] for a, b in zip(x[finite], y[finite], strict=True)])
    cv2.polylines(canvas, [np.round(points * 16).astype(np.int32)], False, LINE, 2, cv2.LINE_AA, 4)
    if marker_x is not None and np.isfinite(marker_x):
        px = int(round(axes.x(marker_x)))
        for yy in range(axes.top, axes.bottom, 8):
            cv2.line(canvas, (px, yy), (px, min(yy + 4, axes.bottom)), HIGHLIGHT, 1)
        marker_y = float(np.interp(marker_x, x[finite], y[finite]))
        cv2.circle(canvas, (px, int(round(axes.y(marker_y)))), 5, HIGHLIGHT, -1, cv2.LINE_AA)
        if marker_label:
            align = "left" if px < (axes.left + axes.right) / 2 else "right"
            put_text(canvas, marker_label, px + (8 if align == "left" else -8), axes.top + 14, 0.4, HIGHLIGHT,
                 align=align)
    return canvas
