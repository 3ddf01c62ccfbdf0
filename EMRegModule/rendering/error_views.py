"""Pictures of the error model: the error budget per target and slices of the predicted TRE map.

- :func:`error_budget_chart`: per target a stacked bar whose segments are the terms of the
  predicted end-to-end RMS TRE (they add in quadrature, so each segment is what its term adds to
  the root of the sum of squares so far) and the measured RMS TRE as a black tick.
- :func:`tre_map_slices`: three orthogonal planes of ``tre_map.nrrd`` through the targets' centre,
  coloured by the predicted RMS TRE (mm), with iso-lines and the targets marked.
- :func:`distortion_views`: the registration's residual vectors at the pinholes and the fitted field
  distortion (its size in colour, its vectors) in two views of the frame.

Output: RGB ``uint8`` images on a white background, drawn with OpenCV.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import cv2
import numpy as np
import SimpleITK as sitk

from .colors import colorize
from .plots import BLACK, WHITE, Axes, fit_text, nice_ticks
from .text import put_text, text_size

#: Segment colours of the budget's terms (RGB).
TERM_COLORS = {"registration": (70, 120, 200), "tracking": (240, 160, 60), "reference": (120, 180, 110),
               "placement": (170, 120, 190), "distortion": (200, 60, 60)}


def error_budget_chart(labels: Sequence[str], budget_rms_mm: Mapping[str, Sequence[float]],
                       measured_rms_mm: Sequence[float], size: tuple[int, int] = (760, 380)) -> np.ndarray:
    """Stacked predicted-error bars per target with the measured RMS TRE as a black tick (mm)."""
    terms = [t for t in budget_rms_mm if np.any(np.nan_to_num(np.asarray(budget_rms_mm[t], dtype=float)) > 0)]
    squares = np.cumsum([np.square(np.asarray(budget_rms_mm[t], dtype=float)) for t in terms], axis=0)
    tops = np.sqrt(squares)  # (terms, targets): the predicted RMS after each term
    measured = np.asarray(measured_rms_mm, dtype=float)
    width, height = size
    canvas = np.full((height, width, 3), WHITE, dtype=np.uint8)
    highest = float(np.nanmax(np.r_[tops[-1] if len(tops) else [0.0], measured, 0.1]))
    axes = Axes(canvas, 62, 56, width - 20, height - 28, (0.0, float(len(labels))),
                 nice_ticks(0.0, highest * 1.1, 5))
    put_text(canvas, "Predicted error budget and measured TRE per target", width / 2, 18, 0.5, align="center")
    axes.draw_y_grid("RMS TRE (mm)")
    slot = (axes.right - axes.left) / max(1, len(labels))
    for k, label in enumerate(labels):
        centre = axes.x(k + 0.5)
        x0, x1 = int(round(centre - slot * 0.3)), int(round(centre + slot * 0.3))
        bottom = 0.0
        for t, term in enumerate(terms):
            top = float(tops[t, k])
            if np.isfinite(top) and top > bottom:
                cv2.rectangle(canvas, (x0, int(round(axes.y(top)))), (x1, int(round(axes.y(bottom)))),
                              TERM_COLORS.get(term, (150, 150, 150)), -1)
                bottom = top
        if np.isfinite(measured[k]):
            y = int(round(axes.y(measured[k])))
            cv2.line(canvas, (x0 - 6, y), (x1 + 6, y), BLACK, 3)
        put_text(canvas, fit_text(str(label), slot - 4), centre, axes.bottom + 17, 0.38, align="center")
    x = axes.left + 4
    for term in terms:
        cv2.rectangle(canvas, (x, 32), (x + 14, 44), TERM_COLORS.get(term, (150, 150, 150)), -1)
        put_text(canvas, term, x + 18, 43, 0.38)
        x += 26 + text_size(term, 0.38)[0]
    cv2.line(canvas, (x, 38), (x + 16, 38), BLACK, 3)
    put_text(canvas, "measured", x + 20, 43, 0.38)
    return canvas


#: The widest a target's label is drawn on the TRE map (pixels; a longer one is cut with "...").
LABEL_WIDTH_PX = 110


def _iso_levels(low: float, high: float) -> list[float]:
    """1 and 2 mm when they fall inside the map's range, else round levels inside it."""
    levels = [v for v in (1.0, 2.0) if low < v < high]
    return levels or [float(v) for v in nice_ticks(low, high, 4) if low < v < high]


def tre_map_slices(tre_map: sitk.Image, targets_image: np.ndarray, labels: Sequence[str] = (),
                   panel_px: int = 300) -> np.ndarray:
    """Three index planes of the map through the targets' centre (mm colour scale, iso-lines, targets)."""
    values = sitk.GetArrayFromImage(tre_map).astype(float)  # (k, j, i)
    targets = np.asarray(targets_image, dtype=float).reshape(-1, 3)
    centre_point = targets.mean(axis=0) if len(targets) else np.asarray(tre_map.TransformContinuousIndexToPhysicalPoint(
        [(n - 1) / 2 for n in tre_map.GetSize()]))
    centre = np.clip(np.round(tre_map.TransformPhysicalPointToContinuousIndex(centre_point.tolist())), 0,
                     np.asarray(tre_map.GetSize()) - 1).astype(int)
    target_index = np.array([tre_map.TransformPhysicalPointToContinuousIndex(p.tolist()) for p in targets]
                            ).reshape(-1, 3)
    finite = values[np.isfinite(values)]
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    high = max(high, low + 1e-3)
    planes = [("k", values[centre[2]], (0, 1)), ("j", values[:, centre[1], :], (0, 2)),
              ("i", values[:, :, centre[0]], (1, 2))]  # (name, 2D array (rows, cols), index axes of cols, rows)
    panels = []
    for name, plane, (col_axis, row_axis) in planes:
        panels.append(_map_panel(plane, (low, high), target_index, col_axis, row_axis, labels, panel_px,
                                 f"plane {name} = {centre['ijk'.index(name)]}"))
    legend = _colour_legend(low, high, 3 * panel_px)
    return np.vstack([np.hstack(panels), legend])


def _map_panel(plane: np.ndarray, value_range: tuple[float, float], target_index: np.ndarray, col_axis: int,
               row_axis: int, labels: Sequence[str], panel_px: int, title: str) -> np.ndarray:
    low, high = value_range
    rows, cols = plane.shape
    scale = (panel_px - 30) / max(rows, cols)
    shape = (max(1, int(round(cols * scale))), max(1, int(round(rows * scale))))
    smooth = cv2.resize(np.nan_to_num(plane, posinf=high).astype(np.float32), shape, interpolation=cv2.INTER_LINEAR)
    rgb = colorize(smooth, low, high).reshape(smooth.shape + (3,)).astype(np.uint8)
    for level in _iso_levels(low, high):
        contours, _ = cv2.findContours((smooth >= level).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(rgb, contours, -1, (255, 255, 255), 1, cv2.LINE_AA)
    for index, label in zip(target_index, list(labels) + [""] * len(target_index), strict=False):
        x, y = int(round(index[col_axis] * scale)), int(round(index[row_axis] * scale))
        cv2.drawMarker(rgb, (x, y), (0, 0, 0), cv2.MARKER_CROSS, 9, 2)
        if label:
            put_text(rgb, fit_text(str(label), LABEL_WIDTH_PX, 0.35), x + 6, y - 4, 0.35, (0, 0, 0))
    panel = np.full((panel_px, panel_px, 3), WHITE, dtype=np.uint8)
    panel[24:24 + rgb.shape[0], 4:4 + rgb.shape[1]] = rgb[: panel_px - 24, : panel_px - 4]
    put_text(panel, title, panel_px / 2, 16, 0.4, align="center")
    return panel


def _colour_legend(low: float, high: float, width: int) -> np.ndarray:
    legend = np.full((58, width, 3), WHITE, dtype=np.uint8)
    ramp = colorize(np.tile(np.linspace(low, high, width - 120), (12, 1)), low, high).reshape(12, -1, 3)
    legend[6:18, 60:60 + ramp.shape[1]] = ramp
    for tick in nice_ticks(low, high, 5):
        if low <= tick <= high:
            x = 60 + int(round((tick - low) / (high - low) * (ramp.shape[1] - 1)))
            put_text(legend, f"{tick:g}", x, 34, 0.35, align="center")
    put_text(legend, "mm", 60 + ramp.shape[1] + 10, 17, 0.38)
    levels = ", ".join(f"{v:g}" for v in _iso_levels(low, high))
    put_text(legend, f"predicted RMS TRE; white iso-lines at {levels} mm; + targets", width / 2, 52, 0.35,
         align="center")
    return legend


def distortion_views(points_mm: np.ndarray, residuals_mm: np.ndarray, fitted_mm: np.ndarray,
                     field_size: Callable[[np.ndarray], np.ndarray], title: str, panel_px: int = 380,
                     arrow_px_per_mm: float | None = None) -> np.ndarray:
    """Two views of the frame's pinholes (Reference frame, mm) along their principal axes: the fitted
    distortion field's size (colour, mm) on the plane through the pinholes' centroid, each pinhole's
    residual vector (black arrow) and the fitted non-rigid field there (magenta arrow), both magnified.

    ``points_mm``, ``residuals_mm``, ``fitted_mm`` (N, 3); ``field_size``: the field's size (mm) at points (K, 3).
    """
    points = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    centroid = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - centroid)  # rows: the principal directions, widest first
    extent = float(np.max(np.abs((points - centroid) @ axes.T))) * 1.15 + 1.0
    largest = float(max(np.max(np.linalg.norm(residuals_mm, axis=1)), np.max(np.linalg.norm(fitted_mm, axis=1)),
                        1e-3))
    magnify = arrow_px_per_mm or 0.12 * panel_px / largest
    scale = (panel_px - 40) / (2 * extent)
    grid = np.linspace(-extent, extent, 64)
    panels = []
    planes = [(0, 1, "principal axes 1-2"), (0, 2, "principal axes 1-3")]
    sizes = []
    for u, v, _ in planes:
        a, b = np.meshgrid(grid, grid)
        sample = centroid + a.reshape(-1, 1) * axes[u] + b.reshape(-1, 1) * axes[v]
        sizes.append(np.asarray(field_size(sample), dtype=float).reshape(a.shape))
    # the colours span the field at the pinholes (beyond them, towards the object, it is only extrapolated)
    high = max(1.5 * float(np.max(np.linalg.norm(fitted_mm, axis=1))), 0.5)
    for (u, v, name), size_map in zip(planes, sizes, strict=True):
        panel = np.full((panel_px, panel_px, 3), WHITE, dtype=np.uint8)
        side = panel_px - 40
        rgb = colorize(cv2.resize(size_map.astype(np.float32), (side, side), interpolation=cv2.INTER_LINEAR),
                       0.0, high).reshape(side, side, 3)
        panel[30:30 + side, 20:20 + side] = rgb[::-1]  # +v up

        def pixel(p: np.ndarray, u: int = u, v: int = v) -> tuple[int, int]:
            d = p - centroid
            return (int(round(20 + (d @ axes[u] + extent) * scale)), int(round(30 + (extent - d @ axes[v]) * scale)))

        for point, residual, fitted in zip(points, residuals_mm, fitted_mm, strict=True):
            x, y = pixel(point)
            for vector, colour, width in ((fitted, (230, 0, 230), 3), (residual, BLACK, 1)):
                tip = (int(round(x + vector @ axes[u] * magnify)), int(round(y - vector @ axes[v] * magnify)))
                cv2.arrowedLine(panel, (x, y), tip, colour, width, cv2.LINE_AA, tipLength=0.25)
            cv2.circle(panel, (x, y), 3, WHITE, -1)
            cv2.circle(panel, (x, y), 3, BLACK, 1)
        put_text(panel, name, panel_px / 2, 18, 0.42, align="center")
        panels.append(panel)
    header = np.full((30, 2 * panel_px, 3), WHITE, dtype=np.uint8)
    put_text(header, fit_text(title, 2 * panel_px - 20, 0.45), panel_px, 20, 0.45, align="center")
    legend = _colour_legend(0.0, high, 2 * panel_px)
    legend[40:, :] = WHITE
    put_text(legend, f"fitted field size (mm, capped at {high:.2g}); arrows x{magnify / scale:.0f}: residual (black), "
         "fitted field (magenta)",
         panel_px, 52, 0.35, align="center")
    return np.vstack([header, np.hstack(panels), legend])
