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

from ...marker_model import MarkerModel
from .components import CONNECTIVITY_26, Component, GrowingComponents
from .settings import DetectionSettings


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
class TooLarge:
    """A coarse component too large for a marker: centroid (index zyx), volume (mm3), longest extent (mm)."""

    centroid_zyx: np.ndarray
    volume_mm3: float
    extent_mm: float


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


class CoarseScan:
    """The coarse candidate search, fed with the slices (numpy axis 0) as they are read.

    ``advance(slices)`` samples the coarse rows that the first ``slices`` slices hold, labels
    their in-band samples (:class:`~.components.GrowingComponents`: each row once, joined to the
    components of the rows before) and returns the components that are now complete (they do
    not reach the newest row): each becomes a full-resolution :class:`Region` or, when too large
    for a marker, a :class:`TooLarge`. Every component is returned exactly once, and the same
    whether the volume arrives at once or in many steps.
    """

    def __init__(self, volume_zyx: np.ndarray, spacing_zyx: np.ndarray, model: MarkerModel,
                 settings: DetectionSettings) -> None:
        self.spacing_zyx = np.asarray(spacing_zyx, dtype=float)
        self.strides = coarse_strides(self.spacing_zyx, settings.coarse_step_mm)
        self.shape = np.array(volume_zyx.shape)
        self._volume = volume_zyx  # sampled slab by slab (_sample_rows): a view of numpy voxels, nothing copied
        sample_shape = tuple(-(-int(n) // int(s)) for n, s in zip(volume_zyx.shape, self.strides, strict=True))
        self._band = np.zeros(sample_shape, dtype=bool)
        self._in_band = _band_test(volume_zyx.dtype, settings.low_hu, settings.high_hu)
        self._metal_hu = settings.metal_hu
        self._metal: list[np.ndarray] = []
        self._rows = 0  # coarse rows sampled so far
        self._components = GrowingComponents()
        self._sample_volume = float(np.prod(self.spacing_zyx * self.strides))
        self._model_volume = model.volume_mm3
        # components of fewer samples are specks that _component drops (its exact test, one sample of margin)
        self._min_count = max(0, int(np.floor(0.3 * self._model_volume / self._sample_volume)) - 1)
        self._max_extent_mm = 1.5 * float(np.hypot(model.height_mm, model.bottom_diameter_mm))
        self._margin = self.strides + np.ceil(3.0 / self.spacing_zyx).astype(int)

    @property
    def metal_zyx(self) -> np.ndarray:
        """Metal samples (full-resolution index zyx) in the rows sampled so far."""
        hits = np.concatenate(self._metal) if self._metal else np.empty((0, 3), dtype=int)
        return hits * self.strides

    def advance(self, slices: int) -> tuple[list[Region], list[TooLarge]]:
        """Components completed by the first ``slices`` slices (all of them once ``slices`` is the last)."""
        total_rows = self._band.shape[0]
        rows = min(total_rows, -(-int(slices) // int(self.strides[0])))
        if rows <= self._rows:
            return [], []
        self._sample_rows(self._rows, rows)
        block, self._rows = self._band[self._rows:rows], rows
        regions: list[Region] = []
        too_large: list[TooLarge] = []
        for component in self._components.add(block, last=rows == total_rows, min_count=self._min_count):
            outcome = self._component(component)
            if isinstance(outcome, Region):
                regions.append(outcome)
            elif outcome is not None:
                too_large.append(outcome)
        return regions, too_large

    def _component(self, component: Component) -> Region | TooLarge | None:
        if np.prod(component.stop_zyx - component.start_zyx) * self._sample_volume < 0.3 * self._model_volume:
            return None
        volume = component.count * self._sample_volume
        if volume < 0.3 * self._model_volume:
            return None  # specks: noise, thin partial-volume shells of bone
        lo = component.start_zyx * self.strides
        hi = (component.stop_zyx - 1) * self.strides + 1
        extent_mm = (hi - lo) * self.spacing_zyx
        centroid = component.mean_zyx * self.strides
        if volume > 3.0 * self._model_volume or np.max(extent_mm) > self._max_extent_mm:
            return TooLarge(centroid, volume, float(np.max(extent_mm)))
        start = np.maximum(lo - self._margin, 0)
        stop = np.minimum(hi + self._margin, self.shape)
        return Region(tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True)), centroid, volume)

    def _sample_rows(self, start: int, stop: int, slab: int = 8) -> None:
        """Band test and metal samples of coarse rows ``start .. stop-1``, slab by slab on two threads.

        int16 volumes are tested with a single unsigned comparison (``low <= v < high`` is
        ``uint16(v - low) < high - low``, exact with wrap-around: the map is a bijection of the
        16-bit values). Slabs keep the temporaries small; numpy releases the GIL.
        """

        sz, sy, sx = (int(v) for v in self.strides)

        def one_slab(z0: int) -> np.ndarray | None:
            z1 = min(z0 + slab, stop)
            block = self._volume[z0 * sz:z1 * sz:sz, ::sy, ::sx]
            self._in_band(block, self._band[z0:z1])
            metal = block >= self._metal_hu
            if not metal.any():
                return None
            hits = np.argwhere(metal)
            hits[:, 0] += z0
            return hits

        with ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1))) as pool:
            self._metal.extend(hits for hits in pool.map(one_slab, range(start, stop, slab)) if hits is not None)


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


@dataclass
class _Segmented:
    """A region's work-grid arrays and its labelled band mask (see :func:`blobs_in_region`)."""

    values: np.ndarray
    smoothed: np.ndarray
    labels: np.ndarray
    count: int
    start: np.ndarray
    stop: np.ndarray
    factors: np.ndarray
    work_spacing: np.ndarray
    full_values: np.ndarray
    work_to_image: np.ndarray
    full_to_image: np.ndarray
    image_shape: np.ndarray

    def blob(self, component: np.ndarray) -> Blob:
        """The blob of a boolean mask on this region's work grid (edge flags and box from its extent)."""
        box = ndimage.find_objects(component.astype(np.uint8))[0]
        lo = np.array([b.start for b in box])
        hi = np.array([b.stop for b in box])
        on_low = lo == 0
        on_high = hi == np.array(self.values.shape)
        at_image_low = self.start == 0
        at_image_high = self.stop + self.factors > self.image_shape
        touches_image = bool(np.any(on_low & at_image_low) or np.any(on_high & at_image_high))
        touches_region = bool(np.any(on_low & ~at_image_low) or np.any(on_high & ~at_image_high))
        return Blob(self.values, self.smoothed, component, self.work_to_image, self.work_spacing, self.full_values,
                    self.full_to_image, touches_image, touches_region,
                    (self.start + lo * self.factors, self.start + hi * self.factors))


def _segment(volume_zyx: np.ndarray, region: Region, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
             settings: DetectionSettings) -> _Segmented:
    """Smooth, band-threshold, open and label one region (work grid)."""
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
    labels, count = ndimage.label(mask, structure=CONNECTIVITY_26)
    return _Segmented(values, smoothed, labels, count, start, stop, factors, work_spacing, full_values,
                      local_to_image(index_to_image, start, factors),
                      local_to_image(index_to_image, start, np.ones(3, dtype=int)), image_shape)


def blobs_in_region(volume_zyx: np.ndarray, region: Region, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
                    model: MarkerModel, settings: DetectionSettings) -> list[Blob]:
    """Connected components of the smoothed, band-thresholded, opened region (work grid)."""
    segmented = _segment(volume_zyx, region, index_to_image, spacing_zyx, settings)
    if segmented.count == 0:
        return []
    voxel_volume = float(np.prod(segmented.work_spacing))
    blobs = []
    for label_value, box in enumerate(ndimage.find_objects(segmented.labels), start=1):
        if box is None or np.prod([b.stop - b.start for b in box]) * voxel_volume < 0.3 * model.volume_mm3:
            continue
        component = segmented.labels == label_value
        if np.count_nonzero(component) * voxel_volume < 0.3 * model.volume_mm3:
            continue
        blobs.append(segmented.blob(component))
    return blobs


def with_fragments(volume_zyx: np.ndarray, blob: Blob, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
                   model: MarkerModel, settings: DetectionSettings, gap_mm: float = 3.0) -> Blob | None:
    """``blob`` joined with the smaller fragments lying within ``gap_mm`` of it and within a marker's extent.

    A dark streak crossing a marker splits its thresholded blob (a disc and a pin, or other
    pieces); their union is the marker again, for the CAD fit to judge like any candidate. A
    fragment joins when it comes within ``gap_mm`` of the blob, is smaller than half a marker,
    and the union is no longer than a marker's diagonal (plus two voxels). None when no fragment
    joins.
    """
    spacing_zyx = np.asarray(spacing_zyx, dtype=float)
    region = region_around(blob, spacing_zyx, volume_zyx.shape, margin_mm=model.height_mm)
    segmented = _segment(volume_zyx, region, index_to_image, spacing_zyx, settings)
    if segmented.count < 2:
        return None
    lo = (blob.box_zyx[0] - segmented.start) // segmented.factors
    hi = -(-(blob.box_zyx[1] - segmented.start) // segmented.factors)
    inside = segmented.labels[tuple(slice(max(0, int(a)), int(b)) for a, b in zip(lo, hi, strict=True))]
    counts = np.bincount(inside.ravel(), minlength=segmented.count + 1)
    counts[0] = 0
    main = int(np.argmax(counts))
    if main == 0:
        return None
    voxel_volume = float(np.prod(segmented.work_spacing))
    sizes = np.bincount(segmented.labels.ravel(), minlength=segmented.count + 1)
    small = sizes * voxel_volume <= 0.5 * model.volume_mm3
    small[[0, main]] = False
    if not small.any():
        return None  # nothing that could be a piece of this marker
    union = segmented.labels == main
    box = _box_around(union, np.array(ball(gap_mm, segmented.work_spacing).shape) // 2)  # all the ball can reach
    near = dilate_ball(union[box], gap_mm, segmented.work_spacing)
    longest = float(np.hypot(model.height_mm, model.bottom_diameter_mm)) + 2 * float(np.max(segmented.work_spacing))
    joined = False
    for label_value in np.unique(segmented.labels[box][near]):
        if not small[label_value]:
            continue
        candidate = union | (segmented.labels == label_value)
        if _diameter_mm(candidate, segmented.work_to_image) > longest:
            continue
        union, joined = candidate, True
    return segmented.blob(union) if joined else None


def _box_around(mask: np.ndarray, margin: np.ndarray) -> tuple[slice, ...]:
    """The bounding box of ``mask``'s voxels grown by ``margin`` voxels (z, y, x), within the array."""
    occupied = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis))) for axis in range(3)]
    return tuple(slice(max(0, int(o[0] - m)), int(o[-1] + m + 1)) for o, m in zip(occupied, margin, strict=True))


def _diameter_mm(mask: np.ndarray, local_to_image: np.ndarray) -> float:
    """The mask's longest extent (mm), by two farthest-point sweeps (exact for convex, near for others)."""
    points = np.argwhere(mask)[:, ::-1] @ local_to_image[:3, :3].T
    far = points[np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1))]
    other = points[np.argmax(np.linalg.norm(points - far, axis=1))]
    return float(np.max(np.linalg.norm(points - other, axis=1)))


def region_around(blob: Blob, spacing_zyx: np.ndarray, image_shape: tuple[int, ...], margin_mm: float = 3.0) -> Region:
    """A region holding ``blob``'s bounding box with ``margin_mm`` around it (to regrow a cut blob)."""
    margin = np.ceil(margin_mm / np.asarray(spacing_zyx)).astype(int) + 1
    lo, hi = blob.box_zyx
    start = np.maximum(lo - margin, 0)
    stop = np.minimum(hi + margin, np.asarray(image_shape))
    return Region(tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True)), (lo + hi) / 2.0,
                  float("nan"))
