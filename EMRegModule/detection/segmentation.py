"""Coarse-to-fine candidate segmentation: band-pass threshold, smoothing, opening, connected components.

The coarse pass looks at a strided view of the volume (one voxel every ``coarse_step_mm``
along each axis, no copy of the full volume, no filter over it) and labels the in-band
samples; every coarse component of plausible size becomes a small region of interest. Only
there does the fine pass work at full resolution: Gaussian smoothing, the band threshold,
a binary opening, connected components. Arrays are in numpy order (z, y, x); index
triples ``ijk`` in SimpleITK order (x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..marker_model import MarkerModel
from .settings import DetectionSettings

_CONNECTIVITY_26 = np.ones((3, 3, 3), dtype=bool)


@dataclass
class Region:
    """A full-resolution region of interest (numpy slices z, y, x) around one coarse component."""

    slices: tuple[slice, slice, slice]
    coarse_centroid_zyx: np.ndarray
    coarse_volume_mm3: float

    @property
    def offset_zyx(self) -> np.ndarray:
        return np.array([s.start for s in self.slices])


@dataclass
class CoarseResult:
    """What the coarse pass found: candidate regions, too-large blobs, metal sample positions (index zyx)."""

    regions: list[Region]
    too_large: list[tuple[np.ndarray, float, float]]
    metal_zyx: np.ndarray
    strides_zyx: np.ndarray


@dataclass
class Blob:
    """One full-resolution connected component inside a region.

    ``values`` is the region's raw intensity (float32), ``smoothed`` its Gaussian-smoothed copy,
    ``mask`` the component; ``offset_zyx`` is the image index of ``values[0, 0, 0]``.
    """

    values: np.ndarray
    smoothed: np.ndarray
    mask: np.ndarray
    offset_zyx: np.ndarray
    touches_image_edge: bool
    touches_region_edge: bool

    @property
    def voxel_count(self) -> int:
        return int(self.mask.sum())

    def centroid_index_zyx(self) -> np.ndarray:
        return np.argwhere(self.mask).mean(axis=0) + self.offset_zyx


def coarse_strides(spacing_zyx: np.ndarray, step_mm: float) -> np.ndarray:
    """Integer strides (z, y, x) giving about ``step_mm`` between coarse samples."""
    return np.maximum(1, np.floor(step_mm / np.asarray(spacing_zyx) + 0.5)).astype(int)


def coarse_pass(volume_zyx: np.ndarray, spacing_zyx: np.ndarray, model: MarkerModel,
                settings: DetectionSettings) -> CoarseResult:
    """Find candidate regions from a strided view of ``volume_zyx`` (touches ~1/stride^2 of the memory)."""
    strides = coarse_strides(spacing_zyx, settings.coarse_step_mm)
    band, metal_zyx = _coarse_band(volume_zyx, strides, settings)
    labels, count = ndimage.label(band, structure=_CONNECTIVITY_26)
    del band
    shape = np.array(volume_zyx.shape)
    sample_volume = float(np.prod(spacing_zyx * strides))
    model_volume = model.volume_mm3
    regions: list[Region] = []
    too_large: list[tuple[np.ndarray, float, float]] = []
    if count == 0:
        return CoarseResult(regions, too_large, metal_zyx, strides)
    boxes = ndimage.find_objects(labels)
    max_extent_mm = 1.5 * np.hypot(model.height_mm, model.bottom_diameter_mm)
    margin = strides + np.ceil(3.0 / np.asarray(spacing_zyx)).astype(int)
    for label_value, box in enumerate(boxes, start=1):
        if box is None or np.prod([s.stop - s.start for s in box]) * sample_volume < 0.3 * model_volume:
            continue
        members = np.argwhere(labels[box] == label_value)  # bincount would make an int64 copy of labels
        volume = len(members) * sample_volume
        if volume < 0.3 * model_volume:
            continue  # specks: noise, thin partial-volume shells of bone
        lo = np.array([s.start for s in box]) * strides
        hi = (np.array([s.stop for s in box]) - 1) * strides + 1
        extent_mm = (hi - lo) * np.asarray(spacing_zyx)
        centroid = members.mean(axis=0) * strides + lo
        if volume > 3.0 * model_volume or np.max(extent_mm) > max_extent_mm:
            too_large.append((centroid, volume, float(np.max(extent_mm))))
            continue
        start = np.maximum(lo - margin, 0)
        stop = np.minimum(hi + margin, shape)
        regions.append(Region(tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True)),
                              centroid, volume))
    return CoarseResult(regions, too_large, metal_zyx, strides)


def _coarse_band(volume_zyx: np.ndarray, strides: np.ndarray, settings: DetectionSettings,
                 slab: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """In-band mask of the strided samples, and the metal samples (index zyx), slab by slab (small temporaries)."""
    sz, sy, sx = (int(v) for v in strides)
    sample = volume_zyx[::sz, ::sy, ::sx]  # a view: nothing is copied
    band = np.empty(sample.shape, dtype=bool)
    metal = []
    for z0 in range(0, sample.shape[0], slab):
        block = sample[z0:z0 + slab]
        np.logical_and(block >= settings.low_hu, block < settings.high_hu, out=band[z0:z0 + slab])
        hits = np.argwhere(block >= settings.metal_hu)
        if len(hits):
            hits[:, 0] += z0
            metal.append(hits)
    metal_zyx = (np.concatenate(metal) if metal else np.empty((0, 3), dtype=int)) * strides
    return band, metal_zyx


def ball(radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    """A boolean ball structuring element of ``radius_mm`` for voxels of ``spacing_zyx`` (at least 3x3x3 cross)."""
    half = np.maximum(1, np.floor(radius_mm / np.asarray(spacing_zyx))).astype(int)
    grids = np.meshgrid(*[np.arange(-h, h + 1) * s for h, s in zip(half, spacing_zyx, strict=True)], indexing="ij")
    r2 = sum(g**2 for g in grids)
    element = r2 <= max(radius_mm, float(np.min(spacing_zyx))) ** 2 + 1e-9
    return element


def blobs_in_region(volume_zyx: np.ndarray, region: Region, spacing_zyx: np.ndarray, model: MarkerModel,
                    settings: DetectionSettings) -> list[Blob]:
    """Full-resolution connected components of the smoothed, band-thresholded, opened region."""
    values = np.asarray(volume_zyx[region.slices], dtype=np.float32)
    sigma = [settings.smoothing_sigma_mm / s for s in spacing_zyx]
    smoothed = ndimage.gaussian_filter(values, sigma, mode="nearest") if settings.smoothing_sigma_mm > 0 else values
    mask = (smoothed >= settings.low_hu) & (smoothed < settings.high_hu)
    if settings.opening_radius_mm > 0:
        mask = ndimage.binary_opening(mask, structure=ball(settings.opening_radius_mm, spacing_zyx))
    labels, count = ndimage.label(mask, structure=_CONNECTIVITY_26)
    if count == 0:
        return []
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    voxel_volume = float(np.prod(spacing_zyx))
    offset = region.offset_zyx
    image_shape = np.array(volume_zyx.shape)
    blobs = []
    for label_value, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None or sizes[label_value] * voxel_volume < 0.3 * model.volume_mm3:
            continue
        lo = np.array([s.start for s in box])
        hi = np.array([s.stop for s in box])
        on_low = lo == 0
        on_high = hi == np.array(values.shape)
        touches_image = bool(np.any(on_low & (offset == 0)) or np.any(on_high & (offset + hi == image_shape)))
        touches_region = bool(np.any(on_low & (offset > 0)) or np.any(on_high & (offset + hi < image_shape)))
        blobs.append(Blob(values, smoothed, labels == label_value, offset, touches_image, touches_region))
    return blobs
