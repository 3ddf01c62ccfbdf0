"""The predicted end-to-end TRE over the CT (written as ``OUT/tre_map.nrrd``, a colour overlay for 3D Slicer, by
:mod:`EMRegModule.io.tre_map`).

The map holds the RMS TRE (mm, float32) that :mod:`EMRegModule.core.error_model` predicts at each node
of a grid covering the CT's physical extent, in the CT's own LPS space: the same origin and
direction cosines as the CT, a coarser spacing (the prediction is a smooth quadratic function of
position, so trilinear interpolation between nodes a few millimetres apart is exact to a few
per cent), so that 3D Slicer shows it as a scalar volume aligned with the CT.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import EMRegError
from .error_model import ErrorModel

#: Nodes along the CT's longest side (the grid is isotropic).
MAP_NODES = 64


@dataclass(frozen=True)
class TreMap:
    """The predicted RMS TRE (mm) at the nodes of a grid in the CT's LPS space: ``values_mm`` (k, j, i) float32,
    the grid's ``spacing`` (3,) mm, ``origin`` (3,) LPS mm and ``direction`` (3, 3), its columns the i, j, k axes."""

    values_mm: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray


def map_grid(geometry: Mapping[str, Any], nodes: int = MAP_NODES) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
    """(size (3,), spacing (3,), origin (3,), direction (3, 3)) of the map grid for a CT geometry.

    ``geometry``: the CT's ``size``, ``spacing``, ``origin`` and ``direction`` (9 numbers, row-major),
    as in ``markers.json``'s ``image`` block. The grid starts at the CT's first voxel centre, has
    the CT's direction cosines, and covers at least the CT's extent.
    """
    try:
        size = np.asarray(geometry["size"], dtype=float).reshape(3)
        spacing = np.asarray(geometry["spacing"], dtype=float).reshape(3)
        origin = np.asarray(geometry["origin"], dtype=float).reshape(3)
        direction = np.asarray(geometry["direction"], dtype=float).reshape(3, 3)
    except (KeyError, TypeError, ValueError) as exc:
        raise EMRegError(f"the CT geometry needed for the TRE map is incomplete ({exc})") from None
    extent = (size - 1) * spacing
    step = max(float(extent.max()) / (nodes - 1), float(spacing.max()))
    map_size = np.ceil(extent / step - 1e-9).astype(int) + 1
    return map_size, np.full(3, step), origin, direction


def predicted_tre_map(model: ErrorModel, geometry: Mapping[str, Any], tracking_ms: float | None = None,
                      nodes: int = MAP_NODES) -> TreMap:
    """The map (mm) in the CT's LPS space; see the module docstring.

    ``tracking_ms``: the probe's per-dwell mean-square error measured at navigation time, when an
    evaluation measured it (the same value the evaluation's predictions used).
    """
    size, spacing, origin, direction = map_grid(geometry, nodes)
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    index = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(float)
    points_image = origin + (index * spacing) @ direction.T
    values = np.empty(len(points_image), dtype=np.float32)
    for start in range(0, len(points_image), 65536):  # bounded memory for the per-point matrices
        chunk = points_image[start:start + 65536]
        values[start:start + len(chunk)] = model.budget(chunk, tracking_ms).rms_mm
    return TreMap(values.reshape(tuple(size[::-1])), spacing, origin, direction)
