"""The distortion test run on a registration's residuals: the test, the one-bad-pair rule, the fitted field."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..error_model import fiducial_jacobian
from .estimate import PREDICTED_SHARE, DistortionEstimate
from .fields import Dipole, Seen
from .power import detectable_rms
from .scan import (
    LENGTH_FRACTIONS,
    MIN_TRANSMITTER_DISTANCE_MM,
    RANK_TOLERANCE,
    NoisePrior,
    Scan,
    as_arrays,
    outlier_p_value,
    pinhole_radius,
    project_residuals,
    rigid_complement,
    rigid_jacobian,
    scan_residuals,
    stack_columns,
)

#: The other pinholes alone carry the evidence when their own test's p-value is at most this.
WITHOUT_LARGEST_LEVEL = 0.05
#: A calibration point left unpaired within this fraction of the pinholes' RMS distance from their centroid of the
#: largest residual's pinhole (the widest bump the test tries) is a neighbour moved too: not one bad pair.
NEIGHBOUR_FRACTION = LENGTH_FRACTIONS[-1]
#: A bad pair's residual lies along its pinhole's axis (a probe not fully inserted): at least this share of its square.
AXIAL_SHARE = 0.7
#: The largest residual is a bad pair's candidate only when its share of the sum of squares has a p-value below this.
OUTLIER_LEVEL = 0.01


def _refine(scan: Scan, model: Any, points: np.ndarray, poses: np.ndarray | None, z: np.ndarray) -> Any:
    """A dipole's position refined from the best candidate (least remaining sum of squares); others as chosen."""
    if not isinstance(model, Dipole):
        return model
    from scipy.optimize import minimize

    def remaining(position: np.ndarray) -> float:
        if np.linalg.norm(position) < MIN_TRANSMITTER_DISTANCE_MM:
            return float(z @ z)
        dipole = Dipole(position, model.tracker_to_reference)
        design = scan.basis.T @ stack_columns(dipole.columns(points, poses, scan.seen))
        q, _ = np.linalg.qr(design)
        return float(z @ z - np.sum((q.T @ z) ** 2))

    result = minimize(remaining, model.object_mm, method="Nelder-Mead",
                      options={"xatol": 1.0, "fatol": 1e-6 * float(z @ z), "maxfev": 300,
                               "initial_simplex": model.object_mm + np.vstack([np.zeros(3), 25.0 * np.eye(3)])})
    return Dipole(np.asarray(result.x, dtype=float), model.tracker_to_reference) \
        if result.fun < remaining(model.object_mm) else model


def estimate_distortion(points_reference: np.ndarray, residuals_reference: np.ndarray,
                        axes_reference: np.ndarray | None, alpha: float, labels: Sequence[str] = (),
                        image_markers: Sequence[str] = (), tracker_to_reference: np.ndarray | None = None,
                        noise: NoisePrior | None = None, max_fre_mm: float = float("inf"),
                        unpaired_reference: np.ndarray | None = None,
                        fitted_count: int | None = None) -> DistortionEstimate:
    """Test the rigid fit's residuals for field distortion and fit it (see the module docstring).

    ``points_reference`` (N, 3): the paired calibration points (Reference, mm); ``residuals_reference``
    (N, 3): measured point minus the registered CT pinhole, in the Reference frame (mm);
    ``axes_reference`` (N, 3): the markers' axes in the Reference frame when l was solved (None: fixed);
    ``alpha``: the false-alarm rate (``[registration] distortion_false_alarm``);
    ``tracker_to_reference`` (N, 4, 4): the transmitter's pose at each point's dwells (None: unknown, no
    dipole candidates; the generic smooth fields and bumps still are); ``noise``: the probe's per-dwell error known
    apart from these residuals (None: the share test alone, and no FRE check); ``max_fre_mm``: the FRE above which
    the registration is refused (``[registration] max_fre_mm``: a field that large is caught, not missed, in
    :func:`.detectable_rms`); ``unpaired_reference`` (K, 3): the calibration points the pairing left out (a
    neighbour of the largest residual among them means a field moved several pinholes, not one bad pair);
    ``fitted_count``: how many of the points (the first) are pairs the registration used (None: all); the others
    are unpaired points near a free CT pinhole, which join the test but not the field's fit or the noise.
    """
    estimate = _estimate(points_reference, residuals_reference, axes_reference, alpha, labels, image_markers,
                         tracker_to_reference, noise, max_fre_mm, unpaired_reference, fitted_count)
    if noise is None or not estimate.tested or not noise.sigma_mm > 0:
        return estimate
    return replace(estimate, noise_prior_sigma_mm=float(noise.sigma_mm), noise_prior_source=noise.source)


def _estimate(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
              alpha: float, labels: Sequence[str], image_markers: Sequence[str],
              tracker_to_reference: np.ndarray | None, noise: NoisePrior | None,
              max_fre_mm: float = float("inf"), unpaired_reference: np.ndarray | None = None,
              fitted_count: int | None = None) -> DistortionEstimate:
    """:func:`.estimate_distortion` before the noise prior is recorded."""
    points, residuals, axes, poses = as_arrays(points_reference, residuals_reference, axes_reference,
                                             tracker_to_reference)
    labels = list(labels) or [f"P{k + 1:02d}" for k in range(len(points))]
    image_markers = list(image_markers)
    n = len(points) if fitted_count is None else min(int(fitted_count), len(points))
    # the pairs: the field and the noise are measured on them; the points after them only add evidence to the test
    pair_points, pair_residuals = points[:n], residuals[:n]
    pair_axes, pair_poses = (None if axes is None else axes[:n]), (None if poses is None else poses[:n])
    joined = labels[n:]
    rms = float(np.sqrt(np.mean(pair_residuals**2))) if n else 0.0
    note = "" if poses is not None else ("the calibration does not say where the transmitter was (an older "
                                         "frame_calibration.json): no induced-dipole candidates, generic smooth "
                                         "fields only")
    untested = DistortionEstimate(labels[:n], pair_points, pair_residuals, 0.0, 1.0, alpha, rms, tested=False,
                                  image_markers=image_markers[:n], note="too few pinholes to test")
    if n < 4:
        return untested
    tested = scan_residuals(points, axes, poses, residuals, noise)
    if tested is None:
        return untested if not len(residuals) or np.any(residuals) else replace(untested, note="")
    scan, z, statistic, p_value, best, null = tested
    pair_test = (tested if n == len(points)
                 else scan_residuals(pair_points, pair_axes, pair_poses, pair_residuals, noise))
    prior = None if noise is None else noise.sigma_mm

    def finished(estimate: DistortionEstimate) -> DistortionEstimate:
        return replace(estimate, tested_unpaired=joined,
                       detectable_rms_mm=detectable_rms(scan, points, null, alpha, estimate.noise_sigma_mm, prior,
                                                        max_fre_mm=max_fre_mm))

    noise_scan, noise_z = (scan, z) if pair_test is None else pair_test[:2]
    noise_alone = (float(np.sqrt(noise_z @ noise_z / noise_scan.dof)), float(noise_scan.dof))
    if p_value > alpha:
        return finished(DistortionEstimate(labels[:n], pair_points, pair_residuals, statistic, p_value, alpha,
                                           *noise_alone, image_markers=image_markers[:n], note=note))
    largest = int(np.argmax(np.sum(residuals**2, axis=1)))
    keep = np.arange(len(points)) != largest
    p_without, share = float("nan"), float("nan")
    rest = scan_residuals(points[keep], None if axes is None else axes[keep], None if poses is None else poses[keep],
                 residuals[keep], noise, support=1.0) if len(points) > 4 else None
    if rest is not None:
        p_without = rest[3]
        share = _predicted_share(rest[0].candidates[rest[4]], points, poses, axes, residuals, largest)
    axial = 1.0 if axes is None else float((residuals[largest] @ axes[largest]) ** 2
                                           / max(residuals[largest] @ residuals[largest], 1e-300))
    if not _several_points(p_without, share, outlier_p_value(scan, residuals), axial,
                           _unpaired_near(points, largest, unpaired_reference)):
        return finished(DistortionEstimate(labels[:n], pair_points, pair_residuals, statistic, p_value, alpha,
                                           *noise_alone, image_markers=image_markers[:n], note=note,
                                           p_value_without_largest=p_without, largest_predicted_share=share,
                                           left_out=labels[largest], one_bad_pair=True))
    if pair_test is None:  # too few pairs to fit a field on them alone: on every point tested
        return finished(_fitted(scan, z, best, points, residuals, axes, poses, labels, image_markers, statistic,
                                p_value, alpha, note, p_without, share, labels[largest]))
    return finished(_fitted(pair_test[0], pair_test[1], pair_test[4], pair_points, pair_residuals, pair_axes,
                            pair_poses, labels[:n], image_markers[:n], statistic, p_value, alpha, note, p_without,
                            share, labels[largest]))


def _fitted(scan: Scan, z: np.ndarray, best: int, points: np.ndarray, residuals: np.ndarray,
            axes: np.ndarray | None, poses: np.ndarray | None, labels: list[str], image_markers: Sequence[str],
            statistic: float, p_value: float, alpha: float, note: str, p_without: float = float("nan"),
            share: float = float("nan"), left_out: str = "") -> DistortionEstimate:
    """The estimate with candidate ``best`` fitted by least squares (a dipole's position refined first)."""
    model = _refine(scan, scan.candidates[best], points, poses, z)
    at_pinholes = model.columns(points, poses, scan.seen)  # (N, 3, P)
    design = scan.basis.T @ stack_columns(at_pinholes)
    # no more directions than the scan tested the candidate with (its rank there): a candidate of more columns than
    # residual dimensions must not fit the noise away (a 60-column cubic polynomial spans all 41 of 28 pinholes)
    u, singular, vt = np.linalg.svd(design, full_matrices=False)
    rank = min(scan.rank_of(best), int(np.count_nonzero(singular > RANK_TOLERANCE * singular[0])))
    inverse = vt[:rank].T @ (u[:, :rank] / singular[:rank]).T
    amplitudes = inverse @ z
    remaining = z - design @ amplitudes
    dof = scan.dof - rank - (3 if isinstance(model, Dipole) else 0)
    variance = float(remaining @ remaining) / max(dof, 1)
    covariance = variance * inverse @ inverse.T
    rigid = np.linalg.pinv(rigid_jacobian(points, axes))[:6] @ stack_columns(at_pinholes)
    centroid = points.mean(axis=0)
    nonrigid = at_pinholes @ amplitudes - fiducial_jacobian(points, centroid) @ (rigid @ amplitudes)
    return DistortionEstimate(labels, points, residuals, statistic, p_value, alpha, float(np.sqrt(variance)),
                              float(max(dof, 1)), model, amplitudes, covariance, rigid, nonrigid,
                              image_markers=list(image_markers), note=note, p_value_without_largest=p_without,
                              largest_predicted_share=share, left_out=left_out,
                              **_leave_one_out(scan.basis, scan.basis @ u[:, :rank], remaining))


def _leave_one_out(basis: np.ndarray, field_basis: np.ndarray, remaining: np.ndarray) -> dict[str, float]:
    """The fitted field's leave-one-out errors at the pinholes, for :attr:`.DistortionEstimate.extension_ms`: each
    pinhole's ``(I - H_ii)^-1`` times its residual beside the fit (``H``: the hat matrix of the rigid motion and the
    field together; ``basis`` (3N, m) the residual space, ``field_basis`` (3N, P) the field's columns there,
    orthonormal; ``remaining`` (m,) the residual beside the field in ``basis``). Returns their mean square
    (``loo_ms``, mm^2) and the mean of ``tr((I - H_ii)^-1)`` (``loo_noise_factor``): noise of variance s^2 per
    axis gives them ``s^2`` times that on average, exactly, for a field of the fitted family."""
    n = len(basis) // 3
    hat = np.eye(3 * n) - basis @ basis.T + field_basis @ field_basis.T
    blocks = np.stack([np.eye(3) - hat[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    left = (basis @ remaining).reshape(n, 3, 1)
    try:
        loo = np.linalg.solve(blocks, left)[..., 0]
        factor = np.trace(np.linalg.inv(blocks), axis1=-2, axis2=-1)
    except np.linalg.LinAlgError:
        return {"loo_ms": 0.0, "loo_noise_factor": 0.0}
    return {"loo_ms": float(np.mean(np.sum(loo**2, axis=1))), "loo_noise_factor": float(np.mean(factor))}


def fit_field(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
              tracker_to_reference: np.ndarray | None = None) -> DistortionEstimate | None:
    """The smooth field the test picks, fitted to the residuals whether significant or not (None: too few points):
    to ask whether it explains where points left out of the pairing lie (:meth:`.DistortionEstimate.field_at`).
    Frames and units as :func:`.estimate_distortion`."""
    points, residuals, axes, poses = as_arrays(points_reference, residuals_reference, axes_reference,
                                             tracker_to_reference)
    projected = project_residuals(points, axes, poses, residuals) if len(points) >= 4 else None
    if projected is None:
        return None
    scan, z = projected
    best = _cross_validated(scan, points, poses, residuals)
    share = float(scan.best(z)[1])
    return _fitted(scan, z, best, points, residuals, axes, poses, [f"P{k + 1:02d}" for k in range(len(points))],
                   (), share, float("nan"), 0.0, "")


def _cross_validated(scan: Scan, points: np.ndarray, poses: np.ndarray | None, residuals: np.ndarray) -> int:
    """The candidate that best predicts each pinhole's residual from the others (leave-one-out, closed form:
    ``(I - H_ii)^-1 e_i`` per pinhole, H the fit's hat matrix): the field to extend beyond the pinholes, where a
    candidate chosen by its fit alone may be the one with most columns."""
    r = residuals.reshape(-1)
    n = len(points)
    scores = []
    for candidate in scan.candidates:
        design = scan.basis @ (scan.basis.T @ stack_columns(candidate.columns(points, poses, scan.seen)))
        u, singular, _ = np.linalg.svd(design, full_matrices=False)
        u = u[:, singular > singular[0] * 1e-9] if singular[0] > 0 else u[:, :0]
        left = (r - u @ (u.T @ r)).reshape(n, 3)
        hat = np.einsum("iap,ibp->iab", u.reshape(n, 3, -1), u.reshape(n, 3, -1))
        try:
            loo = np.linalg.solve(np.eye(3) - hat, left[..., None])[..., 0]
        except np.linalg.LinAlgError:
            scores.append(np.inf)
            continue
        scores.append(float(np.sum(loo**2)))
    return int(np.argmin(scores))


def _several_points(p_without: float, share: float, p_outlier: float, axial: float = 1.0,
                    unpaired_near: bool = False) -> bool:
    """Whether the evidence is carried by more pinholes than the one of the largest residual (a bad pair is one
    point; a field moves several neighbours): not when that residual is an outlier by itself (its share of the sum
    of squares is beyond noise at :data:`.OUTLIER_LEVEL`), the others alone are not significant at
    :data:`.WITHOUT_LARGEST_LEVEL`, the field they pick predicts less than :data:`.PREDICTED_SHARE` of its
    squared residual, no calibration point near it was left unpaired (``unpaired_near``: a neighbour moved out of
    pairing is a second point moved), and, when the marker axes are known, that residual lies along its pinhole's
    axis (``axial``: its share along it, at least :data:`.AXIAL_SHARE`: a probe not fully inserted; a field moves a
    point any way). Untestable without it: counted as several."""
    if not np.isfinite(p_without):
        return True
    return (p_outlier > OUTLIER_LEVEL or p_without <= WITHOUT_LARGEST_LEVEL or share >= PREDICTED_SHARE
            or axial < AXIAL_SHARE or unpaired_near)


def _unpaired_near(points: np.ndarray, index: int, unpaired: np.ndarray | None) -> bool:
    """Whether a calibration point left unpaired (K, 3) lies within :data:`.NEIGHBOUR_FRACTION` of the pinholes' RMS
    distance from their centroid of pinhole ``index`` (all Reference, mm)."""
    if unpaired is None or not len(unpaired):
        return False
    radius = pinhole_radius(points)
    gaps = np.linalg.norm(np.asarray(unpaired, dtype=float).reshape(-1, 3) - points[index], axis=1)
    return bool(np.any(gaps < NEIGHBOUR_FRACTION * radius))


def _predicted_share(model: Any, points: np.ndarray, poses: np.ndarray | None, axes: np.ndarray | None,
                     residuals: np.ndarray, left_out: int) -> float:
    """How much of pinhole ``left_out``'s squared residual ``model`` (the field the other pinholes' test picked),
    fitted to the other pinholes, predicts there (1 - |r - prediction|^2 / |r|^2; 0 or less: nothing)."""
    basis = rigid_complement(rigid_jacobian(points, axes))
    seen = None if poses is None else Seen(points, poses)
    rows = np.ones(3 * len(points), dtype=bool)
    rows[3 * left_out:3 * left_out + 3] = False
    r = residuals.reshape(-1)
    design = basis @ (basis.T @ stack_columns(model.columns(points, poses, seen)))
    amplitudes, *_ = np.linalg.lstsq(design[rows], r[rows], rcond=None)
    target = residuals[left_out]
    return float(1.0 - np.sum((target - design[~rows] @ amplitudes) ** 2) / np.sum(target**2))
