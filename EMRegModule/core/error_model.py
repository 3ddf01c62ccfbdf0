"""The error a user will see: end-to-end target registration error (TRE) predicted from measured quantities.

A target touched with the tracked probe is shown at
``ReferenceToImage @ inv(ReferenceToTracker) @ ProbeToTracker`` (paper Eq. 12). Its error, in image
space (CT LPS, mm), is modelled as the sum of independent, zero-mean, first-order terms:

1. **Registration.** The fiducial localisation errors of both spaces (calibration points in the
   Reference frame, marker points in the CT) propagated through the least-squares rigid fit, with
   the sensor offset l solved jointly. This is the general first-order propagation of Danilchenko &
   Fitzpatrick (2011): anisotropic, different per point and per space; the fit's parameters are a
   small rotation about the fiducial centroid, a translation and l. Fitzpatrick, West & Maurer's
   isotropic formula is the special case of equal isotropic errors and fixed l.
2. **Tracking at the target.** The probe's error at navigation time: the tracker's per-dwell error
   of the same probe on the same tracker, which the calibration residuals reveal (estimated from
   the exact expected residual sum of squares of the fit, :func:`estimate_isotropic_fle`); when a
   navigation recording with repeated dwells at the targets is evaluated, measured directly from
   their scatter (:func:`repeated_dwell_ms`: tracker, hand tremor and jitter at navigation time).
3. **Reference sensor.** The reference sensor's own 6-DOF pose error: once during calibration
   (common to every calibration point, so the fit absorbs it and the whole registration moves with
   it; it never shows in the FRE) and once more during navigation. At a point with lever arm ``x``
   from the sensor's origin (Reference coordinates) a pose error with position sigma ``s_p`` and
   rotation sigma ``s_r`` (per axis) gives the covariance ``s_p^2 I + s_r^2 [x]x [x]x^T`` (Wiles &
   Peters 2010). One session cannot observe this error (it is common to everything measured), so
   its size is a prior: ``[evaluation] reference_error_mm`` / ``reference_error_deg``.
4. **Placement.** How well the probe sits on the target: ``[evaluation] placement_error_mm``.

Dropped, and why: second-order terms (errors are far smaller than the distances involved); any
correlation between the per-dwell tracker errors at different places (treated as independent); the
bound ``a <= l <= b`` (l is treated as free even at an end of the range); changes of the reference
sensor's error within a session (a bump between dwells).

A configuration that does not determine the registration (fewer than 3 markers, collinear markers,
parallel marker axes with l free) gives an infinite prediction, never a small number.

**Field distortion** found at registration (:mod:`EMRegModule.core.distortion`) adds a fifth term: the
fitted non-rigid field at the target and its uncertainty, for navigation in the same field; the probe's
per-dwell error is then the noise beside the field, not the residuals' whole size.

**Checked against what was measured.** Errors the model has no term for (a probe tip that is not
where the sensor reports it, a reference sensor that moved on the patient, a wrong fixed l, field
distortion that appeared after the registration) are invisible to it: the prediction would stay small
while the surgeon sees more.
When dwells at targets were measured, :func:`optimism_limit` gives the largest ratio of measured to
predicted mean-square TRE that the model's own randomness explains; a larger one means the
prediction is optimistic and is said in a warning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .transforms import apply_transform, invert_rigid

#: A fit whose normal matrix is worse conditioned than this does not determine the registration.
MAX_CONDITION = 1e10

#: The reference sensor's default rotation error per its position error (rad per mm): the rotation that moves a point
#: this far (mm) by as much. The trakSTAR's specified static accuracy, 1.4 mm RMS and 0.5 degree RMS for its sensors,
#: puts them level at 160 mm (1.4 / 0.0087). It was 100 mm, a round guess, which over-predicted the clean simulated
#: sessions' TRE by 9 % (200 sessions: the reference term 0.082 mm^2 predicted, 0.045 measured beside an exact
#: registration and tracking term).
REFERENCE_LEVER_MM = 160.0


def skew(vectors: np.ndarray) -> np.ndarray:
    """The cross-product matrices ``[v]x`` (..., 3, 3) of vectors (..., 3): ``[v]x @ w = v x w``."""
    v = np.asarray(vectors, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def fiducial_jacobian(fiducials_image: np.ndarray, centre_image: np.ndarray,
                      axes_image: np.ndarray | None = None) -> np.ndarray:
    """d(residual)/d(parameters), (N, 3, P): how each fit residual changes with the fit's parameters.

    Residual ``r_i = ReferenceToImage(x_i) - (o_i + l a_i)`` (image space, mm). Parameters: a small
    rotation (rad, 3) about ``centre_image`` applied after the fitted transform, a translation (mm, 3)
    and, when ``axes_image`` (N, 3) is given, the sensor offset l (mm): P = 7, otherwise 6.
    """
    arm = np.asarray(fiducials_image, dtype=float) - np.asarray(centre_image, dtype=float)
    blocks = [-skew(arm), np.broadcast_to(np.eye(3), arm.shape[:-1] + (3, 3))]
    if axes_image is not None:
        blocks.append(-np.asarray(axes_image, dtype=float)[..., None])
    return np.concatenate(blocks, axis=-1)


@dataclass(frozen=True)
class RegistrationCovariance:
    """First-order covariance of a fitted ``ReferenceToImage`` (see the module docstring).

    ``parameters``: (P, P) covariance of (rotation about ``centre_image`` in rad, translation in mm
    [, l in mm]); infinite entries when the configuration does not determine the fit.
    """

    parameters: np.ndarray
    centre_image: np.ndarray

    @property
    def determined(self) -> bool:
        return bool(np.all(np.isfinite(self.parameters)))

    @property
    def l_std_mm(self) -> float:
        """Standard error of the sensor offset l (mm); 0 when l was fixed."""
        return float(np.sqrt(self.parameters[6, 6])) if len(self.parameters) > 6 else 0.0

    def at(self, points_image: np.ndarray) -> np.ndarray:
        """Covariance (K, 3, 3, mm^2) of the registration error at image points (K, 3) (LPS, mm)."""
        points = np.asarray(points_image, dtype=float).reshape(-1, 3)
        jacobian = fiducial_jacobian(points, self.centre_image)  # rotation and translation only
        if not self.determined:
            return np.full((len(points), 3, 3), np.inf)
        block = self.parameters[:6, :6]
        return jacobian @ block @ np.swapaxes(jacobian, -1, -2)


def registration_covariance(fiducials_image: np.ndarray, covariances_image: np.ndarray,
                            axes_image: np.ndarray | None = None) -> RegistrationCovariance:
    """Covariance of an unweighted least-squares rigid fit (with l when ``axes_image`` is given).

    ``fiducials_image`` (N, 3): the paired sensor points ``o_i + l a_i`` in image space (mm);
    ``covariances_image`` (N, 3, 3): each point's localisation error covariance in image space,
    both spaces together (a Reference-frame covariance ``C`` enters as ``R C R^T`` with ``R`` the
    fitted rotation). ``axes_image`` (N, 3): the marker axes, when l was solved.
    """
    fiducials = np.asarray(fiducials_image, dtype=float).reshape(-1, 3)
    centre = fiducials.mean(axis=0)
    jacobian = fiducial_jacobian(fiducials, centre, axes_image)
    n_parameters = jacobian.shape[-1]
    normal = np.einsum("nip,niq->pq", jacobian, jacobian)
    if len(fiducials) < 3 or np.linalg.cond(normal) > MAX_CONDITION:
        return RegistrationCovariance(np.full((n_parameters, n_parameters), np.inf), centre)
    inverse = np.linalg.inv(normal)
    meat = np.einsum("nip,nij,njq->pq", jacobian, np.asarray(covariances_image, dtype=float), jacobian)
    return RegistrationCovariance(inverse @ meat @ inverse, centre)


def estimate_isotropic_fle(residuals_mm: np.ndarray, fiducials_image: np.ndarray,
                           axes_image: np.ndarray | None = None,
                           known_covariances: np.ndarray | None = None) -> float:
    """Per-axis sigma (mm) of the isotropic localisation error that explains a fit's residuals.

    With point errors of covariance ``s^2 I + K_i`` the expected residual sum of squares of the fit
    is ``s^2 (3N - P) + tr((I - H) K)`` (H the fit's hat matrix, P its parameter count); solved for
    ``s^2`` from the observed residuals (N,) (mm). This generalises ``FLE^2 = FRE^2 N / (N - 2)``
    to a solved l and to known anisotropic parts ``known_covariances`` (N, 3, 3). Infinite when the
    fit has no residual degrees of freedom.
    """
    fiducials = np.asarray(fiducials_image, dtype=float).reshape(-1, 3)
    jacobian = fiducial_jacobian(fiducials, fiducials.mean(axis=0), axes_image)
    n, n_parameters = len(fiducials), jacobian.shape[-1]
    dof = 3 * n - n_parameters
    if dof <= 0:
        return float("inf")
    ssr = float(np.sum(np.square(residuals_mm)))
    known = 0.0
    if known_covariances is not None:
        stacked = jacobian.reshape(3 * n, n_parameters)
        hat = stacked @ np.linalg.pinv(stacked.T @ stacked) @ stacked.T
        block = np.zeros((3 * n, 3 * n))
        for i, covariance in enumerate(np.asarray(known_covariances, dtype=float)):
            block[3 * i:3 * i + 3, 3 * i:3 * i + 3] = covariance
        known = float(np.trace(block) - np.trace(hat @ block))
    return float(np.sqrt(max(ssr - known, 0.0) / dof))


def pose_error_covariance(lever_arms_mm: np.ndarray, position_sigma_mm: float,
                          rotation_sigma_rad: float) -> np.ndarray:
    """Covariance (K, 3, 3, mm^2) of points fixed to a 6-DOF sensor whose pose has an error.

    ``lever_arms_mm`` (K, 3): the points in the sensor's frame (mm); the pose error has per-axis
    sigmas ``position_sigma_mm`` (mm) and ``rotation_sigma_rad`` (rad), isotropic and independent
    (Wiles & Peters 2010, first order). Expressed in the sensor's frame; rotate for another frame.
    """
    cross = skew(np.asarray(lever_arms_mm, dtype=float).reshape(-1, 3))
    return position_sigma_mm**2 * np.eye(3) + rotation_sigma_rad**2 * cross @ np.swapaxes(cross, -1, -2)


def repeated_dwell_ms(dwell_means_by_target: dict[str, np.ndarray]) -> tuple[float, int] | None:
    """Mean-square 3D error (mm^2) of one dwell, measured from repeated dwells at the same targets.

    ``dwell_means_by_target``: per target the (n, 3) means of its dwells (image space, mm). The
    scatter of a target's dwells about their own mean is the probe's per-dwell error at navigation
    time (tracker, tremor, jitter), whatever the registration's error (common to them); pooled
    over targets with ``n - 1`` degrees of freedom each. Returns (mean square, dwells' degrees of
    freedom), or None when no target was visited twice.
    """
    squares, dof = 0.0, 0
    for means in dwell_means_by_target.values():
        means = np.asarray(means, dtype=float).reshape(-1, 3)
        if len(means) > 1:
            squares += float(np.sum((means - means.mean(axis=0)) ** 2))
            dof += len(means) - 1
    return (squares / dof, dof) if dof else None


def satterthwaite_dof(mean_squares: list[float], dofs: list[float]) -> float:
    """Effective degrees of freedom of a sum of independent mean-square estimates (Welch-Satterthwaite):
    ``(sum m)^2 / sum(m^2 / dof)``; infinite when every part is exact (infinite dof) or zero."""
    parts = [(float(m), float(d)) for m, d in zip(mean_squares, dofs, strict=True) if m > 0]
    spread = sum(m * m / d for m, d in parts if np.isfinite(d))
    total = sum(m for m, _ in parts)
    return total * total / spread if spread > 0 else float("inf")


#: Quadrature nodes of the probability integrals in :func:`optimism_limit` (midpoints in probability).
_NODES = 128


# chi-square tail, inverse tail and quantile from the regularised incomplete gamma functions, imported where
# used: scipy.stats and scipy.optimize at the top of this module added about a second of imports to every command
# that reads a registration (the report's among them), for a check only the evaluation makes
def _chi2_sf(x: np.ndarray | float, dof: float) -> np.ndarray:
    from scipy.special import gammaincc

    return gammaincc(dof / 2.0, np.asarray(x, dtype=float) / 2.0)


def _chi2_isf(p: np.ndarray, dof: float) -> np.ndarray:
    from scipy.special import gammainccinv

    return 2.0 * gammainccinv(dof / 2.0, p)


def _chi2_ppf(p: np.ndarray, dof: float) -> np.ndarray:
    from scipy.special import gammaincinv

    return 2.0 * gammaincinv(dof / 2.0, p)


def _ratio_survival(ratio: float, common_share: float, scatter_share: float, scatter_dof: float,
                    prediction_scale: np.ndarray, prediction_weight: np.ndarray) -> float:
    """P(measured / predicted mean square > ``ratio``) with the measured one ``common_share * X / 3 +
    scatter_share * Y / scatter_dof`` (X ~ chi2(3), Y ~ chi2(scatter_dof), independent), averaged over
    the prediction's own relative error: values ``prediction_scale`` with probabilities ``prediction_weight``."""
    threshold = ratio * prediction_scale  # (W,): the measured share each prediction value must exceed
    if scatter_share <= 0:
        return float(prediction_weight @ _chi2_sf(3.0 * threshold / common_share, 3))
    if common_share <= 0:
        return float(prediction_weight @ _chi2_sf(threshold * scatter_dof / scatter_share, scatter_dof))
    # integrate over X by its tail probability v = P(chi2(3) > X), on a log scale (the excess comes from
    # the tail): v in (v0, 1), v0 = P(chi2(3) > 3 t / common_share); for X beyond, always exceeded
    v0 = np.maximum(_chi2_sf(3.0 * threshold / common_share, 3), 1e-300)  # (W,)
    step = -np.log(v0) / _NODES
    v = np.exp(np.log(v0)[:, None] + step[:, None] * (np.arange(_NODES) + 0.5))
    rest = threshold[:, None] - common_share * _chi2_isf(v, 3) / 3.0
    weight = v * step[:, None]  # dv = v ds
    inside = np.sum(weight * _chi2_sf(np.maximum(rest, 0.0) * scatter_dof / scatter_share, scatter_dof), axis=1)
    return float(prediction_weight @ (inside + v0))


def optimism_limit(common_ms: float, independent_ms: float, n_dwells: int, prediction_dof: float = float("inf"),
                   false_alarm: float = 1e-3) -> float:
    """The largest ratio of measured to predicted mean-square TRE over ``n_dwells`` dwells that the model's own
    randomness explains (exceeded by chance with probability ``false_alarm``).

    ``common_ms`` (mm^2): the predicted mean square of the terms every dwell of one session shares
    (registration, reference sensor), counted as one 3D error ``c`` (3 degrees of freedom: the fewest
    it can have, so the limit errs high); ``independent_ms`` (mm^2): the terms drawn afresh per dwell
    (tracking, placement), ``u_j``. The measured mean square ``mean |c + u_j|^2`` splits exactly into
    two independent parts, ``|c + mean u|^2`` (3 degrees of freedom) and the dwells' scatter about
    their mean (``3 (n - 1)``); its distribution is integrated numerically. The prediction itself
    was estimated from ``prediction_dof`` degrees of freedom (residuals, dwell scatter; infinite
    for an exact one): its relative error, ``chi2(dof) / dof``, is averaged over. Infinite without dwells.
    """
    total = common_ms + independent_ms
    if n_dwells < 1 or total <= 0:
        return float("inf")
    common_share = (common_ms + independent_ms / n_dwells) / total
    scatter_share = independent_ms * (n_dwells - 1) / n_dwells / total
    scatter_dof = 3.0 * (n_dwells - 1)
    if np.isfinite(prediction_dof):  # its probability on a logit scale, out to 6e-6 in either tail
        z = np.linspace(-12.0, 12.0, _NODES)
        u = 1.0 / (1.0 + np.exp(-z))
        scale = _chi2_ppf(u, prediction_dof) / prediction_dof
        weight = u * (1.0 - u) * (z[1] - z[0])
        weight /= weight.sum()
    else:
        scale, weight = np.ones(1), np.ones(1)

    def excess(ratio: float) -> float:
        return _ratio_survival(ratio, common_share, scatter_share, scatter_dof, scale, weight) - false_alarm

    low, high = 1e-6, 2.0
    while excess(high) > 0 and high < 1e6:
        low, high = high, high * 2.0
    while high - low > 1e-6 + 1e-7 * high:  # bisection: the tail probability falls as the ratio grows
        middle = (low + high) / 2.0
        low, high = (middle, high) if excess(middle) > 0 else (low, middle)
    return float((low + high) / 2.0)


@dataclass(frozen=True)
class ErrorBudget:
    """Predicted mean-square error (mm^2) per target of each term, and the predicted RMS TRE (mm)."""

    registration_ms: np.ndarray
    tracking_ms: np.ndarray
    reference_ms: np.ndarray
    placement_ms: np.ndarray
    #: The field distortion detected at registration, at targets probed in the same field (None: none detected).
    distortion_ms: np.ndarray | None = None

    @property
    def rms_mm(self) -> np.ndarray:
        distortion = 0.0 if self.distortion_ms is None else self.distortion_ms
        return np.sqrt(self.registration_ms + self.tracking_ms + self.reference_ms + self.placement_ms + distortion)

    def term_rms_mm(self) -> dict[str, np.ndarray]:
        """Each term's own RMS (mm), for a stacked error-budget plot (they add in quadrature)."""
        terms = {"registration": np.sqrt(self.registration_ms), "tracking": np.sqrt(self.tracking_ms),
                 "reference": np.sqrt(self.reference_ms), "placement": np.sqrt(self.placement_ms)}
        if self.distortion_ms is not None:
            terms["distortion"] = np.sqrt(self.distortion_ms)
        return terms


@dataclass(frozen=True)
class RegistrationError:
    """What a registration knows of its own error: the fit's covariance and the probe's per-dwell error.

    ``covariance``: first-order covariance of the fitted ``ReferenceToImage`` (and l);
    ``probe_sigma_mm``: per-axis localisation error of one calibration dwell that the residuals
    reveal (mm); ``probe_sigma_dof``: the residual degrees of freedom it was estimated from
    (``3N - P``; infinite when unknown). Stored in ``registration.json`` under ``error_model``.
    ``distortion``: the field distortion found at registration (a
    :class:`.distortion.estimate.DistortionEstimate`, stored under ``distortion``; None: not tested);
    when detected, the probe's error is the noise that remains beside the fitted field, and the field
    adds its own term to the budget.
    """

    covariance: RegistrationCovariance
    probe_sigma_mm: float
    probe_sigma_dof: float = float("inf")
    distortion: Any = None

    def to_json(self) -> dict:
        def number(value: float) -> float | None:
            return float(value) if np.isfinite(value) else None

        return {"parameter_covariance": [[number(v) for v in row] for row in self.covariance.parameters],
                "parameters": "rotation about centre_image (rad, 3), translation (mm, 3)"
                              + (", l (mm)" if len(self.covariance.parameters) > 6 else ""),
                "centre_image": [float(v) for v in self.covariance.centre_image],
                "probe_sigma_mm": number(self.probe_sigma_mm), "probe_sigma_dof": number(self.probe_sigma_dof)}

    @classmethod
    def from_json(cls, document: dict) -> RegistrationError:
        """Inverse of :meth:`to_json` (null entries are infinite: an undetermined configuration)."""
        parameters = np.array([[np.inf if v is None else float(v) for v in row]
                               for row in document["parameter_covariance"]], dtype=float)
        if parameters.ndim != 2 or parameters.shape[0] != parameters.shape[1] or parameters.shape[0] not in (6, 7):
            raise ValueError("parameter_covariance must be a 6x6 or 7x7 matrix")
        sigma, dof = document.get("probe_sigma_mm"), document.get("probe_sigma_dof")
        return cls(RegistrationCovariance(parameters, np.asarray(document["centre_image"], dtype=float).reshape(3)),
                   float("inf") if sigma is None else float(sigma), float("inf") if dof is None else float(dof))


def registration_error(points_reference: np.ndarray, origins_image: np.ndarray, axes_image: np.ndarray,
                       l_mm: float, l_solved: bool, residuals_mm: np.ndarray,
                       image_sigma_mm: np.ndarray | None = None, distortion: Any = None) -> RegistrationError:
    """The :class:`RegistrationError` of a fit from the paired points it used.

    ``points_reference`` (N, 3): calibration points (Reference, mm); ``origins_image`` and
    ``axes_image`` (N, 3): their markers (CT LPS); ``residuals_mm`` (N,): the fit's residuals;
    ``image_sigma_mm`` (N,): per-axis localisation sigma of each marker point in the CT when known
    (it is then kept out of the probe's error, which is the rest of what the residuals show);
    ``distortion``: the :class:`.distortion.estimate.DistortionEstimate` of these residuals: when it
    detected a field, the probe's error is the noise beside it (``noise_sigma_mm``), not the residuals'.
    """
    fiducials = np.asarray(origins_image, dtype=float) + l_mm * np.asarray(axes_image, dtype=float)
    axes = np.asarray(axes_image, dtype=float) if l_solved else None
    n = len(fiducials)
    image_var = np.zeros(n) if image_sigma_mm is None else np.square(np.asarray(image_sigma_mm, dtype=float))
    dof = float(3 * n - (7 if l_solved else 6))
    if distortion is not None and distortion.detected:
        probe_sigma = float(np.sqrt(max(distortion.noise_sigma_mm**2 - float(np.mean(image_var)), 0.0)))
        dof = float(distortion.noise_dof)
    else:
        probe_sigma = estimate_isotropic_fle(residuals_mm, fiducials, axes, image_var[:, None, None] * np.eye(3))
    covariances = (probe_sigma**2 + image_var)[:, None, None] * np.eye(3)
    return RegistrationError(registration_covariance(fiducials, covariances, axes), probe_sigma,
                             dof if dof > 0 else float("inf"), distortion)


@dataclass(frozen=True)
class ErrorModel:
    """Everything needed to predict the end-to-end TRE at any image point (see the module docstring).

    ``reference_to_image``: the registration (Reference -> CT LPS, mm); ``registration``: its own
    error; ``reference_position_sigma_mm`` / ``reference_rotation_sigma_rad``: the reference
    sensor's per-axis pose error; ``placement_rms_mm``: 3D RMS placement error of the probe on a target.
    """

    reference_to_image: np.ndarray
    registration: RegistrationError
    reference_position_sigma_mm: float
    reference_rotation_sigma_rad: float
    placement_rms_mm: float = 0.0

    @classmethod
    def with_priors(cls, reference_to_image: np.ndarray, registration: RegistrationError,
                    reference_error_mm: float | None = None, reference_error_deg: float | None = None,
                    placement_error_mm: float = 0.0) -> ErrorModel:
        """The model with the reference sensor's pose error given, or by default a quarter of the probe's
        per-dwell error and the rotation that moves a point :data:`REFERENCE_LEVER_MM` away by as much (a
        larger 6-DOF sensor at rest; an assumption, see the module docstring)."""
        position = 0.25 * registration.probe_sigma_mm if reference_error_mm is None else float(reference_error_mm)
        rotation = (position / REFERENCE_LEVER_MM if reference_error_deg is None
                    else float(np.radians(reference_error_deg)))
        return cls(np.asarray(reference_to_image, dtype=float), registration, position, rotation,
                   float(placement_error_mm))

    def budget(self, points_image: np.ndarray, tracking_ms: float | None = None) -> ErrorBudget:
        """The error budget at image points (K, 3) (LPS, mm).

        ``tracking_ms``: the probe's mean-square 3D error per dwell when measured at navigation time
        (:func:`repeated_dwell_ms`); otherwise the calibration's per-dwell error is used.
        """
        points = np.asarray(points_image, dtype=float).reshape(-1, 3)
        registration = np.trace(self.registration.covariance.at(points), axis1=-2, axis2=-1)
        lever_arms = apply_transform(invert_rigid(self.reference_to_image), points)
        reference_one_pose = np.trace(pose_error_covariance(
            lever_arms, self.reference_position_sigma_mm, self.reference_rotation_sigma_rad), axis1=-2, axis2=-1)
        probe_ms = 3 * self.registration.probe_sigma_mm**2 if tracking_ms is None else tracking_ms
        distortion = self.registration.distortion
        return ErrorBudget(registration_ms=registration, tracking_ms=np.full(len(points), probe_ms),
                           reference_ms=2 * reference_one_pose,
                           placement_ms=np.full(len(points), self.placement_rms_mm**2),
                           distortion_ms=distortion.mean_square_at(lever_arms)
                           if distortion is not None and distortion.detected else None)
