"""Marker pose in image space: PCA/skew-axis start, flying-edges reconstruction with VTK ICP,
sub-voxel edge points, point-to-plane steps, final VTK ICP.

Frames: ``Marker`` is the CAD frame (origin bottom-face centre, +Y toward the narrow top),
``Image`` the CT's LPS physical space (mm). Poses are ``marker_to_image`` (4x4).

Steps, for one segmented blob:

1. Start: centroid of the blob's voxels and, from their principal axes, the direction of their
   largest skewness (the marker is wide at the bottom and narrow at the top), which points +Y
   toward the narrow top. The second moments alone cannot give the axis: the marker's principal
   spreads differ by only 8 %, so thick slices or partial volume can swap them.
2. Reconstruction: the blob's iso-surface by ``vtkFlyingEdges3D`` (150 of its points), aligned
   to the CAD surface by a short ``vtkIterativeClosestPointTransform`` (at most 5 iterations,
   0.05 mm criterion). Its iso-level is biased where PVC meets plastic, so this
   only brings the start within a few tenths of a millimetre.
3. Sub-voxel fit: a single iso-level is biased where the marker meets plastic on one side and
   air on the other, so edge points are found per surface point instead: the intensity profile
   along the CAD normal is sampled (trilinear) and the edge is where it crosses half-way between
   its own inner (PVC) and outer (local background) plateaus, which is the true edge of a blurred
   step whatever the background. Since each edge point belongs to a known CAD point and
   normal, a point-to-plane Gauss-Newton step moves the model onto them (the first with every
   edge, later ones with outliers trimmed); profiles are sampled again at the new pose until
   the step is below 0.02 mm (three or four steps: the method converges quadratically; every
   third profile while the steps exceed 0.3 mm, and the edges found before a step under
   0.02 mm are kept rather than sampled again).
4. Final refinement: ``vtkIterativeClosestPointTransform`` of the edge points (outliers
   trimmed) onto the CAD surface, from that close start with a 1e-4 mm convergence criterion;
   the fit RMS is the distance of the edge points to the fitted surface.

The work per marker is small and bounded: a few thousand profile samples per step, a short ICP
of a few hundred reconstruction points, one ICP of ~800 edge points that starts converged
(timings: ``scripts/bench_detect.py``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache, partial

import numpy as np
from scipy import ndimage
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkIterativeClosestPointTransform, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

from ...marker_model import MarkerModel
from ..transforms import apply_rotation, apply_transform, axis_angle_to_rotation, invert_rigid, make_transform


@dataclass(frozen=True)
class EdgeSamples:
    """Points on the CAD surface away from corners, their outward normals and inner profile length (marker frame)."""

    points: np.ndarray
    normals: np.ndarray
    inner_mm: np.ndarray


@dataclass
class PoseFit:
    """A fitted marker pose and its quality (distances of edge points to the CAD surface, mm)."""

    marker_to_image: np.ndarray
    fit_rms_mm: float
    inlier_fraction: float
    edge_points: int

    @property
    def origin(self) -> np.ndarray:
        return self.marker_to_image[:3, 3].copy()

    @property
    def axis(self) -> np.ndarray:
        return self.marker_to_image[:3, 1].copy()


# --- the model side -------------------------------------------------------------------------


@lru_cache(maxsize=8)
def edge_samples(model: MarkerModel, spacing_mm: float = 1.0, corner_margin_mm: float = 1.0) -> EdgeSamples:
    """Surface points of the marker for edge search, at least ``corner_margin_mm`` from every rim.

    Near rims the blurred edges of two faces mix, and profiles along one face's normal would
    cross the other face; the pinhole opening is left out for the same reason.
    """
    r_b, r_t, r_h = model.bottom_diameter_mm / 2, model.top_diameter_mm / 2, model.pinhole_diameter_mm / 2
    h_b, h = model.bottom_height_mm, model.height_mm
    m = corner_margin_mm
    parts: list[tuple[np.ndarray, np.ndarray, float]] = []

    def disc(r0: float, r1: float, y: float, normal_y: float, inner: float) -> None:
        if r1 <= r0:
            return
        rings = np.arange(r0 + spacing_mm / 2 if r0 > 0 else 0.0, r1 + 1e-9, spacing_mm)
        pts = []
        for radius in rings:
            n = max(1, int(np.ceil(2 * np.pi * radius / spacing_mm)))
            a = np.linspace(0, 2 * np.pi, n, endpoint=False)
            pts.append(np.column_stack([radius * np.cos(a), np.full(n, y), radius * np.sin(a)]))
        p = np.concatenate(pts)
        parts.append((p, np.tile([0.0, normal_y, 0.0], (len(p), 1)), inner))

    def side(radius: float, y0: float, y1: float, inner: float) -> None:
        if y1 <= y0:
            return
        n = max(6, int(np.ceil(2 * np.pi * radius / spacing_mm)))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        ys = np.arange(y0, y1 + 1e-9, spacing_mm)
        aa, yy = np.meshgrid(a, ys)
        p = np.column_stack([radius * np.cos(aa).ravel(), yy.ravel(), radius * np.sin(aa).ravel()])
        nrm = np.column_stack([np.cos(aa).ravel(), np.zeros(aa.size), np.sin(aa).ravel()])
        parts.append((p, nrm, inner))

    disc(0.0, r_b - m, 0.0, -1.0, min(2.0, h_b - 1.0))
    side(r_b, m, h_b - m, min(2.0, r_b - r_t - 0.5))
    disc(r_t + 1.5 * m, r_b - m, h_b, 1.0, min(2.0, h_b - 1.0))
    side(r_t, h_b + m, h - m, min(2.0, r_t - r_h - 0.8))
    disc(r_h + m, r_t - m, h, 1.0, 2.0)
    points = np.concatenate([p for p, _, _ in parts])
    normals = np.concatenate([n for _, n, _ in parts])
    inner = np.concatenate([np.full(len(p), i) for p, _, i in parts])
    return EdgeSamples(points, normals, inner)


@lru_cache(maxsize=8)
def sparse_edge_samples(model: MarkerModel, every: int = 3) -> EdgeSamples:
    """Every ``every``-th point of :func:`edge_samples` (for the first, large pose steps)."""
    full = edge_samples(model)
    return EdgeSamples(full.points[::every], full.normals[::every], full.inner_mm[::every])


_PER_THREAD = threading.local()


def cad_surface(model: MarkerModel) -> vtkPolyData:
    """The CAD surface (marker frame) used as the ICP target; cached per model and per thread.

    VTK builds a polydata's cell links and bounds lazily on first use, so threads that pose
    markers at the same time each get their own copy.
    """
    cache = getattr(_PER_THREAD, "surfaces", None)
    if cache is None:
        cache = _PER_THREAD.surfaces = {}
    if model not in cache:
        cache[model] = model.surface_polydata(resolution=96)
    return cache[model]


def model_moments(model: MarkerModel) -> tuple[np.ndarray, float]:
    """Principal spreads (sqrt of the principal second moments, ascending, mm) and the centroid's y.

    Exact for the solid: bottom cylinder + top cylinder - pinhole, each a cylinder about +Y.
    """
    parts = [(model.bottom_diameter_mm / 2, 0.0, model.bottom_height_mm, 1.0),
             (model.top_diameter_mm / 2, model.bottom_height_mm, model.height_mm, 1.0),
             (model.pinhole_diameter_mm / 2, model.pinhole_bottom_mm, model.height_mm, -1.0)]
    volume = first = second_y = second_x = 0.0
    for radius, y0, y1, sign in parts:
        area = sign * np.pi * radius**2
        volume += area * (y1 - y0)
        first += area * (y1**2 - y0**2) / 2
        second_y += area * (y1**3 - y0**3) / 3
        second_x += area * (y1 - y0) * radius**2 / 4
    centroid_y = first / volume
    variances = [second_x / volume, second_x / volume, second_y / volume - centroid_y**2]
    return np.sqrt(np.sort(variances)), float(centroid_y)


# --- the image side -----------------------------------------------------------------------


def principal_start(points_image: np.ndarray, model: MarkerModel) -> np.ndarray:
    """Initial ``marker_to_image`` from the centroid and the skew axis of blob points (image, mm).

    The symmetry axis is the direction of largest skewness (third moment) of the points: the
    marker is wide at the bottom and narrow at the top, so its skewness along +Y is large
    (about 1.1) and zero across. The principal axes of the second moments cannot be trusted
    for it: the marker's principal spreads differ by only 8% (3.75/3.75/4.07 mm for the
    default design), so slice thickness or partial volume can swap them.
    """
    centroid = points_image.mean(axis=0)
    return start_along(centroid, skew_axis(points_image - centroid), model)


def other_starts(points_image: np.ndarray, model: MarkerModel, tried_axis: np.ndarray) -> list[np.ndarray]:
    """Starts along the reversed ``tried_axis``, then the blob's principal axes both ways (those not near it).

    For blobs whose narrow top the scan has blurred (voxels of a large fraction of the top's
    diameter), where the skew axis can point across or backwards.
    """
    centroid = points_image.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points_image - centroid).T))
    axes = [sign * vectors[:, k] for k in range(3) for sign in (1.0, -1.0)]
    axes = [-tried_axis, *(a for a in axes if abs(float(a @ tried_axis)) < 0.9)]
    return [start_along(centroid, a, model) for a in axes]


def start_along(centroid: np.ndarray, axis: np.ndarray, model: MarkerModel) -> np.ndarray:
    """``marker_to_image`` with +Y along ``axis`` and the model's centroid at ``centroid`` (any spin)."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    z = np.cross(helper, axis)
    z /= np.linalg.norm(z)
    x = np.cross(axis, z)
    rotation = np.column_stack([x, axis, z])
    _, centroid_y = model_moments(model)
    return make_transform(rotation, centroid - centroid_y * axis)


def skew_axis(centred: np.ndarray, iterations: int = 100, tolerance: float = 1e-9) -> np.ndarray:
    """Unit direction ``u`` maximising the skewness ``E[(p.u)^3] / E[(p.u)^2]^1.5`` of centred points.

    Starts from the principal direction of largest absolute skewness (sign made positive) and
    climbs by the power iteration of the third-moment tensor, ``u <- E[(p.u)^2 p]``, keeping the
    best direction seen (the iteration is not guaranteed monotone). The moments are computed
    once; the iteration works on them alone.
    """
    count = max(len(centred), 1)
    second = centred.T @ centred / count
    pairs = (centred[:, :, None] * centred[:, None, :]).reshape(len(centred), 9)
    third = (pairs.T @ centred).reshape(3, 3, 3) / count

    def skewness(u: np.ndarray) -> float:
        return float(np.einsum("ijk,i,j,k->", third, u, u, u) / max(float(u @ second @ u), 1e-12) ** 1.5)

    _, vectors = np.linalg.eigh(second)
    values = [skewness(vectors[:, k]) for k in range(3)]
    k = int(np.argmax(np.abs(values)))
    best = vectors[:, k] * (1.0 if values[k] > 0 else -1.0)
    best_value = abs(values[k])
    u = best
    for _ in range(iterations):
        step = np.einsum("ijk,j,k->i", third, u, u)
        norm = float(np.linalg.norm(step))
        if norm < 1e-12:
            break
        moved = step / norm
        value = skewness(moved)
        if value > best_value:
            best, best_value = moved, value
        if float(np.linalg.norm(moved - u)) < tolerance:
            break
        u = moved
    return best


def blob_surface_points(mask_zyx: np.ndarray, local_to_image: np.ndarray, max_points: int = 150) -> np.ndarray:
    """The blob's reconstruction: ``vtkFlyingEdges3D`` iso-surface of the mask at 0.5 (linear
    interpolation between voxel centres), at most ``max_points`` of its points (evenly taken), image mm."""
    field = np.pad(mask_zyx.astype(np.float32), 2)
    image = vtkImageData()
    image.SetDimensions(field.shape[2], field.shape[1], field.shape[0])
    image.GetPointData().SetScalars(numpy_to_vtk(field.ravel(), deep=True))
    surface = vtkFlyingEdges3D()
    surface.SetInputData(image)
    surface.SetValue(0, 0.5)
    surface.ComputeNormalsOff()
    surface.ComputeGradientsOff()
    surface.ComputeScalarsOff()
    surface.Update()
    points = surface.GetOutput().GetPoints()
    if points is None:
        return np.empty((0, 3))
    ijk = vtk_to_numpy(points.GetData()).astype(float) - 2.0
    ijk = ijk[:: max(1, int(np.ceil(len(ijk) / max_points)))]
    return apply_transform(local_to_image, ijk)


def icp_to_model(points_marker: np.ndarray, model: MarkerModel, max_iterations: int = 40,
                 max_landmarks: int = 1500, tolerance_mm: float = 1e-3) -> np.ndarray:
    """Rigid ``vtkIterativeClosestPointTransform`` of points (near the marker frame) onto the CAD surface.

    Returns the 4x4 correction ``C`` with ``C @ p`` on the CAD surface. Stops when the points
    move less than ``tolerance_mm`` (RMS) in one iteration.
    """
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points_marker, dtype=float), deep=True))
    source = vtkPolyData()
    source.SetPoints(vtk_points)
    icp = vtkIterativeClosestPointTransform()
    icp.SetSource(source)
    icp.SetTarget(cad_surface(model))
    icp.GetLandmarkTransform().SetModeToRigidBody()
    icp.SetMaximumNumberOfIterations(max_iterations)
    icp.SetMaximumNumberOfLandmarks(max_landmarks)
    icp.StartByMatchingCentroidsOff()
    icp.CheckMeanDistanceOn()
    icp.SetMeanDistanceModeToRMS()
    icp.SetMaximumMeanDistance(tolerance_mm)
    icp.Update()
    matrix = icp.GetMatrix()
    return np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def refine_with(points_image: np.ndarray, marker_to_image: np.ndarray, model: MarkerModel,
                **icp_options) -> np.ndarray:
    """One ICP refinement of ``marker_to_image`` from image points on the marker surface."""
    points_marker = apply_transform(invert_rigid(marker_to_image), points_image)
    correction = icp_to_model(points_marker, model, **icp_options)
    return _orthonormal(marker_to_image @ invert_rigid(correction))


@dataclass
class EdgeHits:
    """Edges found along CAD normals: the predicted surface points, normals (image) and signed offsets (mm)."""

    surface: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @property
    def points(self) -> np.ndarray:
        """The edge points (image mm)."""
        return self.surface + self.offsets[:, None] * self.normals

    def __len__(self) -> int:
        return len(self.offsets)


def edge_points(values_zyx: np.ndarray, local_to_image: np.ndarray, marker_to_image: np.ndarray,
                samples: EdgeSamples, outer_mm: float = 2.0, step_mm: float = 0.2, min_contrast_hu: float = 300.0,
                min_inner_hu: float = 600.0, image_to_local: np.ndarray | None = None) -> EdgeHits:
    """Sub-voxel edges along the CAD normals of ``samples`` placed at ``marker_to_image`` (image mm).

    Each profile's level is half-way between its inner plateau (inside the PVC) and its outer
    plateau (the local background: air, plastic or tissue); the edge is the level crossing
    nearest to the predicted surface. Profiles with too little contrast give no point.
    """
    if image_to_local is None:
        image_to_local = np.linalg.inv(local_to_image)
    s = np.arange(-2.0, outer_mm + step_mm / 2, step_mm)
    base = apply_transform(marker_to_image, samples.points)
    direction = apply_rotation(marker_to_image, samples.normals)
    # index coordinates along every profile: start point plus a per-step increment (cheap), made directly in the
    # (k, j, i) x (profile, step) layout map_coordinates reads (contiguous: no strided reads, no copy)
    start_kji = apply_transform(image_to_local, base + s[0] * direction).T[::-1, :, None]
    step_kji = (apply_rotation(image_to_local, direction) * step_mm).T[::-1, :, None]
    coordinates = (start_kji + np.arange(len(s))[None, None, :] * step_kji).reshape(3, -1)
    profiles = ndimage.map_coordinates(values_zyx, coordinates, order=1, mode="nearest").reshape(len(base), len(s))
    plateau = int(round(0.6 / step_mm))
    inner = np.empty(len(base))
    for depth in np.unique(samples.inner_mm):
        rows = samples.inner_mm == depth
        first = int(np.argmin(np.abs(s + depth)))
        inner[rows] = _row_medians(profiles[rows, first:first + plateau + 1])
    outer = _row_medians(profiles[:, -plateau - 1:])
    level = (inner + outer) / 2
    usable = (inner - outer >= min_contrast_hu) & (inner >= min_inner_hu)
    above = profiles - level[:, None]
    valid = s[None, :-1] >= -samples.inner_mm[:, None]
    crossing = (above[:, :-1] >= 0) & (above[:, 1:] < 0) & valid
    centre = int(np.argmin(np.abs(s)))
    distance = np.where(crossing, np.abs(np.arange(len(s) - 1) - centre), np.iinfo(np.int32).max)
    k = np.argmin(distance, axis=1)
    found = crossing[np.arange(len(k)), k] & usable
    rows = np.nonzero(found)[0]
    k = k[rows]
    a0, a1 = above[rows, k], above[rows, k + 1]
    offsets = s[k] + step_mm * a0 / (a0 - a1)
    return EdgeHits(base[rows], direction[rows], offsets)


def _row_medians(values: np.ndarray) -> np.ndarray:
    """``np.median(values, axis=1)`` for short rows (the same values), without its general machinery: a sort."""
    ordered = np.sort(values, axis=1)
    n = ordered.shape[1]
    return (ordered[:, (n - 1) // 2] + ordered[:, n // 2]) / 2


def point_to_plane_step(hits: EdgeHits, marker_to_image: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """One Gauss-Newton step moving the CAD surface onto the edges along their normals.

    Linearised small rotation ``w`` about the marker's centre and translation ``v``:
    ``offset_i ~ ((q_i - c) x n_i) . w + n_i . v``; the spin about the symmetry axis is not
    observable and the least-squares solution leaves it at zero.
    """
    centre = marker_to_image[:3, 3] + 6.0 * marker_to_image[:3, 1]
    q, n, r = hits.surface[keep], hits.normals[keep], hits.offsets[keep]
    jacobian = np.hstack([np.cross(q - centre, n), n])
    delta, *_ = np.linalg.lstsq(jacobian, r, rcond=1e-6)
    w, v = delta[:3], delta[3:]
    angle = float(np.linalg.norm(w))
    rotation = axis_angle_to_rotation(w / angle, angle) if angle > 1e-12 else np.eye(3)
    update = make_transform(rotation, centre + v - rotation @ centre)
    return update @ marker_to_image


def _robust_keep(offsets: np.ndarray, trim_mm: float) -> np.ndarray:
    centre = np.median(offsets)
    return np.abs(offsets - centre) <= max(min(trim_mm, 0.5), 4 * 1.4826 * _mad(offsets))


def _orthonormal(transform: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(transform[:3, :3])
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        u[:, -1] *= -1
        rotation = u @ vt
    out = transform.copy()
    out[:3, :3] = rotation
    return out


def surface_distances(points_image: np.ndarray, marker_to_image: np.ndarray, model: MarkerModel) -> np.ndarray:
    """Signed distances (mm, negative inside) of image points to the CAD surface at ``marker_to_image``."""
    return model.signed_distance(apply_transform(invert_rigid(marker_to_image), points_image))


#: A fit's RMS before its final ICP above ``good_rms_mm / HOPELESS_FRACTION`` ends it there (:func:`fit_pose`).
HOPELESS_FRACTION = 0.8


def fit_pose(mask_zyx: np.ndarray, mask_to_image: np.ndarray, values_zyx: np.ndarray, values_to_image: np.ndarray,
             model: MarkerModel, min_contrast_hu: float = 300.0, min_inner_hu: float = 600.0,
             trim_mm: float = 1.0, good_rms_mm: float | None = None) -> PoseFit:
    """The pose of one blob (``marker_to_image``) and the fit's quality.

    ``mask_zyx`` is the segmented blob and ``values_zyx`` the raw intensities around it
    (float32, any resolution); ``*_to_image`` map their local (i, j, k) indices to LPS mm.
    Steps: skew-axis start; ``vtkIterativeClosestPointTransform`` of the blob's flying-edges
    reconstruction onto the CAD surface; edge points along the CAD normals with point-to-plane
    steps (usually three); a final ICP of the edge points onto the CAD surface from that close start.

    Given ``good_rms_mm``: on voxels coarse against the marker the skew axis can point across or
    backwards. Edges alone cannot tell a marker from the same marker upside down once the scan
    has blurred its narrow top (the wide part fits either way and the top then finds no edges,
    so the RMS is as small), but the image can: the right pose has PVC inside its top
    (:func:`top_level`). So a good fit whose turned-over pose (:func:`upside_down`) is
    brighter inside its top is fitted again from there; a fit whose RMS exceeds ``good_rms_mm`` is
    tried again from the reversed axis and the blob's principal axes (:func:`other_starts`);
    of the fits within ``good_rms_mm`` the one brightest inside its top is kept.
    """
    voxels_image = apply_transform(mask_to_image, np.argwhere(mask_zyx)[:, ::-1].astype(float))
    start = principal_start(voxels_image, model)
    # the blob's flying-edges reconstruction, brought onto the CAD surface by a short ICP: a start
    # within a few tenths of a millimetre and degree for the edge steps (its iso-level is biased
    # where PVC meets plastic, which the edge steps then remove)
    surface = blob_surface_points(mask_zyx, mask_to_image)
    image_to_local = np.linalg.inv(values_to_image)

    def edges(at: np.ndarray, where: EdgeSamples) -> EdgeHits:
        return edge_points(values_zyx, values_to_image, at, where, min_contrast_hu=min_contrast_hu,
                           min_inner_hu=min_inner_hu, image_to_local=image_to_local)

    # a fit this far from good before its final ICP is taken as staying rejected, so it is not polished: that ICP
    # lowered the RMS by 7% at most over 230 fits of markers and decoys at 0.5-1.5 mm voxels, but by more in 19 of
    # 1597 fits over 79 cases with coarser voxels and 3 mm slices (up to 26% on fits above 0.3 mm: 0.417 -> 0.309)
    hopeless_rms_mm = None if good_rms_mm is None else good_rms_mm / HOPELESS_FRACTION

    def fit_from(pose: np.ndarray, give_up_early: bool = False) -> PoseFit:
        if len(surface) >= 50:
            pose = refine_with(surface, pose, model, max_iterations=5, max_landmarks=len(surface), tolerance_mm=0.05)
        return _edge_fit(pose, edges, model, trim_mm, hopeless_rms_mm, give_up_early)

    fit = fit_from(start)
    if good_rms_mm is None:
        return fit
    level = partial(top_level, values_zyx, image_to_local, model=model)
    if fit.fit_rms_mm <= good_rms_mm:
        turned = fit.marker_to_image @ upside_down(model)
        if level(turned) <= level(fit.marker_to_image):
            return fit
        fits = [fit, fit_from(turned)]
    else:
        # another start counts only if it ends good: one still beyond the hopeless bound on every profile once its
        # sparse steps have settled is given up there. Over 79 simulated cases (0.5 x 0.5 x 0.8 to 2 mm voxels, 3 mm
        # slices, streaks, 4-5 mm tops, decoys; 2735 fits from other starts) every one that ended good on a marker,
        # the right way up or turned over (412), was at most 0.30 mm there against the bound's 0.44; of those that
        # ended not good, 1335 of 2270 were beyond it: a third of the time the other starts take (decoys try all)
        fits = [fit, *(fit_from(other, True) for other in other_starts(voxels_image, model, start[:3, 1]))]
    good = [f for f in fits if f.fit_rms_mm <= good_rms_mm]
    return max(good, key=lambda f: level(f.marker_to_image)) if good else fit


def upside_down(model: MarkerModel) -> np.ndarray:
    """Marker-frame 4x4 turning the marker over about the middle of its wide part (a half turn about X).

    ``marker_to_image @ upside_down(model)`` keeps the wide cylinder where it is and points the
    top the other way: the pose an edge fit can confuse with the right one.
    """
    turn = np.diag([1.0, -1.0, -1.0, 1.0])
    turn[1, 3] = model.bottom_height_mm
    return turn


def top_level(values_zyx: np.ndarray, image_to_local: np.ndarray, marker_to_image: np.ndarray, *,
              model: MarkerModel) -> float:
    """Mean intensity (HU, linear interpolation) at points inside the narrow top at ``marker_to_image``.

    Only the top tells a pose from its turned-over twin (:func:`upside_down` maps the base onto itself):
    averaging the base in as well only adds the noise of sampling it at other points, which outweighed
    a thin top blurred by coarse voxels (a 4 mm top at 1.25 mm voxels, 3 markers of 28 turned over).
    """
    top_points = _interior_parts(model)[1]
    points = top_points if len(top_points) else interior_points(model)  # a top too thin for any: the whole solid
    local = apply_transform(image_to_local @ marker_to_image, points)
    return float(np.mean(ndimage.map_coordinates(values_zyx, local[:, ::-1].T, order=1, mode="nearest")))


def top_contrast(values_zyx: np.ndarray, values_to_image: np.ndarray, marker_to_image: np.ndarray,
                 model: MarkerModel) -> float:
    """How much of the base's contrast the narrow top shows at ``marker_to_image``: (top - around) / (base - around).

    ``top`` and ``base`` are the mean intensities (HU, linear interpolation) inside the top and inside the base
    (:func:`interior_points`), ``around`` the median on a cylinder 2 mm outside the top's side, above the base.
    About 1 for a marker, 0.7 where 3 mm slices blur its top; about 0 for a solid as wide as the base with
    nothing above it, which the edges alone cannot tell from a marker (the top's profiles then find no edge,
    as they find none on a marker's top blurred by coarse voxels). A top too thin to hold any interior point (a
    design with a top under about 2 mm wide) cannot be judged so: 1.0.
    """
    base_points, top_points = _interior_parts(model)
    if not len(top_points):
        return 1.0
    above = model.bottom_height_mm
    angles, heights = np.meshgrid(np.linspace(0.0, 2 * np.pi, 24, endpoint=False),
                                  np.arange(above + 1.0, model.height_mm - 1.0 + 1e-9, 1.0))
    radius = model.top_diameter_mm / 2 + 2.0
    ring = np.column_stack([radius * np.cos(angles).ravel(), heights.ravel(), radius * np.sin(angles).ravel()])
    marker_to_local = np.linalg.inv(values_to_image) @ marker_to_image

    def sampled(marker_points: np.ndarray) -> np.ndarray:
        local = apply_transform(marker_to_local, marker_points)
        return ndimage.map_coordinates(values_zyx, local[:, ::-1].T, order=1, mode="nearest")

    around = float(np.median(sampled(ring)))
    top, base = float(np.mean(sampled(top_points))), float(np.mean(sampled(base_points)))
    return (top - around) / max(base - around, 1.0)


@lru_cache(maxsize=8)
def _interior_parts(model: MarkerModel) -> tuple[np.ndarray, np.ndarray]:
    """:func:`interior_points` of the base and of the top, each at least 0.5 mm from the step between them."""
    points = interior_points(model)
    above = model.bottom_height_mm
    return points[points[:, 1] < above - 0.5], points[points[:, 1] > above + 0.5]


@lru_cache(maxsize=8)
def interior_points(model: MarkerModel, step_mm: float = 0.75, depth_mm: float = 0.5) -> np.ndarray:
    """Points of a grid in the marker frame lying at least ``depth_mm`` inside the solid (pinhole excluded)."""
    r = model.bottom_diameter_mm / 2
    axes = [np.arange(-r, r + step_mm, step_mm), np.arange(0.0, model.height_mm + step_mm, step_mm),
            np.arange(-r, r + step_mm, step_mm)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid[model.signed_distance(grid) <= -depth_mm]


def _edge_fit(pose: np.ndarray, edges: Callable[[np.ndarray, EdgeSamples], EdgeHits], model: MarkerModel,
              trim_mm: float, hopeless_rms_mm: float | None = None, give_up_early: bool = False) -> PoseFit:
    """Point-to-plane steps on edge points found along the CAD normals, then a final VTK ICP.

    A fit whose RMS exceeds ``hopeless_rms_mm`` once the steps have converged is returned as it is,
    without the final ICP (which only polishes a pose that is then rejected); with ``give_up_early``, already once
    the sparse steps have settled (its RMS on every profile then)."""
    samples = edge_samples(model)
    sparse = sparse_edge_samples(model)
    # sparse profiles while the steps are large, every profile once they are small; the last
    # step's edges are kept (a step under 0.02 mm leaves them where they are)
    current = sparse
    hits = edges(pose, current)
    for step in range(8):
        if len(hits) < 30 * len(current.points) / len(samples.points):
            return PoseFit(pose, float("inf"), 0.0, len(hits))
        previous = pose
        # the first step keeps every edge found: the start may sit ~1 mm off along the axis, and
        # trimming around the median offset would then drop the end faces, the only ones that see it
        keep = _robust_keep(hits.offsets, trim_mm) if step else np.ones(len(hits), dtype=bool)
        pose = point_to_plane_step(hits, pose, keep)
        moved = apply_transform(pose, samples.points[::25]) - apply_transform(previous, samples.points[::25])
        moved_mm = float(np.max(np.linalg.norm(moved, axis=1)))
        settled = current is sparse and moved_mm < 0.3
        if settled:
            current = samples
        elif current is samples and moved_mm < 0.02:  # Gauss-Newton: the next step would be ~1e-4 mm
            break
        hits = edges(pose, current)
        if settled and give_up_early and hopeless_rms_mm is not None:
            fit = _scored_fit(pose, hits, model, trim_mm, len(samples.points))
            if fit.fit_rms_mm > hopeless_rms_mm:
                return fit
    if len(hits) < 30 or current is sparse:
        return PoseFit(pose, float("inf"), 0.0, len(hits))
    if hopeless_rms_mm is not None:
        fit = _scored_fit(pose, hits, model, trim_mm, len(samples.points))
        if fit.fit_rms_mm > hopeless_rms_mm:
            return fit
    keep = _robust_keep(hits.offsets, trim_mm)
    pose = refine_with(hits.points[keep], pose, model, max_iterations=20, max_landmarks=len(samples.points),
                       tolerance_mm=1e-4)
    return _scored_fit(pose, hits, model, trim_mm, len(samples.points))


def _scored_fit(pose: np.ndarray, hits: EdgeHits, model: MarkerModel, trim_mm: float, samples: int) -> PoseFit:
    """``pose`` with the RMS distance of the edge points within ``trim_mm`` of the CAD surface, and the share of
    those (scaled down where fewer than half of the ``samples`` profiles found an edge)."""
    distances = surface_distances(hits.points, pose, model)
    inliers = np.abs(distances) <= trim_mm
    rms = float(np.sqrt(np.mean(distances[inliers] ** 2))) if inliers.any() else float("inf")
    coverage = len(hits) / samples
    return PoseFit(pose, rms, float(inliers.mean()) * min(1.0, coverage / 0.5), len(hits))


def _mad(values: np.ndarray) -> float:
    return float(np.median(np.abs(values - np.median(values))))
