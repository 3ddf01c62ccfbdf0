"""The sensor offset l and FRE(l) (paper section 2.4, Eq. 10).

The probe's electrical centre sits at an unknown depth l in every marker's pinhole: the image
pinhole point of marker j is ``q_j(l) = origin_j + l * axis_j`` (image space, LPS mm). For one l
the calibration points ``p_j`` (Reference frame, mm) are fitted onto ``q_j(l)`` by a least-squares
rigid fit; FRE(l) is the RMS residual of that fit (Eq. 10), and the l minimising it is the sensor
offset.

This module is the one implementation of Eq. 10 in EMReg: :func:`fre_curve` evaluates FRE(l) for
many l and many point sets at once (pairing scores thousands of triangle hypotheses in one call;
registration samples the pinhole range; the report plots the curve), and
:func:`solve_sensor_offset` finds its minimum over [a, b] with the standard error of l.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .transforms import fit_rigid_batch


@dataclass(frozen=True)
class FRECurve:
    """FRE(l) samples and the rigid fit behind each sample.

    Shapes: ``...`` are the batch axes of the point sets, L the number of l values and N the
    number of points. ``l_mm`` (L,); ``fre_mm`` and ``sse_mm2`` (..., L): RMS residual and sum of
    squared residuals; ``rotation`` (..., L, 3, 3) and ``translation`` (..., L, 3): the fitted
    ``ReferenceToImage``; ``residuals_mm`` (..., L, N): per-point residuals (mm).
    """

    l_mm: np.ndarray
    fre_mm: np.ndarray
    sse_mm2: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    residuals_mm: np.ndarray

    @property
    def reference_to_image(self) -> np.ndarray:
        """The fitted ``ReferenceToImage`` transforms (..., L, 4, 4) (Reference -> image LPS, mm)."""
        transforms = np.zeros(self.rotation.shape[:-2] + (4, 4))
        transforms[..., :3, :3] = self.rotation
        transforms[..., :3, 3] = self.translation
        transforms[..., 3, 3] = 1.0
        return transforms


def fre_curve(l_values: ArrayLike, points_reference: ArrayLike, origins_image: ArrayLike,
              axes_image: ArrayLike) -> FRECurve:
    """FRE(l) (paper Eq. 10) at each sensor offset of ``l_values`` (L,) in mm.

    ``points_reference`` (..., N, 3): calibration points (Reference frame, mm);
    ``origins_image`` and ``axes_image`` (..., N, 3): the paired markers' origins (bottom-face
    centres) and unit +Y axes (image space, LPS mm). The batch axes ``...`` broadcast against
    each other. For every l the points are fitted rigidly (reflection-safe least squares, see
    :func:`EMRegModule.core.transforms.fit_rigid_batch`) onto ``origins + l * axes``.
    """
    l_mm = np.atleast_1d(np.asarray(l_values, dtype=float))
    if l_mm.ndim != 1:
        raise ValueError(f"fre_curve needs a 1-D array of l values, got shape {l_mm.shape}")
    points = np.asarray(points_reference, dtype=float)[..., None, :, :]
    origins = np.asarray(origins_image, dtype=float)[..., None, :, :]
    axes = np.asarray(axes_image, dtype=float)[..., None, :, :]
    pinholes = origins + l_mm[:, None, None] * axes  # (..., L, N, 3)
    points = np.broadcast_to(points, np.broadcast_shapes(points.shape, pinholes.shape))
    pinholes = np.broadcast_to(pinholes, points.shape)
    rotation, translation = fit_rigid_batch(points, pinholes)
    mapped = np.einsum("...ij,...nj->...ni", rotation, points) + translation[..., None, :]
    squared = np.sum((mapped - pinholes) ** 2, axis=-1)  # (..., L, N)
    sse = np.sum(squared, axis=-1)
    return FRECurve(l_mm, np.sqrt(sse / squared.shape[-1]), sse, rotation, translation, np.sqrt(squared))


@dataclass
class OffsetSolution:
    """The l minimising FRE(l) in [a, b] (mm), its standard error (mm), FRE at it (mm), the fitted
    ``ReferenceToImage`` (4x4) and FRE(l) samples over [a, b] every 0.25 mm for the report."""

    l_mm: float
    l_std_mm: float
    fre_mm: float
    reference_to_image: np.ndarray
    curve_l_mm: np.ndarray
    curve_fre_mm: np.ndarray


def solve_sensor_offset(points_reference: np.ndarray, origins_image: np.ndarray, axes_image: np.ndarray,
                        l_range_mm: tuple[float, float], grid_step_mm: float = 0.1) -> OffsetSolution:
    """Minimise FRE(l) over l in ``l_range_mm`` = (a, b): a grid of ``grid_step_mm``, then a bounded
    Brent search around the best node.

    Arguments as for :func:`fre_curve` (one point set, N >= 3). The standard error of l comes from
    the curvature of the residual sum of squares at the minimum, ``std(l) = sqrt(2 sigma^2 / SSE''(l))``
    with sigma^2 the per-coordinate noise variance estimated from the residuals (``inf`` when the
    curve is flat: the axes are parallel and l trades off against a translation).
    """
    a, b = float(l_range_mm[0]), float(l_range_mm[1])
    n = len(points_reference)

    def curve(l_values) -> FRECurve:
        return fre_curve(l_values, points_reference, origins_image, axes_image)

    def sse(l_value: float) -> float:
        return float(curve([l_value]).sse_mm2[0])

    if b - a < 1e-9:
        at_a = curve([a])
        return OffsetSolution(a, 0.0, float(at_a.fre_mm[0]), at_a.reference_to_image[0], np.array([a]),
                              at_a.fre_mm.copy())
    grid = np.linspace(a, b, max(3, int(round((b - a) / grid_step_mm)) + 1))
    grid_sse = curve(grid).sse_mm2
    k = int(np.argmin(grid_sse))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    from scipy.optimize import minimize_scalar  # here: readers of FRE(l) (the report) do not load scipy.optimize

    found = minimize_scalar(sse, bounds=(lo, hi), method="bounded", options={"xatol": 1e-5})
    l_best = float(found.x) if found.fun <= grid_sse[k] else float(grid[k])
    at_best = curve([l_best])
    fre_value = float(at_best.fre_mm[0])
    curvature = _sse_curvature(sse, l_best, a, b)
    dof = 3 * n - 7
    sigma2 = (n * fre_value**2) / dof if dof > 0 else float("nan")
    l_std = float(np.sqrt(2 * sigma2 / curvature)) if curvature > 1e-12 and np.isfinite(sigma2) else float("inf")
    curve_l = np.linspace(a, b, max(2, int(round((b - a) / 0.25)) + 1))
    curve_fre = np.sqrt(np.interp(curve_l, grid, grid_sse) / n)
    return OffsetSolution(l_best, l_std, fre_value, at_best.reference_to_image[0], curve_l, curve_fre)


def _sse_curvature(sse, l_best: float, a: float, b: float, h: float = 0.05) -> float:
    """Second derivative of SSE(l) at ``l_best`` (central difference, one-sided at a bound of [a, b])."""
    if l_best - h < a:
        c = sse(l_best) - 2 * sse(l_best + h) + sse(l_best + 2 * h)
    elif l_best + h > b:
        c = sse(l_best) - 2 * sse(l_best - h) + sse(l_best - 2 * h)
    else:
        c = sse(l_best - h) - 2 * sse(l_best) + sse(l_best + h)
    return c / h**2
