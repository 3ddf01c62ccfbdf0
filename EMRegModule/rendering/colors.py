"""Colour maps for residuals and plots, taken from OpenCV's built-in tables.

matplotlib is not a dependency, so the 256-entry tables come from ``cv2.applyColorMap``.
Colours are RGB ``uint8``.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

_OPENCV_MAPS = {
    "viridis": cv2.COLORMAP_VIRIDIS,
    "plasma": cv2.COLORMAP_PLASMA,
    "inferno": cv2.COLORMAP_INFERNO,
    "magma": cv2.COLORMAP_MAGMA,
    "cividis": cv2.COLORMAP_CIVIDIS,
    "turbo": cv2.COLORMAP_TURBO,
    "jet": cv2.COLORMAP_JET,
    "hot": cv2.COLORMAP_HOT,
    "bone": cv2.COLORMAP_BONE,
}

#: The colour map of residuals (mm) in every figure.
DEFAULT_COLORMAP = "viridis"

#: Fixed colours (RGB) used across figures.
GREY = (150, 150, 150)
PAIRED = (40, 200, 80)
UNPAIRED = (255, 140, 0)
SENSOR = (255, 220, 0)
CALIBRATION = (230, 40, 230)
TARGET = (220, 30, 30)
NAVIGATION = (0, 190, 230)


def colormap_names() -> list[str]:
    """Names accepted by :func:`colormap_table`."""
    return sorted(_OPENCV_MAPS)


@cache
def _table(name: str) -> np.ndarray:
    if name not in _OPENCV_MAPS:
        raise ValueError(f"unknown colour map {name!r}; known: {', '.join(colormap_names())}")
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    bgr = cv2.applyColorMap(ramp, _OPENCV_MAPS[name]).reshape(256, 3)
    table = bgr[:, ::-1].copy()
    table.setflags(write=False)
    return table


def colormap_table(name: str = DEFAULT_COLORMAP) -> np.ndarray:
    """The (256, 3) RGB ``uint8`` table of a colour map."""
    return _table(name)


def colorize(values: np.ndarray, vmin: float, vmax: float, name: str = DEFAULT_COLORMAP) -> np.ndarray:
    """RGB ``uint8`` colours (N, 3) of ``values`` mapped linearly from [vmin, vmax] onto the map."""
    values = np.asarray(values, dtype=float).reshape(-1)
    span = vmax - vmin if vmax > vmin else 1.0
    index = np.clip(np.round((values - vmin) / span * 255.0), 0, 255).astype(int)
    return colormap_table(name)[index]


def residual_range(residuals_mm: np.ndarray) -> tuple[float, float]:
    """The colour range (mm) for residuals: 0 to the next 0.5 mm step above the largest, at least 1 mm."""
    residuals_mm = np.asarray(residuals_mm, dtype=float)
    top = float(np.nanmax(residuals_mm)) if residuals_mm.size and np.any(np.isfinite(residuals_mm)) else 0.0
    return 0.0, max(1.0, float(np.ceil(top * 2.0 + 1e-9) / 2.0))
