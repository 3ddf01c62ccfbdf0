"""Per-marker orthogonal CT slices with the fitted marker model's outline drawn on them (OpenCV).

For each marker three planes are sampled from the CT (trilinear interpolation, physical
space honoured through the image's origin, spacing and direction):

- ``XY``: the plane through the marker axis spanned by marker +X (right) and +Y (up);
- ``ZY``: the plane through the marker axis spanned by marker +Z (right) and +Y (up);
- ``XZ``: the cross-section perpendicular to the axis through the bottom cylinder.

On them: the fitted CAD outline (green when paired, orange when not), the probe sensor
point at the solved offset ``l`` (yellow dot) and the calibration point mapped into image
space by ``ReferenceToImage`` (magenta cross), both projected onto the plane. A gap between
the dot and the cross is the marker's registration residual.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..core.ct import index_to_physical_matrix
from ..core.transforms import apply_transform, invert_rigid
from ..marker_model import MarkerModel
from .colors import CALIBRATION, PAIRED, SENSOR, UNPAIRED
from .text import put_text, recorded_text, relay_text

if TYPE_CHECKING:
    import SimpleITK as sitk

_SHIFT = 4  # OpenCV sub-pixel drawing: coordinates in 1/16 pixel
_SCALE = 1 << _SHIFT
BACKGROUND = (32, 32, 36)
#: Pixels per side of one view and their size (mm) in the report's mosaic.
VIEW_PX = 140
MM_PER_PX = 0.2
TEXT = (235, 235, 235)


@dataclass
class SliceMarker:
    """One marker to show: label, ``MarkerToImage``, caption and optional points (image space, LPS mm)."""

    label: str
    marker_to_image: np.ndarray
    caption: str = ""
    paired: bool = True
    sensor_point: np.ndarray | None = None
    calibration_point: np.ndarray | None = None


class CTSampler:
    """Samples a CT at physical points (LPS mm) with trilinear interpolation."""

    def __init__(self, image: sitk.Image, array: np.ndarray | None = None) -> None:
        """``image``: the CT, or its geometry when ``array`` holds its voxels (k, j, i)."""
        import SimpleITK as sitk


        self.array = sitk.GetArrayViewFromImage(image) if array is None else array  # (k, j, i)
        self.image_to_index = np.linalg.inv(index_to_physical_matrix(image))

    def sample(self, points_image: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """Values at points (..., 3); NaN outside the volume. ``index``: the points' continuous (i, j, k)
        indices when already computed (``apply_transform(image_to_index, points)``)."""
        from scipy.ndimage import map_coordinates

        points_image = np.asarray(points_image, dtype=float)
        if index is None:
            index = apply_transform(self.image_to_index, points_image.reshape(-1, 3))
        values = map_coordinates(self.array, index[:, ::-1].T, order=1, mode="constant", cval=np.nan,
                                 output=np.float32)
        return values.reshape(points_image.shape[:-1])


def _view_planes(model: MarkerModel) -> list[tuple[str, int, int, int, float, float]]:
    """(name, horizontal axis, vertical axis, normal axis, offset along normal, vertical centre)."""
    mid_height = model.height_mm / 2.0
    return [
        ("XY", 0, 1, 2, 0.0, mid_height),
        ("ZY", 2, 1, 0, 0.0, mid_height),
        ("XZ", 0, 2, 1, model.bottom_height_mm / 2.0, 0.0),
    ]


def _profile(model: MarkerModel) -> np.ndarray:
    rb, rt, rh = model.bottom_diameter_mm / 2, model.top_diameter_mm / 2, model.pinhole_diameter_mm / 2
    hb, h, a = model.bottom_height_mm, model.height_mm, model.pinhole_bottom_mm
    return np.array([(-rb, 0), (rb, 0), (rb, hb), (rt, hb), (rt, h), (rh, h), (rh, a), (-rh, a), (-rh, h),
                     (-rt, h), (-rt, hb), (-rb, hb)], dtype=float)


def marker_view_points(marker_to_image: np.ndarray, model: MarkerModel, view_px: int, mm_per_px: float
                       ) -> np.ndarray:
    """Image-space points (3, view_px, view_px, 3; LPS mm) of a marker's three planes (XY, ZY, XZ)."""
    centre_px = (view_px - 1) / 2.0
    offsets = (np.arange(view_px) - centre_px) * mm_per_px
    planes = []
    for _, h_axis, v_axis, n_axis, n_offset, v_centre in _view_planes(model):
        horizontal, vertical = np.meshgrid(offsets, v_centre - offsets)
        points_marker = np.zeros(horizontal.shape + (3,))
        points_marker[..., h_axis] = horizontal
        points_marker[..., v_axis] = vertical
        points_marker[..., n_axis] = n_offset
        planes.append(apply_transform(marker_to_image, points_marker.reshape(-1, 3)).reshape(points_marker.shape))
    return np.stack(planes)


def sample_marker_views(
    sampler: CTSampler, marker_to_image: np.ndarray, model: MarkerModel, view_px: int, mm_per_px: float
) -> list[np.ndarray]:
    """The three planes of one marker as float arrays (view_px, view_px) of CT values."""
    return list(sampler.sample(marker_view_points(marker_to_image, model, view_px, mm_per_px)))


class StreamingMarkerViews:
    """Samples each marker's three planes as soon as the CT slices they cross have been read.

    ``sample_ready(n)`` samples every marker whose planes lie within slices ``0 .. n-1`` (numpy
    axis 0, the image's k index); ``views()`` returns them all (sampling what is left), in the
    order of ``markers``, for :func:`marker_slices_mosaic`.
    """

    def __init__(self, image: sitk.Image, markers: list[SliceMarker], model: MarkerModel, view_px: int = VIEW_PX,
                 mm_per_px: float = MM_PER_PX, array: np.ndarray | None = None) -> None:
        self.sampler = CTSampler(image, array)
        self._views: list[list[np.ndarray] | None] = [None] * len(markers)
        self._pending: list[tuple[int, int, np.ndarray, int, np.ndarray]] = []
        slices = self.sampler.array.shape[0]
        for n, marker in enumerate(markers):
            points = marker_view_points(marker.marker_to_image, model, view_px, mm_per_px)
            index = apply_transform(self.sampler.image_to_index, points.reshape(-1, 3))  # sampled with these
            k = index[:, 2]
            stop = int(np.clip(np.floor(np.max(k)) + 2, 0, slices))  # trilinear: floor(k) and floor(k) + 1
            start = int(np.clip(np.floor(np.min(k)), 0, slices))
            self._pending.append((stop, n, points, start, index))
        self._pending.sort(key=lambda item: item[0])
        self._slices = slices

    def release(self) -> None:
        """Sample what is left, then let go of the CT (the views stay)."""
        self.views()
        self.sampler.array = None

    def sample_ready(self, ready_slices: int) -> None:
        while self._pending and self._pending[0][0] <= ready_slices:
            _, n, points, _, index = self._pending.pop(0)
            self._views[n] = list(self.sampler.sample(points, index))

    def first_needed_slice(self) -> int:
        """The lowest slice a marker still to be sampled reads (the slice count when none is left)."""
        return min((item[3] for item in self._pending), default=self._slices)

    def views(self) -> list[list[np.ndarray]]:
        self.sample_ready(self._slices)
        return self._views


def _to_px(h_mm: np.ndarray, v_mm: np.ndarray, v_centre: float, view_px: int, mm_per_px: float) -> np.ndarray:
    centre_px = (view_px - 1) / 2.0
    x = centre_px + np.asarray(h_mm) / mm_per_px
    y = centre_px - (np.asarray(v_mm) - v_centre) / mm_per_px
    return np.round(np.stack([x, y], axis=-1) * _SCALE).astype(np.int32)


def draw_marker_overlay(
    view_rgb: np.ndarray, view_index: int, marker: SliceMarker, model: MarkerModel, mm_per_px: float
) -> None:
    """Draw the fitted outline, the sensor point and the calibration point on one view (in place)."""
    view_px = view_rgb.shape[0]
    name, h_axis, v_axis, n_axis, n_offset, v_centre = _view_planes(model)[view_index]
    color = PAIRED if marker.paired else UNPAIRED
    if name in ("XY", "ZY"):
        profile = _profile(model)
        polygon = _to_px(profile[:, 0], profile[:, 1], v_centre, view_px, mm_per_px)
        cv2.polylines(view_rgb, [polygon], True, color, 1, cv2.LINE_AA, _SHIFT)
    else:
        radii = [model.bottom_diameter_mm / 2] if n_offset <= model.bottom_height_mm else \
            [model.top_diameter_mm / 2] + ([model.pinhole_diameter_mm / 2] if n_offset > model.pinhole_bottom_mm
                                           else [])
        centre = _to_px(0.0, 0.0, v_centre, view_px, mm_per_px)
        for radius in radii:
            cv2.circle(view_rgb, tuple(int(c) for c in centre), int(round(radius / mm_per_px * _SCALE)), color, 1,
                       cv2.LINE_AA, _SHIFT)
    image_to_marker = invert_rigid(marker.marker_to_image)
    if marker.sensor_point is not None:
        p = apply_transform(image_to_marker, marker.sensor_point)
        centre = _to_px(p[h_axis], p[v_axis], v_centre, view_px, mm_per_px)
        cv2.circle(view_rgb, tuple(int(c) for c in centre), 3 * _SCALE, SENSOR, -1, cv2.LINE_AA, _SHIFT)
    if marker.calibration_point is not None:
        p = apply_transform(image_to_marker, marker.calibration_point)
        cx, cy = _to_px(p[h_axis], p[v_axis], v_centre, view_px, mm_per_px)
        arm = 4 * _SCALE
        cv2.line(view_rgb, (int(cx - arm), int(cy - arm)), (int(cx + arm), int(cy + arm)), CALIBRATION, 1,
                 cv2.LINE_AA, _SHIFT)
        cv2.line(view_rgb, (int(cx - arm), int(cy + arm)), (int(cx + arm), int(cy - arm)), CALIBRATION, 1,
                 cv2.LINE_AA, _SHIFT)
    put_text(view_rgb, name, 3, view_px - 4, 0.32, TEXT)


def _window(values: list[np.ndarray]) -> tuple[float, float]:
    finite = np.concatenate([v[np.isfinite(v)].ravel() for v in values]) if values else np.zeros(0)
    if finite.size == 0:
        return 0.0, 1.0
    low, high = np.percentile(finite, [1.0, 99.5])
    return float(low), float(high if high > low else low + 1.0)


def _to_grey_rgb(values: np.ndarray, window: tuple[float, float]) -> np.ndarray:
    low, high = window
    scaled = np.clip((np.nan_to_num(values, nan=low) - low) / (high - low), 0.0, 1.0)
    grey = np.round(scaled * 255.0).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def marker_slices_mosaic(
    image: sitk.Image | None, markers: list[SliceMarker], model: MarkerModel, columns: int = 3,
    view_px: int = VIEW_PX, mm_per_px: float = MM_PER_PX, window: tuple[float, float] | None = None,
    views: list[list[np.ndarray]] | None = None,
) -> np.ndarray:
    """A mosaic (RGB ``uint8``) of every marker's three views with overlays, ``columns`` markers per row.

    ``window`` is the displayed CT value range (default: 1st to 99.5th percentile of all views);
    ``views``: the planes already sampled (:class:`StreamingMarkerViews`), else sampled from ``image``.
    """
    if not markers:
        raise ValueError("marker_slices_mosaic needs at least one marker")
    if views is None:
        sampler = CTSampler(image)
        views = [sample_marker_views(sampler, m.marker_to_image, model, view_px, mm_per_px) for m in markers]
    all_views = views
    window = window or _window([v for views in all_views for v in views])
    gap, header = 4, 20
    tile_w = 3 * view_px + 2 * gap
    tile_h = header + view_px
    columns = max(1, min(columns, len(markers)))
    rows = int(np.ceil(len(markers) / columns))
    margin = 8
    mosaic = np.full((margin + rows * (tile_h + margin), margin + columns * (tile_w + margin), 3), BACKGROUND,
                     dtype=np.uint8)
    for n, (marker, views) in enumerate(zip(markers, all_views, strict=True)):
        top = margin + (n // columns) * (tile_h + margin)
        left = margin + (n % columns) * (tile_w + margin)
        caption = marker.caption or marker.label
        put_text(mosaic, caption, left + 2, top + 14, 0.42, TEXT)
        for k, values in enumerate(views):
            view_rgb = _to_grey_rgb(values, window)
            with recorded_text() as view_texts:
                draw_marker_overlay(view_rgb, k, marker, model, mm_per_px)
            x0 = left + k * (view_px + gap)
            relay_text(view_texts, x0, top + header)
            mosaic[top + header: top + header + view_px, x0: x0 + view_px] = view_rgb
    return mosaic
