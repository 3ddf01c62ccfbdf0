"""The CT as context for the 3D view: a binned copy small enough to contour, and its cleaned iso-surface.

:func:`binned_ct` averages the CT over ``f x f x f`` blocks (``f`` chosen so that at most
``max_voxels`` remain, like ITK's ``BinShrinkImageFilter``: the last incomplete block of each
axis is dropped) without ever making a full-size copy: it accumulates whole slices into one
int32 plane, and it can follow a CT that is still being read (:class:`~EMRegModule.io.ct_handle.CTHandle`),
block of slices by block of slices, so that the binning costs no time of its own. Its memory is
the binned volume plus one slice.

:func:`context_surface` contours the binned volume and keeps what a reviewer wants to see,
the frame and the patient, without the artefacts of the metal in the reference sensor:

1. the iso-value is Otsu's threshold of the binned volume's histogram between its 0.5th and
   99.5th percentiles (air against everything else; the metal's extreme values cannot move it),
   with values below air (-1024 HU) counted as air: scanners write -2000 or -3024 outside their
   field of view (DICOM's Pixel Padding Value), and that would otherwise be "air" against the rest;
2. thin pieces are opened away: a morphological opening with a 3 x 3 x 3 cube removes every
   structure less than three binned voxels thick, which is what a streak through the metal
   becomes (a sheet in the scanner's axial planes), and keeps boxes, edges and corners whole;
3. of what remains, connected pieces smaller than ``min_piece_fraction`` of the largest are dropped;
4. the surface is contoured on the original binned values of the kept pieces and of the air
   around them (everything else is set to air), so it lies where the plain iso-surface lies
   wherever it is kept.

Frames: the binned volume is in index space of its own grid; ``index_to_image`` (4x4) maps
it to image space (CT LPS, mm), honouring the CT's origin, spacing and direction.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..core.ct import index_to_physical_matrix
from ..core.transforms import apply_transform
from ..io.ct_handle import CTHandle

if TYPE_CHECKING:
    import SimpleITK as sitk

#: CT values below this (HU) are counted as air by :func:`otsu_threshold` (padding outside the field of view).
AIR_HU = -1024.0
#: Largest number of binned voxels (the CT is averaged over blocks down to at most this).
MAX_CONTEXT_VOXELS = 3_000_000
#: Connected pieces smaller than this fraction of the largest kept piece are left out of the surface.
MIN_PIECE_FRACTION = 0.01
#: Thin voxels removed are named in the caption when they are more than this share of those above the iso-value
#: (a rounded surface loses a few voxels to the opening without any streak).
THIN_REPORTED_FRACTION = 0.002


@dataclass
class BinnedCT:
    """A block-averaged CT: ``values`` (k, j, i) float32, ``index_to_image`` (4x4, LPS mm), block size ``factor``."""

    values: np.ndarray
    index_to_image: np.ndarray
    factor: int


@dataclass
class ContextSurface:
    """The CT surface shown in the 3D view and what was left out of it.

    ``surface``: ``pyvista.PolyData`` in image space (LPS mm); ``iso_value``: the CT value
    contoured; ``pieces``: connected pieces shown; ``dropped_thin_voxels``: binned voxels above
    the iso-value removed as thin sheets (streaks); ``dropped_pieces``: small disconnected pieces
    left out; ``voxel_mm``: the binned voxel size (mm, largest axis).
    """

    surface: object
    iso_value: float
    pieces: int = 0
    dropped_thin_voxels: int = 0
    dropped_pieces: int = 0
    voxel_mm: float = 0.0
    inside_voxels: int = 0
    otsu: bool = True  # iso_value is Otsu's threshold (else the ``[report] iso_value`` setting)

    def description(self) -> str:
        """One sentence for the report's caption: what the grey surface shows."""
        removed = []
        if self.dropped_thin_voxels > THIN_REPORTED_FRACTION * max(self.inside_voxels, 1):
            removed.append("thin sheets (metal streaks)")
        if self.dropped_pieces:
            removed.append(f"{self.dropped_pieces} small disconnected piece(s)")
        chosen = ("Otsu's threshold between air and the frame and patient" if self.otsu
                  else "the [report] iso_value setting")
        text = (f"The grey surface is the CT at {self.iso_value:.0f} ({chosen}), on {self.voxel_mm:.1f} mm voxels, "
                f"{self.pieces} connected piece(s)")
        return text + ("; left out: " + " and ".join(removed) + "." if removed else ".")


def bin_factor(size: tuple[int, ...], max_voxels: int = MAX_CONTEXT_VOXELS) -> int:
    """The block size ``f``: the cube root of the volume over ``max_voxels``, rounded up."""
    return max(1, int(np.ceil((float(np.prod(size)) / max_voxels) ** (1.0 / 3.0))))


def binned_ct(source: sitk.Image | CTHandle, max_voxels: int = MAX_CONTEXT_VOXELS,
              on_slices: Callable[[int], None] | None = None) -> BinnedCT:
    """Average a CT over ``f x f x f`` blocks (see module docstring); a CT still being read is followed.

    ``source``: a ``SimpleITK.Image`` or a :class:`~EMRegModule.io.ct_handle.CTHandle` (waited on slice block by
    slice block; its read errors propagate; slices ``on_slices`` may release once binned). No full-size copy is
    made. ``on_slices(n)`` is called whenever slices ``0 .. n-1`` are known to be read (other work on them can
    follow the read too).
    """
    handle = source if isinstance(source, CTHandle) else CTHandle.of_image(source)
    fill = None if handle.is_complete else handle
    image = handle.geometry
    array = handle.array  # (k, j, i); voxels may still be arriving
    factor = bin_factor(image.GetSize(), max_voxels)
    nk, nj, ni = (s // factor for s in array.shape)
    values = np.empty((nk, nj, ni), dtype=np.float32)

    def bin_blocks(blocks: range) -> None:
        integer = np.issubdtype(array.dtype, np.integer) and array.dtype.itemsize <= 2
        accumulator = np.empty((nj * factor, ni * factor), dtype=np.int32 if integer else np.float64)
        columns = np.empty((nj * factor, ni), dtype=accumulator.dtype)
        for k in blocks:
            if fill is not None:
                fill.wait_for_slices((k + 1) * factor)
                if on_slices is not None:
                    on_slices((k + 1) * factor)
            _bin_block(array[k * factor:(k + 1) * factor, :nj * factor, :ni * factor], factor, accumulator,
                       columns, values[k])

    if fill is None and nk > 1:  # all voxels there: two threads (numpy lets go of the GIL)
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(bin_blocks, (range(0, nk // 2), range(nk // 2, nk))))
    else:
        bin_blocks(range(nk))
    if fill is not None:
        fill.result()  # a read that failed after the last binned slice must not go unnoticed
    if on_slices is not None:
        on_slices(array.shape[0])
    index_to_image = index_to_physical_matrix(image) @ np.diag([factor, factor, factor, 1.0])
    index_to_image[:3, 3] += index_to_physical_matrix(image)[:3, :3] @ np.full(3, (factor - 1) / 2.0)
    return BinnedCT(values, index_to_image, factor)


def _bin_block(block: np.ndarray, factor: int, accumulator: np.ndarray, columns: np.ndarray, out: np.ndarray) -> None:
    """Mean of ``block`` (factor, J, I) over factor^3 blocks into ``out`` (J/f, I/f), summing contiguous planes."""
    np.copyto(accumulator, block[0])
    for plane in block[1:]:
        accumulator += plane
    by_column = accumulator.reshape(accumulator.shape[0], -1, factor)
    np.copyto(columns, by_column[:, :, 0])
    for i in range(1, factor):
        columns += by_column[:, :, i]
    by_row = columns.reshape(-1, factor, columns.shape[1])
    total = by_row[:, 0, :].astype(np.float64)
    for j in range(1, factor):
        total += by_row[:, j, :]
    out[...] = total / factor**3


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of CT values (HU) between their 0.5th and 99.5th percentiles (metal cannot pull it), values
    below :data:`AIR_HU` counted as air (the padding outside the scanner's field of view cannot either)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0
    low, high = np.percentile(finite, [0.5, 99.5])
    low = max(float(low), AIR_HU) if high > AIR_HU else float(low)
    if high <= low:
        return float(low)
    counts, edges = np.histogram(np.clip(finite, low, high), bins=bins, range=(low, high))
    centres = (edges[:-1] + edges[1:]) / 2.0
    weight_low = np.cumsum(counts)
    weight_high = weight_low[-1] - weight_low
    sum_low = np.cumsum(counts * centres)
    mean_low = sum_low / np.maximum(weight_low, 1)
    mean_high = (sum_low[-1] - sum_low) / np.maximum(weight_high, 1)
    between = (weight_low * weight_high * (mean_low - mean_high) ** 2)[:-1]
    best = np.flatnonzero(between >= between.max() * (1.0 - 1e-9))  # an empty gap: the middle of it
    return float((edges[best[0] + 1] + edges[best[-1] + 1]) / 2.0)


def context_surface(binned: BinnedCT, iso_value: float | None = None, clean: bool = True,
                    min_piece_fraction: float = MIN_PIECE_FRACTION) -> ContextSurface:
    """The iso-surface of a binned CT in image space, without thin and small artefact pieces (module docstring)."""
    import pyvista as pv
    from scipy.ndimage import binary_dilation, binary_opening, label  # not for a surface kept (report.ct_memo)

    values = binned.values
    otsu = iso_value is None
    if iso_value is None:
        iso_value = otsu_threshold(values)
    result = ContextSurface(None, float(iso_value), voxel_mm=float(np.max(np.linalg.norm(
        binned.index_to_image[:3, :3], axis=0))), otsu=otsu)
    if clean and values.size:
        inside = values > iso_value
        opened = binary_opening(inside, structure=np.ones((3, 3, 3), dtype=bool))
        labels, count = label(opened)
        sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
        keep = sizes >= min_piece_fraction * sizes.max() if count else np.zeros(0, dtype=bool)
        kept = np.concatenate([[False], keep])[labels]
        result.pieces, result.dropped_pieces = int(np.count_nonzero(keep)), int(count - np.count_nonzero(keep))
        result.dropped_thin_voxels = int(np.count_nonzero(inside) - np.count_nonzero(opened))
        result.inside_voxels = int(np.count_nonzero(inside))
        # original values on the kept pieces and the air around them; everything else is air
        shown = kept | (binary_dilation(kept, structure=np.ones((3, 3, 3), dtype=bool)) & ~inside)
        floor = np.float32(min(float(values.min()), iso_value - 1.0))
        values = np.where(shown, values, floor)
    elif values.size:
        result.pieces = int(label(values > iso_value)[1])
    grid = pv.ImageData(dimensions=values.shape[::-1])
    grid.point_data["ct"] = np.ascontiguousarray(values, dtype=np.float32).ravel()
    surface = grid.contour([iso_value], scalars="ct", method="flying_edges")
    if surface.n_points:
        surface.points = apply_transform(binned.index_to_image, np.asarray(surface.points, dtype=float))
    result.surface = surface
    return result
