"""Coarse-to-fine candidate segmentation: band-pass threshold, smoothing, opening, connected components.

The coarse pass looks at a strided view of the volume (one voxel every ``coarse_step_mm``
along each axis, no copy of the full volume, no filter over it) and labels the in-band
samples; every coarse component of plausible size becomes a small region of interest. Only
there does the fine pass work at full resolution: Gaussian smoothing, the band threshold,
a binary opening, connected components. Arrays are in numpy order (z, y, x); index
triples ``ijk`` in SimpleITK order (x, y, z).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

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
    """One connected component inside a region, on the region's work grid.

    The work grid is the full-resolution grid, or for voxels finer than ``WORK_SPACING_MM`` its
    block average (segmentation needs no finer voxels; the pose's edge profiles still sample
    ``full_values``). ``values`` holds the work grid's raw intensities (float32), ``smoothed``
    their Gaussian-smoothed copy, ``mask`` the component. Each array set has its own
    ``*_to_image`` (4x4: local array index (i, j, k) -> LPS mm).
    """

    values: np.ndarray
    smoothed: np.ndarray
    mask: np.ndarray
    work_to_image: np.ndarray
    spacing_zyx: np.ndarray
    full_values: np.ndarray
    full_to_image: np.ndarray
    touches_image_edge: bool
    touches_region_edge: bool
    box_zyx: tuple[np.ndarray, np.ndarray] = (np.zeros(3, dtype=int), np.zeros(3, dtype=int))
    """Bounding box of the mask in full-resolution image indices (z, y, x): start, stop."""

    @property
    def voxel_count(self) -> int:
        return int(np.count_nonzero(self.mask))

    @property
    def voxel_volume_mm3(self) -> float:
        return float(np.prod(self.spacing_zyx))

    def centroid(self) -> np.ndarray:
        """Centroid of the mask's voxels (LPS mm)."""
        ijk = np.argwhere(self.mask).mean(axis=0)[::-1]
        return self.work_to_image[:3, :3] @ ijk + self.work_to_image[:3, 3]


WORK_SPACING_MM = 0.6
"""Regions with finer voxels are block-averaged to about this size for segmentation."""


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
    """In-band mask of the strided samples, and the metal samples (index zyx), slab by slab (small temporaries).

    Slabs go to two threads (numpy releases the GIL); int16 volumes are tested with a single
    unsigned comparison (``low <= v < high`` is ``uint16(v - low) < high - low``, exact with
    wrap-around since the map is a bijection of the 16-bit values).
    """
    sz, sy, sx = (int(v) for v in strides)
    sample = volume_zyx[::sz, ::sy, ::sx]  # a view: nothing is copied
    band = np.empty(sample.shape, dtype=bool)
    in_band = _band_test(sample.dtype, settings.low_hu, settings.high_hu)

    def one_slab(z0: int) -> np.ndarray | None:
        block = sample[z0:z0 + slab]
        in_band(block, band[z0:z0 + slab])
        metal = block >= settings.metal_hu
        if not metal.any():
            return None
        hits = np.argwhere(metal)
        hits[:, 0] += z0
        return hits

    with ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1))) as pool:
        metal = [hits for hits in pool.map(one_slab, range(0, sample.shape[0], slab)) if hits is not None]
    metal_zyx = (np.concatenate(metal) if metal else np.empty((0, 3), dtype=int)) * strides
    return band, metal_zyx


def _band_test(dtype: np.dtype, low: float, high: float):
    """``out[...] = (low <= block) & (block < high)``, as a function of ``(block, out)``."""
    if dtype == np.int16:
        lo = int(np.clip(np.ceil(low), -32768, 32767))
        width = int(np.clip(np.ceil(high), -32768, 32768)) - lo
        if width <= 0:
            return lambda block, out: out.fill(False)

        def unsigned(block: np.ndarray, out: np.ndarray) -> None:
            np.less(np.subtract(block, np.int16(lo), dtype=np.int16).view(np.uint16), width, out=out)

        return unsigned

    def plain(block: np.ndarray, out: np.ndarray) -> None:
        np.logical_and(block >= low, block < high, out=out)

    return plain


def ball(radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    """A boolean ball structuring element of ``radius_mm`` for voxels of ``spacing_zyx`` (at least 3x3x3 cross)."""
    half = np.maximum(1, np.floor(radius_mm / np.asarray(spacing_zyx))).astype(int)
    grids = np.meshgrid(*[np.arange(-h, h + 1) * s for h, s in zip(half, spacing_zyx, strict=True)], indexing="ij")
    r2 = sum(g**2 for g in grids)
    element = r2 <= max(radius_mm, float(np.min(spacing_zyx))) ** 2 + 1e-9
    return element


def dilate_ball(mask: np.ndarray, radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    """``ndimage.binary_dilation(mask, ball(radius_mm, spacing_zyx))``, exactly, from box maxima.

    A ball of voxel offsets contains, with every offset, all offsets of smaller absolute value,
    so it is the union of the boxes spanned by its maximal corners: the dilation is the union
    of box dilations, each a few shifted ORs per axis (several times faster than scipy's
    generic binary morphology on these small arrays).
    """
    boxes = _ball_boxes(float(radius_mm), tuple(float(v) for v in spacing_zyx))
    out = box_extreme(mask, boxes[0], np.maximum)
    for half in boxes[1:]:
        np.logical_or(out, box_extreme(mask, half, np.maximum), out=out)
    return out


def erode_ball(mask: np.ndarray, radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    """``ndimage.binary_erosion(mask, ball(radius_mm, spacing_zyx))`` exactly (outside the array is False).

    Erosion by a union of boxes is the intersection of the box erosions.
    """
    boxes = _ball_boxes(float(radius_mm), tuple(float(v) for v in spacing_zyx))
    out = box_extreme(mask, boxes[0], np.minimum, border=False)
    for half in boxes[1:]:
        np.logical_and(out, box_extreme(mask, half, np.minimum, border=False), out=out)
    return out


def open_ball(mask: np.ndarray, radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    """``ndimage.binary_opening(mask, ball(radius_mm, spacing_zyx))`` exactly."""
    return dilate_ball(erode_ball(mask, radius_mm, spacing_zyx), radius_mm, spacing_zyx)


def box_extreme(values: np.ndarray, half_zyx: tuple[int, int, int], combine: np.ufunc,
                border: bool | None = None) -> np.ndarray:
    """Running ``combine`` (``np.maximum`` or ``np.minimum``) over a box of ``2 * half + 1`` voxels per axis.

    ``border`` None ignores neighbours outside the array (as scipy's ``mode="nearest"`` does for
    a minimum or maximum); a value makes them count as that value. Returns a new array.
    """
    out = values
    for axis, half in enumerate(half_zyx):
        if half == 0:
            continue
        source, out = out, out.copy()
        for shift in range(1, half + 1):
            ahead = tuple(slice(shift, None) if a == axis else slice(None) for a in range(values.ndim))
            behind = tuple(slice(None, -shift) if a == axis else slice(None) for a in range(values.ndim))
            combine(out[ahead], source[behind], out=out[ahead])
            combine(out[behind], source[ahead], out=out[behind])
        if border is not None:
            edge = [slice(None)] * values.ndim
            for part in (slice(0, half), slice(max(0, values.shape[axis] - half), None)):
                edge[axis] = part
                out[tuple(edge)] = combine(out[tuple(edge)], border)
    return out.copy() if out is values else out


@lru_cache(maxsize=32)
def _ball_boxes(radius_mm: float, spacing_zyx: tuple[float, float, float]) -> list[tuple[int, int, int]]:
    return _maximal_corners(ball(radius_mm, np.array(spacing_zyx)))


def _maximal_corners(element: np.ndarray) -> list[tuple[int, int, int]]:
    """Half extents (z, y, x) of the boxes whose union is the symmetric, monotone ``element``."""
    centre = np.array(element.shape) // 2
    corners = {tuple(int(v) for v in c) for c in np.abs(np.argwhere(element) - centre)}
    return sorted(c for c in corners if not any(o != c and all(a >= b for a, b in zip(o, c, strict=True))
                                                for o in corners))


def work_factors(spacing_zyx: np.ndarray) -> np.ndarray:
    """Block-averaging factors (z, y, x) that bring voxels up to about ``WORK_SPACING_MM``."""
    return np.maximum(1, np.floor(WORK_SPACING_MM / np.asarray(spacing_zyx) + 1e-6)).astype(int)


def local_to_image(index_to_image: np.ndarray, offset_zyx: np.ndarray, factors_zyx: np.ndarray) -> np.ndarray:
    """4x4 mapping a (block-averaged) region's local index (i, j, k) to LPS mm."""
    factors = np.asarray(factors_zyx, dtype=float)[::-1]
    local = np.eye(4)
    local[:3, :3] = np.diag(factors)
    local[:3, 3] = np.asarray(offset_zyx, dtype=float)[::-1] + (factors - 1) / 2
    return index_to_image @ local


def block_mean(values: np.ndarray, factors_zyx: np.ndarray) -> np.ndarray:
    """Average over blocks of ``factors_zyx`` voxels (the shape must be a multiple of the factors)."""
    fz, fy, fx = (int(f) for f in factors_zyx)
    if fz == fy == fx == 1:
        return values
    nz, ny, nx = (n // f for n, f in zip(values.shape, (fz, fy, fx), strict=True))
    return values.reshape(nz, fz, ny, fy, nx, fx).mean(axis=(1, 3, 5), dtype=np.float32)


def blobs_in_region(volume_zyx: np.ndarray, region: Region, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
                    model: MarkerModel, settings: DetectionSettings) -> list[Blob]:
    """Connected components of the smoothed, band-thresholded, opened region (work grid)."""
    spacing_zyx = np.asarray(spacing_zyx, dtype=float)
    factors = work_factors(spacing_zyx)
    image_shape = np.array(volume_zyx.shape)
    start = np.array([sl.start for sl in region.slices])
    stop = np.array([sl.stop for sl in region.slices])
    stop = start + (stop - start) // factors * factors  # whole blocks only
    slices = tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True))
    full_values = np.asarray(volume_zyx[slices], dtype=np.float32)
    values = block_mean(full_values, factors)
    work_spacing = spacing_zyx * factors
    sigma = [settings.smoothing_sigma_mm / s for s in work_spacing]
    smoothed = ndimage.gaussian_filter(values, sigma, mode="nearest") if settings.smoothing_sigma_mm > 0 else values
    mask = (smoothed >= settings.low_hu) & (smoothed < settings.high_hu)
    if settings.opening_radius_mm > 0:
        mask = open_ball(mask, settings.opening_radius_mm, work_spacing)
    labels, count = ndimage.label(mask, structure=_CONNECTIVITY_26)
    if count == 0:
        return []
    work_to_image = local_to_image(index_to_image, start, factors)
    full_to_image = local_to_image(index_to_image, start, np.ones(3, dtype=int))
    voxel_volume = float(np.prod(work_spacing))
    blobs = []
    for label_value, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None or np.prod([b.stop - b.start for b in box]) * voxel_volume < 0.3 * model.volume_mm3:
            continue
        component = labels == label_value
        if np.count_nonzero(component) * voxel_volume < 0.3 * model.volume_mm3:
            continue
        lo = np.array([b.start for b in box])
        hi = np.array([b.stop for b in box])
        on_low = lo == 0
        on_high = hi == np.array(values.shape)
        at_image_low = start == 0
        at_image_high = stop + factors > image_shape
        touches_image = bool(np.any(on_low & at_image_low) or np.any(on_high & at_image_high))
        touches_region = bool(np.any(on_low & ~at_image_low) or np.any(on_high & ~at_image_high))
        blobs.append(Blob(values, smoothed, component, work_to_image, work_spacing, full_values, full_to_image,
                          touches_image, touches_region, (start + lo * factors, start + hi * factors)))
    return blobs


def region_around(blob: Blob, spacing_zyx: np.ndarray, image_shape: tuple[int, ...], margin_mm: float = 3.0) -> Region:
    """A region holding ``blob``'s bounding box with ``margin_mm`` around it (to regrow a cut blob)."""
    margin = np.ceil(margin_mm / np.asarray(spacing_zyx)).astype(int) + 1
    lo, hi = blob.box_zyx
    start = np.maximum(lo - margin, 0)
    stop = np.minimum(hi + margin, np.asarray(image_shape))
    return Region(tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True)), (lo + hi) / 2.0,
                  float("nan"))
