"""Measurements of one blob that decide whether it can be a marker: volume, principal spreads, bone, metal.

The volume is counted at a local half-way level: each voxel's background is the minimum of
the smoothed intensity within ~1.5 mm (air, plastic or tissue, whichever the marker touches
there), so the count does not shrink against air nor swell against plastic the way a single
threshold would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..transforms import apply_transform
from .segmentation import Blob, ball
from .settings import DetectionSettings


@dataclass
class BlobMeasures:
    """Image-space measurements (LPS, mm) of a blob."""

    centroid: np.ndarray
    volume_mm3: float
    spreads_mm: np.ndarray
    marker_hu: float
    bone_fraction: float
    points: np.ndarray


def measure_blob(blob: Blob, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
                 settings: DetectionSettings) -> BlobMeasures:
    """Volume, centroid, principal spreads and the marker's own intensity of ``blob``."""
    spacing_zyx = np.asarray(spacing_zyx, dtype=float)
    near = ndimage.binary_dilation(blob.mask, structure=ball(1.5, spacing_zyx))
    core = ndimage.binary_erosion(blob.mask, structure=ball(1.0, spacing_zyx))
    marker_hu = float(np.median(blob.values[core] if core.sum() >= 20 else blob.values[blob.mask]))
    size = 2 * np.ceil(1.5 / spacing_zyx).astype(int) + 1
    background = ndimage.minimum_filter(blob.smoothed, size=tuple(size), mode="nearest")
    contrast = marker_hu - background
    flat = contrast < 200.0
    inside = near & np.where(flat, blob.smoothed >= settings.low_hu,
                             blob.smoothed - background >= 0.5 * contrast)
    if inside.any():
        labels, _ = ndimage.label(inside)
        keep = np.unique(labels[blob.mask & inside])
        inside = np.isin(labels, keep[keep > 0])
    voxel_volume = float(np.prod(spacing_zyx))
    ijk = (np.argwhere(inside) + blob.offset_zyx)[:, ::-1].astype(float)
    points = apply_transform(index_to_image, ijk) if len(ijk) else np.empty((0, 3))
    if len(points) >= 4:
        spreads = np.sqrt(np.maximum(np.sort(np.linalg.eigvalsh(np.cov(points.T))), 0))
        centroid = points.mean(axis=0)
    else:
        spreads = np.zeros(3)
        centroid = apply_transform(index_to_image, blob.centroid_index_zyx()[::-1])
    shell = ndimage.binary_dilation(blob.mask, structure=ball(1.0, spacing_zyx))
    bone = np.count_nonzero(shell & (blob.values >= settings.high_hu))
    return BlobMeasures(centroid, inside.sum() * voxel_volume, spreads, marker_hu,
                        bone / max(1, blob.voxel_count), points)


def metal_distance_mm(centroid: np.ndarray, metal_zyx: np.ndarray, index_to_image: np.ndarray,
                      blob: Blob, settings: DetectionSettings) -> float:
    """Distance (mm) from the blob's centroid to the nearest metal voxel (coarse samples and the region)."""
    candidates = [metal_zyx]
    local = np.argwhere(blob.values >= settings.metal_hu)
    if len(local):
        candidates.append(local + blob.offset_zyx)
    metal = np.concatenate(candidates) if any(len(c) for c in candidates) else np.empty((0, 3))
    if len(metal) == 0:
        return float("inf")
    points = apply_transform(index_to_image, metal[:, ::-1].astype(float))
    return float(np.min(np.linalg.norm(points - centroid, axis=1)))
