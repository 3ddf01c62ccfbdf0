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
from .segmentation import Blob, box_extreme, dilate_ball, erode_ball
from .settings import DetectionSettings

_FACE_NEIGHBOURS = ndimage.generate_binary_structure(3, 1)


@dataclass
class BlobMeasures:
    """Image-space measurements (LPS, mm) of a blob."""

    centroid: np.ndarray
    volume_mm3: float
    spreads_mm: np.ndarray
    marker_hu: float
    bone_fraction: float
    points: np.ndarray
    bright_hu: float = float("nan")  # median of the voxels >= low_hu within 1.5 mm, those above the band included


def measure_blob(blob: Blob, settings: DetectionSettings) -> BlobMeasures:
    """Volume, centroid, principal spreads and the marker's own intensity of ``blob``.

    Works in the blob's bounding box grown by 2 mm (all it needs), not the whole region.
    """
    spacing_zyx = blob.spacing_zyx
    crop = _grown_box(blob.mask, np.ceil(2.0 / spacing_zyx).astype(int))
    mask, values, smoothed = blob.mask[crop], blob.values[crop], blob.smoothed[crop]
    # every voxel within 1.5 mm, and every face neighbour: with slices thicker than 1.5 mm the
    # partial-volume voxels of the outermost slices are candidates too
    near = dilate_ball(mask, 1.5, spacing_zyx) | ndimage.binary_dilation(mask, _FACE_NEIGHBOURS)
    core = erode_ball(mask, 1.0, spacing_zyx)
    marker_hu = float(np.median(values[core] if np.count_nonzero(core) >= 20 else values[mask]))
    half = tuple(int(h) for h in np.ceil(1.5 / spacing_zyx))
    background = box_extreme(smoothed, half, np.minimum)  # ndimage.minimum_filter, mode "nearest"
    contrast = marker_hu - background
    flat = contrast < 200.0
    inside = near & np.where(flat, smoothed >= settings.low_hu, smoothed - background >= 0.5 * contrast)
    if inside.any():
        labels, _ = ndimage.label(inside)
        keep = np.unique(labels[mask & inside])
        inside = np.isin(labels, keep[keep > 0])
    offset = np.array([c.start for c in crop], dtype=float)
    ijk = (np.argwhere(inside) + offset)[:, ::-1]
    points = apply_transform(blob.work_to_image, ijk) if len(ijk) else np.empty((0, 3))
    if len(points) >= 4:
        axes = blob.work_to_image[:3, :3]  # columns: one voxel step along i, j, k (mm)
        voxel_moment = axes @ axes.T / 12.0  # each voxel's own second moment: a union of boxes, not of points
        spreads = np.sqrt(np.maximum(np.sort(np.linalg.eigvalsh(np.cov(points.T) + voxel_moment)), 0))
        centroid = points.mean(axis=0)
    else:
        spreads = np.zeros(3)
        centroid = blob.centroid()
    bright = near & (values >= settings.high_hu)
    bone = np.count_nonzero(bright)
    bright_hu = float(np.median(values[near & (values >= settings.low_hu)])) if bone else marker_hu
    return BlobMeasures(centroid, np.count_nonzero(inside) * blob.voxel_volume_mm3, spreads, marker_hu,
                        bone / max(1, blob.voxel_count), points, bright_hu)


def _grown_box(mask: np.ndarray, margin: np.ndarray) -> tuple[slice, slice, slice]:
    """The bounding box of ``mask`` grown by ``margin`` voxels per axis, clipped to the array."""
    box = ndimage.find_objects(mask.astype(np.uint8))[0]
    return tuple(slice(max(0, b.start - int(m)), min(n, b.stop + int(m)))
                 for b, m, n in zip(box, margin, mask.shape, strict=True))


def metal_distance_mm(centroid: np.ndarray, metal_zyx: np.ndarray, index_to_image: np.ndarray,
                      blob: Blob, settings: DetectionSettings) -> float:
    """Distance (mm) from the blob's centroid to the nearest metal voxel (coarse samples and the region)."""
    points = [apply_transform(index_to_image, metal_zyx[:, ::-1].astype(float))] if len(metal_zyx) else []
    local = np.argwhere(blob.full_values >= settings.metal_hu)
    if len(local):
        points.append(apply_transform(blob.full_to_image, local[:, ::-1].astype(float)))
    if not points:
        return float("inf")
    return float(np.min(np.linalg.norm(np.concatenate(points) - centroid, axis=1)))
