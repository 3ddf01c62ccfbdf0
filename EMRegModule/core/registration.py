"""Sensor offset and patient-to-image registration (paper sections 2.4-2.5, Eq. 10-11).

Given the markers detected in the CT (origin and +Y axis of each marker frame, image space)
and the calibrated pinhole points (Reference frame), :func:`register`

1. pairs them automatically (:mod:`EMRegModule.core.pairing`; refuses when ambiguous);
2. solves the probe sensor's depth l in [a, b] by minimising FRE(l) (paper Eq. 10): the
   image pinhole points are ``q_j(l) = origin_j + l * axis_j`` and for each l the least-squares
   rigid fit of the calibration points onto them gives FRE(l)
   (:func:`EMRegModule.core.sensor_offset.fre_curve`); a 0.1 mm grid then a bounded scalar
   minimisation find the minimum (:func:`EMRegModule.core.sensor_offset.solve_sensor_offset`);
3. reports how well l is determined: its standard error from the curvature of the residual
   sum of squares at the minimum, ``std(l) = sqrt(2 sigma^2 / SSE''(l))`` with sigma^2 the
   per-coordinate noise variance estimated from the residuals. When the marker axes are
   (nearly) parallel, a change of l is (nearly) a translation that the fit absorbs, the
   curvature vanishes and so does the information about l: above ``warn_l_std_mm`` the
   result carries a warning, above ``max_l_std_mm`` it is refused (the translation along the
   axes would be unknown by that much) unless l is given in ``[registration] sensor_offset_l_mm``;
4. tests the residuals for field distortion (spatially coherent, beyond noise:
   :mod:`EMRegModule.core.distortion`); refuses one above ``max_distortion_mm`` (RMS of the fitted
   non-rigid field at the pinholes), warns below, and the error model then carries it;
5. returns ``ReferenceToImage`` with FRE overall and per pair, flagged outliers (residual
   above ``outlier_factor`` times the robust RMS residual and above ``outlier_min_mm``), the
   FLE estimated from the FRE (``FLE^2 = FRE^2 N / (N - 2)``) and the predicted TRE at the
   targets (Fitzpatrick, West & Maurer), plus FRE(l) samples for the report's plot. The
   predicted TRE is the registration's own contribution; an error measured at a target with
   the tracked probe adds the probe's localisation error during navigation.

FRE above ``max_fre_mm`` raises :class:`NoSafeAnswerError`: nothing is written.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from ..marker_model import MarkerModel
from ..names import REFERENCE_TO_IMAGE_H5
from ..settings import RegistrationSettings, Settings
from .calibration import CalibrationPoint, FrameCalibration
from .distortion import SUSPECT_LEVEL, DistortionEstimate, NoisePrior, estimate_distortion, fit_field, size_words
from .error_model import RegistrationError, registration_error
from .probe_axis import pair_with_probe_axis
from .sensor_offset import OffsetSolution, solve_sensor_offset
from .transforms import apply_rotation, apply_transform, check_rigid, invert_rigid, residuals

#: Median of a chi-squared variable with 3 degrees of freedom (robust RMS of 3D residuals).
_CHI2_3_MEDIAN = 2.3660

if TYPE_CHECKING:
    from ..settings import PairingSettings
    from .pairing import PairingResult


@dataclass
class RegistrationResult:
    """``ReferenceToImage`` (4x4, mm, Reference -> CT LPS) and everything that qualifies it.

    ``pairs``: dicts ``image_marker``, ``calibration_point``, ``residual_mm``, ``outlier``;
    ``fre_curve``: (l values, FRE values) in mm; ``predicted_tre_mm``: the registration's own
    RMS error at each target (or None; the end-to-end prediction adds tracking, the reference
    sensor and placement: :mod:`EMRegModule.core.error_model`); ``error``: what the fit knows of its error.
    """

    reference_to_image: np.ndarray
    sensor_offset_l_mm: float
    fre_mm: float
    pairs: list[dict[str, Any]]
    unpaired_image_markers: list[str] = field(default_factory=list)
    unpaired_calibration_points: list[str] = field(default_factory=list)
    sensor_offset_l_std_mm: float = float("nan")
    sensor_offset_range_mm: tuple[float, float] = (float("nan"), float("nan"))
    sensor_offset_fixed: bool = False
    fle_mm: float = float("nan")
    fre_curve: tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros(0), np.zeros(0)))
    targets_image: np.ndarray | None = None
    predicted_tre_mm: np.ndarray | None = None
    error: RegistrationError | None = None
    warnings: list[str] = field(default_factory=list)
    pairing: dict[str, Any] = field(default_factory=dict)
    probe_axis: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] | None = None  # what it was made from (``EMRegModule.io.provenance``)
    #: The tracker ports of the calibration the registration was made from (None: an older file without them).
    reference_sensor: int | None = None
    probe_sensor: int | None = None
    #: Registered onto fiducial points (``emreg register --fiducials``): where they came from, the points (mm, the
    #: fiducials' frame) and how the calibration points were taken (:mod:`EMRegModule.core.fiducial_registration`);
    #: None for the CT markers' pinhole route.
    fiducials: dict[str, Any] | None = None

    @property
    def point_fit(self) -> bool:
        """True for a plain rigid point fit onto fiducials (no sensor offset l: ``sensor_offset_l_mm`` is 0)."""
        return self.fiducials is not None

    @property
    def outliers(self) -> list[str]:
        """Image marker ids of the pairs flagged as outliers."""
        return [p["image_marker"] for p in self.pairs if p.get("outlier")]

    def to_json(self) -> dict[str, Any]:
        """The ``registration.json`` document: the spec's keys first, then extra ones."""
        document: dict[str, Any] = {
            "ReferenceToImage": np.asarray(self.reference_to_image).tolist(),
            "sensor_offset_l_mm": round(float(self.sensor_offset_l_mm), 4),
            "fre_mm": round(float(self.fre_mm), 4),
            "pairs": [{**p, "residual_mm": round(float(p["residual_mm"]), 4)} for p in self.pairs],
            "unpaired_image_markers": list(self.unpaired_image_markers),
            "unpaired_calibration_points": list(self.unpaired_calibration_points),
            **({"reference_sensor": int(self.reference_sensor)} if self.reference_sensor is not None else {}),
            **({"probe_sensor": int(self.probe_sensor)} if self.probe_sensor is not None else {}),
            "transform_file": REFERENCE_TO_IMAGE_H5,
            "transform_file_note": ("ITK file: stores ImageToReference (the resampling direction, LPS); "
                                    "3D Slicer loads it as the ReferenceToImage linear transform"),
            "sensor_offset_l_std_mm": _round(self.sensor_offset_l_std_mm),
            "sensor_offset_range_mm": [float(v) for v in self.sensor_offset_range_mm],
            "sensor_offset_fixed": bool(self.sensor_offset_fixed),
            "fle_mm": _round(self.fle_mm),
            "outliers": self.outliers,
            "fre_curve": {"l_mm": [round(float(v), 4) for v in self.fre_curve[0]],
                          "fre_mm": [round(float(v), 5) for v in self.fre_curve[1]]},
            "warnings": list(self.warnings),
            "pairing": self.pairing,
            "probe_axis": self.probe_axis,
        }
        if self.targets_image is not None and self.predicted_tre_mm is not None:
            document["targets_image"] = np.asarray(self.targets_image).tolist()
            document["predicted_registration_tre_mm"] = [_round(v) for v in self.predicted_tre_mm]
        if self.error is not None:
            document["error_model"] = self.error.to_json()
            if self.error.distortion is not None:
                document["distortion"] = self.error.distortion.to_json()
                document["prediction_trust"] = self.error.distortion.prediction_trust()
        if self.fiducials is not None:
            document["fiducials"] = self.fiducials
        if self.provenance is not None:
            document["provenance"] = self.provenance
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any], source: str = "registration") -> RegistrationResult:
        try:
            matrix = np.asarray(document["ReferenceToImage"], dtype=float)
            if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
                raise EMRegError(f"{source}: ReferenceToImage must be a 4x4 matrix of finite numbers")
            check_rigid(matrix, f"{source}: ReferenceToImage")
            point_fit = document.get("fiducials") is not None  # a point fit onto fiducials: no offset, l = 0
            for key in ("sensor_offset_l_mm", "fre_mm"):
                if not np.isfinite(float(document[key])):
                    raise EMRegError(f"{source}: {key} is not a finite number")
                if float(document[key]) < 0 or (key == "sensor_offset_l_mm" and float(document[key]) == 0
                                                and not point_fit):
                    raise EMRegError(f"{source}: {key} = {float(document[key]):g} is not a possible value "
                                     f"({'an FRE is never negative' if key == 'fre_mm' else 'l must be positive'}): "
                                     "a damaged or hand-edited file")
            for key in ("fle_mm", "sensor_offset_l_std_mm"):
                if _float(document.get(key)) < 0:
                    raise EMRegError(f"{source}: {key} = {_float(document.get(key)):g} is negative: a damaged or "
                                     "hand-edited file")
            curve = document.get("fre_curve") or {}
            targets = document.get("targets_image")
            tre = document.get("predicted_registration_tre_mm", document.get("predicted_tre_mm"))
            error = document.get("error_model")
            return cls(
                reference_to_image=matrix,
                sensor_offset_l_mm=float(document["sensor_offset_l_mm"]),
                fre_mm=float(document["fre_mm"]),
                pairs=[dict(p) for p in document.get("pairs", [])],
                unpaired_image_markers=[str(v) for v in document.get("unpaired_image_markers", [])],
                unpaired_calibration_points=[str(v) for v in document.get("unpaired_calibration_points", [])],
                sensor_offset_l_std_mm=_float(document.get("sensor_offset_l_std_mm")),
                sensor_offset_range_mm=tuple(_float(v) for v in document.get("sensor_offset_range_mm",
                                                                            [None, None])),
                sensor_offset_fixed=bool(document.get("sensor_offset_fixed", False)),
                fle_mm=_float(document.get("fle_mm")),
                fre_curve=(np.asarray(curve.get("l_mm", []), dtype=float),
                           np.asarray(curve.get("fre_mm", []), dtype=float)),
                targets_image=None if targets is None else np.asarray(targets, dtype=float).reshape(-1, 3),
                predicted_tre_mm=None if tre is None else np.array([_float(v) for v in tre]),
                error=None if error is None else _with_distortion(RegistrationError.from_json(error),
                                                                  document.get("distortion")),
                warnings=[str(w) for w in document.get("warnings", [])],
                pairing=dict(document.get("pairing", {})),
                probe_axis=dict(document.get("probe_axis") or {}),
                provenance=document["provenance"] if isinstance(document.get("provenance"), dict) else None,
                reference_sensor=_port(document, "reference_sensor", source),
                probe_sensor=_port(document, "probe_sensor", source),
                fiducials=document["fiducials"] if isinstance(document.get("fiducials"), dict) else None,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise EMRegError(f"{source}: not a registration file ({exc!s:.100})") from None


def _with_distortion(error: RegistrationError, document: Any) -> RegistrationError:
    """The error model with the ``distortion`` block it was made with (absent in older files)."""
    if not isinstance(document, Mapping):
        return error
    return dataclasses.replace(error, distortion=DistortionEstimate.from_json(document))


def _port(document: Mapping[str, Any], key: str, source: str) -> int | None:
    """A recorded tracker port (1..4), or None when the file predates the key."""
    value = document.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 4:
        raise EMRegError(f"{source}: {key} must be a tracker port 1..4, got {value!r:.30}")
    return value


def _round(value: float, digits: int = 4) -> float | None:
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def _float(value: Any) -> float:
    return float("nan") if value is None else float(value)


# --- image markers ---------------------------------------------------------------------------


def _image_markers(detection: Any) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Ids, origins (M, 3) and unit axes (M, 3) from a DetectionResult (or a list of markers)."""
    markers = getattr(detection, "markers", detection)
    ids, origins, axes = [], [], []
    for k, marker in enumerate(markers):
        get = marker.get if isinstance(marker, Mapping) else lambda name, m=marker: getattr(m, name)
        ids.append(str(get("id") or f"I{k + 1:02d}"))
        origins.append(np.asarray(get("origin"), dtype=float))
        axes.append(np.asarray(get("axis"), dtype=float))
    origins_array = np.asarray(origins, dtype=float).reshape(-1, 3)
    axes_array = np.asarray(axes, dtype=float).reshape(-1, 3)
    norms = np.linalg.norm(axes_array, axis=1)
    if np.any(~np.isfinite(norms)) or np.any(norms < 1e-9) or not np.all(np.isfinite(origins_array)):
        raise EMRegError("detected markers: every marker needs a finite origin and a non-zero axis")
    return ids, origins_array, axes_array / norms[:, None]


# --- registration ----------------------------------------------------------------------------


def register(
    detection: Any,
    frame_calibration: FrameCalibration,
    model: MarkerModel,
    settings: RegistrationSettings | None = None,
    targets_image: np.ndarray | None = None,
    probe_axis: str | None = None,
) -> RegistrationResult:
    """Pair, solve the sensor offset l and fit ``ReferenceToImage`` (Reference -> CT LPS, mm).

    ``probe_axis``: ``[sensors] probe_axis`` (None: the setting the calibration was made with);
    the probe directions help the pairing when they fit, and never make it refuse
    (:func:`EMRegModule.core.probe_axis.pair_with_probe_axis`).

    ``detection``: a DetectionResult (markers with ``id``, ``origin``, ``axis`` in image space);
    ``frame_calibration``: pinhole points in the Reference frame; ``model``: gives l's range
    [a, b]; ``settings``: the ``[registration]`` table; ``targets_image`` (K, 3, LPS mm):
    targets for the predicted TRE. Raises :class:`NoSafeAnswerError` for an ambiguous pairing,
    too few pairs, FRE above ``max_fre_mm`` or a poorly determined l.
    """
    config = settings or RegistrationSettings()
    image_ids, origins, axes = _image_markers(detection)
    labels = frame_calibration.labels
    points = frame_calibration.positions
    fixed = config.sensor_offset_l_mm is not None
    l_range = _offset_range(config, model)
    stored = frame_calibration.direction_convention
    pairing, axis_report = pair_with_probe_axis(
        origins, axes, points, frame_calibration.directions, l_range, config.pairing,
        setting=frame_calibration.probe_axis if probe_axis is None else probe_axis,
        stored_convention=stored if stored in ("+x_in", "+x_out") else "+x_in")
    image_index = np.array([j for j, _ in pairing.pairs])
    cal_index = np.array([i for _, i in pairing.pairs])
    warnings: list[str] = list(axis_report.warnings)

    fit = fit_pairs(points[cal_index], origins[image_index], axes[image_index], l_range, config)
    solution, pair_residuals, outlier, used = fit.solution, fit.residuals_mm, fit.outlier, fit.used
    warnings += fit.warnings
    if np.any(outlier):
        names = ", ".join(f"{image_ids[j]}/{labels[i]} ({r:.2f} mm)"
                          for j, i, r, o in zip(image_index, cal_index, pair_residuals, outlier, strict=True) if o)
        warnings.append(f"outlier pair(s): {names}")
    fre_value = float(np.sqrt(np.mean(pair_residuals[used] ** 2)))
    warnings += _check_fre_and_offset(fre_value, solution, l_range, config)
    if fixed:
        warnings += _check_fixed_offset(points[cal_index[used]], origins[image_index[used]], axes[image_index[used]],
                                        solution.l_mm, model)
    n_used = int(np.count_nonzero(used))
    fle = fre_value * np.sqrt(n_used / (n_used - 2)) if n_used > 2 else float("nan")
    paired_images = set(image_index.tolist())
    paired_cal = set(cal_index.tolist())
    near_cal, near_images = near_pinholes(solution, points, origins, axes, paired_cal, paired_images,
                                          UNPAIRED_TESTED_FACTOR * config.pairing.point_tolerance_mm)
    tested_cal = np.concatenate([cal_index[used], near_cal]).astype(int)
    tested_images = np.concatenate([image_index[used], near_images]).astype(int)
    unpaired = np.array(sorted(set(range(len(labels))) - paired_cal - set(near_cal.tolist())), dtype=int)
    distortion = distortion_of_fit(solution, points[tested_cal], origins[tested_images], axes[tested_images], fixed,
                                   config, [frame_calibration.points[i] for i in tested_cal],
                                   [image_ids[j] for j in tested_images], points[unpaired], n_used)
    warnings += check_distortion(distortion, config)
    error = registration_error(points[cal_index[used]], origins[image_index[used]], axes[image_index[used]],
                               solution.l_mm, not fixed, pair_residuals[used], distortion=distortion)
    targets, predicted = predicted_registration_tre(error, targets_image)

    pairs = [
        {"image_marker": image_ids[j], "calibration_point": labels[i], "residual_mm": float(r), "outlier": bool(o)}
        for j, i, r, o in zip(image_index, cal_index, pair_residuals, outlier, strict=True)
    ]
    moved = _moved_by_field(distortion, solution, points, labels, paired_cal, origins, axes, image_ids,
                            paired_images, config.pairing.point_tolerance_mm, n_used)
    warnings += _unpaired_warnings([m for k, m in enumerate(image_ids) if k not in paired_images],
                                   [p for k, p in enumerate(labels) if k not in paired_cal and p not in moved],
                                   distortion, noise_beyond_tolerance(distortion, len(labels),
                                                                      config.pairing.point_tolerance_mm))
    warnings += list(moved.values())
    warnings += _distortion_evidence(distortion, solution, points, labels, paired_cal, origins, axes, image_ids,
                                     paired_images)
    return RegistrationResult(
        reference_to_image=solution.reference_to_image,
        sensor_offset_l_mm=solution.l_mm,
        fre_mm=fre_value,
        pairs=pairs,
        unpaired_image_markers=[m for k, m in enumerate(image_ids) if k not in paired_images],
        unpaired_calibration_points=[p for k, p in enumerate(labels) if k not in paired_cal],
        sensor_offset_l_std_mm=0.0 if fixed else solution.l_std_mm,
        sensor_offset_range_mm=(model.pinhole_bottom_mm, model.pinhole_top_mm),
        sensor_offset_fixed=fixed,
        fle_mm=fle,
        fre_curve=(solution.curve_l_mm, solution.curve_fre_mm),
        targets_image=targets,
        predicted_tre_mm=predicted,
        error=error,
        warnings=warnings + list(frame_calibration.warnings),
        pairing=pairing_record(pairing, config.pairing),
        probe_axis=axis_report.to_json(),
        reference_sensor=calibration_port(frame_calibration, "reference_sensor"),
        probe_sensor=calibration_port(frame_calibration, "probe_sensor"),
    )


def predicted_registration_tre(error: RegistrationError, targets_image: np.ndarray | None
                               ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The targets (K, 3, image space mm) and the registration's own RMS error at each (mm), or (None, None)."""
    if targets_image is None or not len(np.atleast_2d(targets_image)):
        return None, None
    targets = np.asarray(targets_image, dtype=float).reshape(-1, 3)
    return targets, np.sqrt(np.trace(error.covariance.at(targets), axis1=-2, axis2=-1))


def pairing_record(pairing: PairingResult, settings: PairingSettings) -> dict[str, Any]:
    """The ``pairing`` block of ``registration.json``: how well the pairing was supported, and its tolerances."""
    return {"support": pairing.support, "rival_support": pairing.rival_support,
            "hypotheses": pairing.hypotheses, "seed_triangles": pairing.seeds,
            "ambiguity_margin": settings.ambiguity_margin,
            "point_tolerance_mm": round(settings.point_tolerance_mm, 3),
            "distance_tolerance_mm": round(settings.distance_tolerance_mm, 3)}


#: The expected number of calibration points the tracker's noise alone puts beyond the pairing tolerance from which
#: an unpaired point is put down to that noise rather than to the user.
NOISE_EXPLAINS_UNPAIRED = 0.5


def _unpaired_warnings(image_markers: list[str], calibration_points: list[str],
                       distortion: DistortionEstimate | None = None,
                       noise_beyond: tuple[float, float, float] | None = None) -> list[str]:
    """One line per kind of point left out of the registration, naming them and the likely reason (a detected
    field distortion first: it moves points off their pinholes, and the user is not blamed for it; then the
    tracker's own noise when it alone puts points beyond the pairing tolerance, ``noise_beyond``:
    :func:`noise_beyond_tolerance`; then, for points that joined the distortion test because they lie near a CT
    pinhole no pair took, a field too local for the test or a probe not fully in: the user is blamed only for points
    near no free pinhole)."""
    lines = []
    if calibration_points and distortion is not None and distortion.detected:
        largest, _ = distortion.largest()
        lines.append(f"calibration point(s) {', '.join(calibration_points)} paired with no marker of the CT, left "
                     f"out of the registration: the field distortion detected here (up to {largest:.1f} mm at the "
                     f"paired pinholes, largest near {distortion.where()}) may have moved them beyond the pairing "
                     "tolerance; remove metal from near the frame and transmitter and calibrate again (or that "
                     "marker was not found in the CT: see 'rejected' in markers.json)")
    elif calibration_points and _suspected(distortion):
        lines.append(f"calibration point(s) {', '.join(calibration_points)} paired with no marker of the CT, left "
                     "out of the registration: the paired pinholes' residuals are more coherent than noise "
                     f"(p = {distortion.p_value:.2g}, below the distortion test's false-alarm rate only at "
                     f"{SUSPECT_LEVEL:g}): a field distortion may have moved them beyond the pairing tolerance; remove "
                     "metal from near the frame and transmitter and calibrate again (or the probe was not in the "
                     "pinhole, or that marker was not found in the CT: see 'rejected' in markers.json)")
    elif calibration_points and noise_beyond is not None:
        lines.append(f"calibration point(s) {', '.join(calibration_points)} paired with no marker of the CT, left "
                     f"out of the registration: the tracker's noise at this calibration ({noise_beyond[0]:.2f} mm per "
                     f"axis per dwell, from the dwells' spread) puts about {noise_beyond[1]:.1f} of the points beyond "
                     f"the pairing tolerance ({noise_beyond[2]:.2f} mm) by itself: it may have moved them there "
                     "(or the probe was not in the pinhole, or that marker was not found in the CT: see 'rejected' "
                     "in markers.json)")
    elif calibration_points:
        near = [p for p in calibration_points if distortion is not None and p in distortion.tested_unpaired]
        far = [p for p in calibration_points if p not in near]
        if near:
            lines.append(f"calibration point(s) {', '.join(near)} paired with no marker of the CT, left out of the "
                         "registration, though each lies within twice the pairing tolerance of a CT pinhole no other "
                         "point took: a field distortion too local for the test to find, or the probe not fully in "
                         "its pinhole, moved it there; check with the probe in that pinhole, or calibrate again with "
                         "metal kept away")
        if far:
            lines.append(f"calibration point(s) {', '.join(far)} paired with no marker of the CT, left out of the "
                         "registration: the probe was likely not in a pinhole while recorded there, or that marker "
                         "was not found in the CT (see 'rejected' in markers.json)")
    if image_markers and calibration_points and distortion is not None and distortion.detected:
        lines.append(f"CT marker(s) {', '.join(image_markers)} paired with no calibration point, left out of the "
                     "registration: the field distortion may have moved their calibration points out of pairing "
                     "(or their pinholes were not recorded in the calibration)")
    elif image_markers and calibration_points and _suspected(distortion):
        lines.append(f"CT marker(s) {', '.join(image_markers)} paired with no calibration point, left out of the "
                     "registration: a field distortion, suspected from the paired pinholes' residuals, may have moved "
                     "their calibration points out of pairing (or their pinholes were not recorded)")
    elif image_markers and calibration_points and noise_beyond is not None:
        lines.append(f"CT marker(s) {', '.join(image_markers)} paired with no calibration point, left out of the "
                     "registration: the tracker's noise may have moved their calibration points out of pairing (or "
                     "their pinholes were not recorded)")
    elif image_markers and distortion is not None and set(calibration_points) & set(distortion.tested_unpaired):
        lines.append(f"CT marker(s) {', '.join(image_markers)} paired with no calibration point, left out of the "
                     "registration: calibration points lie near some of them beyond the pairing tolerance (above), "
                     "moved there by a local field distortion or a probe not fully in its pinhole (or a pinhole was "
                     "not recorded)")
    elif image_markers:
        lines.append(f"CT marker(s) {', '.join(image_markers)} paired with no calibration point, left out of the "
                     "registration: their pinholes were likely not recorded in the calibration (or their dwells "
                     "not found)")
    return lines


def noise_beyond_tolerance(distortion: DistortionEstimate, points: int, tolerance_mm: float
                           ) -> tuple[float, float, float] | None:
    """When the tracker's noise known from the dwells (per axis, mm) is enough by itself to put at least
    :data:`NOISE_EXPLAINS_UNPAIRED` of ``points`` calibration points beyond the pairing tolerance (a 3D Gaussian's
    chance of a distance above it): (that noise, the expected number beyond, the tolerance); None otherwise or
    without a noise prior."""
    from scipy.special import gammaincc

    sigma = distortion.noise_prior_sigma_mm
    if not sigma > 0:
        return None
    expected = points * float(gammaincc(1.5, (tolerance_mm / sigma) ** 2 / 2.0))
    return (sigma, expected, tolerance_mm) if expected >= NOISE_EXPLAINS_UNPAIRED else None


def _suspected(distortion: DistortionEstimate | None) -> bool:
    """A distortion not detected but suspected: the residuals more coherent than noise at :data:`SUSPECT_LEVEL`."""
    return distortion is not None and distortion.tested and not distortion.detected \
        and distortion.p_value <= SUSPECT_LEVEL


def _distortion_evidence(distortion: DistortionEstimate, solution: OffsetSolution, points_reference: np.ndarray,
                         labels: list[str], paired_cal: set[int], origins_image: np.ndarray, axes_image: np.ndarray,
                         image_ids: list[str], paired_images: set[int]) -> list[str]:
    """For each unpaired calibration point, when a distortion was detected: how far it lies from the nearest
    unpaired CT pinhole (at the solved l), with and without the fitted field taken off (Reference frame, mm)."""
    unpaired_cal = [k for k in range(len(labels)) if k not in paired_cal]
    unpaired_images = [k for k in range(len(image_ids)) if k not in paired_images]
    if not distortion.detected or not unpaired_cal or not unpaired_images:
        return []
    pinholes = apply_transform(invert_rigid(solution.reference_to_image),
                               origins_image[unpaired_images] + solution.l_mm * axes_image[unpaired_images])
    measured = points_reference[unpaired_cal]
    corrected = measured - distortion.field_at(measured)
    lines = []
    for k, before, after in zip(unpaired_cal, measured, corrected, strict=True):
        gaps = np.linalg.norm(pinholes - before, axis=1)
        nearest = int(np.argmin(gaps))
        lines.append(f"{labels[k]}: {gaps[nearest]:.1f} mm from CT marker {image_ids[unpaired_images[nearest]]}'s "
                     f"pinhole as measured, {np.linalg.norm(pinholes[nearest] - after):.1f} mm once the fitted field "
                     "distortion is taken off")
    return lines


def _moved_by_field(distortion: DistortionEstimate, solution: OffsetSolution, points_reference: np.ndarray,
                    labels: list[str], paired_cal: set[int], origins_image: np.ndarray, axes_image: np.ndarray,
                    image_ids: list[str], paired_images: set[int], tolerance_mm: float,
                    paired_tested: int) -> dict[str, str]:
    """Before an unpaired calibration point is put down to the user: when no distortion was detected, whether the
    smooth field fitted to the paired pinholes anyway (:func:`.distortion.detect.fit_field`) explains where it
    lies, i.e. takes it to within ``tolerance_mm`` of an unpaired CT pinhole it was farther from (the field fitted to
    the test's first ``paired_tested`` points, the pairs the fit used). Returns, per such point's label, a line naming
    the distortion, how much and where (Reference frame, mm)."""
    unpaired_cal = [k for k in range(len(labels)) if k not in paired_cal]
    unpaired_images = [k for k in range(len(image_ids)) if k not in paired_images]
    if distortion.detected or not unpaired_cal or not unpaired_images or distortion.model is not None:
        return {}
    # the test's first ``paired_tested`` points are the pairs the fit used; unpaired ones near a pinhole follow
    field = fit_field(distortion.points_mm[:paired_tested], distortion.residuals_mm[:paired_tested], None, None)
    if field is None:
        return {}
    pinholes = apply_transform(invert_rigid(solution.reference_to_image),
                               origins_image[unpaired_images] + solution.l_mm * axes_image[unpaired_images])
    lines = {}
    for k in unpaired_cal:
        measured = points_reference[k]
        shift = field.field_at(measured[None])[0]
        gaps = np.linalg.norm(pinholes - measured, axis=1)
        nearest = int(np.argmin(np.linalg.norm(pinholes - (measured - shift), axis=1)))
        after = float(np.linalg.norm(pinholes[nearest] - (measured - shift)))
        if after <= tolerance_mm < gaps[nearest]:
            lines[labels[k]] = (
                f"calibration point {labels[k]} paired with no marker of the CT: a smooth field distortion fitted to "
                f"the paired pinholes (not significant there alone) explains where it lies: it moved it "
                f"{np.linalg.norm(shift):.1f} mm, {gaps[nearest]:.1f} mm from CT marker "
                f"{image_ids[unpaired_images[nearest]]}'s pinhole as measured, {after:.1f} mm once the field is taken "
                "off; remove metal from near the frame and transmitter and calibrate again")
    return lines


#: Calibration points left unpaired within this many pairing tolerances of an unpaired CT pinhole (at the fit) join
#: the distortion test, not the fit: a field concentrated near a few pinholes moves them beyond the pairing
#: tolerance, and the paired ones alone show little of it (issue 37).
UNPAIRED_TESTED_FACTOR = 2.0


def near_pinholes(solution: OffsetSolution, points_reference: np.ndarray, origins_image: np.ndarray,
                  axes_image: np.ndarray, paired_cal: set[int], paired_images: set[int], limit_mm: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unpaired calibration points (indices into ``points_reference``) each matched to the nearest unpaired CT
    pinhole at the fit (indices into ``origins_image``), nearest pairs first, each point and pinhole once, where that
    gap is below ``limit_mm`` (Reference frame, mm): points the pairing left out but that lie near a pinhole no
    other point took, for the distortion test (never for the fit)."""
    cal = [k for k in range(len(points_reference)) if k not in paired_cal]
    images = [j for j in range(len(origins_image)) if j not in paired_images]
    if not cal or not images:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    pinholes = apply_transform(invert_rigid(solution.reference_to_image),
                               origins_image[images] + solution.l_mm * axes_image[images])
    gaps = np.linalg.norm(points_reference[cal][:, None, :] - pinholes[None], axis=2)
    chosen_cal, chosen_images = [], []
    for flat in np.argsort(gaps, axis=None):
        a, b = np.unravel_index(flat, gaps.shape)
        if gaps[a, b] >= limit_mm:
            break
        if cal[a] not in chosen_cal and images[b] not in chosen_images:
            chosen_cal.append(cal[a])
            chosen_images.append(images[b])
    return np.array(chosen_cal, dtype=int), np.array(chosen_images, dtype=int)


def distortion_of_fit(solution: OffsetSolution, points_reference: np.ndarray, origins_image: np.ndarray,
                      axes_image: np.ndarray, fixed: bool, config: RegistrationSettings,
                      calibration_points: list[CalibrationPoint], image_markers: list[str],
                      unpaired_reference: np.ndarray | None = None, fitted_count: int | None = None
                      ) -> DistortionEstimate:
    """The distortion test on the fit's residual vectors, taken into the Reference frame (measured point minus
    the registered CT pinhole; :func:`.distortion.detect.estimate_distortion`), with the transmitter's pose
    at each point when the calibration kept it, and the calibration points the pairing left out
    (``unpaired_reference``, (K, 3) Reference mm); the first ``fitted_count`` points are the pairs the fit used, the
    others unpaired points near a free pinhole that only join the test (None: all pairs). It carries
    ``[registration] max_undetectable_distortion_mm``."""
    image_to_reference = invert_rigid(solution.reference_to_image)
    pinholes_reference = apply_transform(image_to_reference, origins_image + solution.l_mm * axes_image)
    axes_reference = None if fixed else apply_rotation(image_to_reference, axes_image)
    poses = [p.tracker_to_reference for p in calibration_points]
    estimate = estimate_distortion(points_reference, points_reference - pinholes_reference, axes_reference,
                                   config.distortion_false_alarm, [p.label for p in calibration_points],
                                   image_markers, None if any(p is None for p in poses) else np.asarray(poses),
                                   dwell_noise(calibration_points, config.dwell_error_ratio), config.max_fre_mm,
                                   unpaired_reference, fitted_count)
    return replace(estimate, undetectable_limit_mm=config.max_undetectable_distortion_mm)


def dwell_noise(calibration_points: list[CalibrationPoint], ratio: float) -> NoisePrior | None:
    """The probe's per-dwell error (per axis, mm) from evidence apart from the fit's residuals: ``ratio``
    (``[registration] dwell_error_ratio``) times the within-dwell spread of the calibration samples (RMS of the
    points' ``std_mm`` over the three axes). None when a point's spread is unknown (an older calibration file) or
    was taken with a tool (a pivoting or resting stylus: the tip calibration's error is common to a dwell's samples
    and does not show in their spread)."""
    spreads = np.array([p.std_mm for p in calibration_points], dtype=float)
    if any(p.motion for p in calibration_points):
        return None
    if not len(spreads) or not np.all(np.isfinite(spreads)) or not np.any(spreads > 0):
        return None
    spread = float(np.sqrt(np.mean(spreads**2) / 3.0))
    return NoisePrior(ratio * spread, f"{ratio:g} x the calibration dwells' spread of {spread:.3f} mm per axis")


def check_distortion(distortion: DistortionEstimate, config: RegistrationSettings) -> list[str]:
    """Refuse (:class:`NoSafeAnswerError`) a detected distortion above ``max_distortion_mm`` (RMS at the
    pinholes), and residuals beyond ``max_fle_ratio`` times the tracker's own noise (:func:`check_fle`); below, a
    warning saying where and how much."""
    check_fle(distortion, config)
    if not distortion.detected:
        return check_detectable(distortion, config)
    largest, _ = distortion.largest()
    size = (f"{distortion.rms_mm:.2f} mm RMS at the pinholes beyond the rigid fit, up to {largest:.2f} mm near "
            f"{distortion.where()} (p = {distortion.p_value:.2g})")
    if distortion.rms_mm > config.max_distortion_mm:
        raise NoSafeAnswerError(
            f"the EM field is distorted: {size}, above the limit of {config.max_distortion_mm:g} mm "
            "([registration] max_distortion_mm); move metal (C-arm, table rails, instrument trays) away from the "
            "frame and the transmitter and calibrate again")
    return [f"field distortion detected: {size}; metal near the frame or the transmitter? The predicted TRE and "
            "tre_map.nrrd include it for navigation in this same field"]


def check_fle(distortion: DistortionEstimate, config: RegistrationSettings) -> None:
    """Refuse (:class:`NoSafeAnswerError`) residuals whose per-dwell error, beside any fitted field, is above
    ``[registration] max_fle_ratio`` times the one known apart from them
    (:attr:`.distortion.estimate.DistortionEstimate.fle_ratio`): no predicted TRE explains them."""
    ratio = distortion.fle_ratio
    if np.isfinite(ratio) and ratio > config.max_fle_ratio:
        beside = " beside the field distortion detected" if distortion.detected else ""
        raise NoSafeAnswerError(
            f"the calibration residuals{beside} show a per-dwell error {ratio:.1f} times what the tracker's own "
            f"noise explains ({distortion.noise_prior_source}), above the limit of {config.max_fle_ratio:g} "
            "([registration] max_fle_ratio): no predicted error can be trusted; check that the probe sits in each "
            "pinhole, that nothing metal is near, and calibrate again")


def check_detectable(distortion: DistortionEstimate, config: RegistrationSettings) -> list[str]:
    """A warning (or, with ``[registration] refuse_undetectable_distortion``, a refusal: :class:`NoSafeAnswerError`)
    for a registration whose distortion test found nothing but could have missed a field of
    ``[registration] max_undetectable_distortion_mm`` (its
    :attr:`.distortion.estimate.DistortionEstimate.detectable_rms_mm` above it): with this much tracking
    noise, or this few pinholes, "no distortion found" does not mean "no distortion"."""
    if not distortion.undetectable:  # its limit is config.max_undetectable_distortion_mm (distortion_of_fit)
        return []
    size = distortion.detectable_rms_mm
    words = (f"with this tracking noise (about {distortion.noise_sigma_mm:.2f} mm per axis per dwell) and "
             f"{len(distortion.labels) + len(distortion.tested_unpaired)} pinholes, the distortion test could miss a "
             f"field of {size_words(size)} RMS at the pinholes, above the limit of "
             f"{config.max_undetectable_distortion_mm:g} mm ([registration] max_undetectable_distortion_mm)")
    if config.refuse_undetectable_distortion:
        raise NoSafeAnswerError(f"{words}; more pinholes, the probe held stiller in each, or the transmitter nearer "
                                "the frame let it see smaller fields: calibrate again")
    return [f"{words}: the predicted TRE does not include such a field; check the registration at a known point "
            "before relying on it (more pinholes, the probe held stiller, or the transmitter nearer the frame let the "
            "test see smaller fields)"]


def calibration_port(frame_calibration: FrameCalibration, key: str) -> int | None:
    """The tracker port (``reference_sensor`` or ``probe_sensor``) the calibration was recorded on (None: unknown)."""
    value = getattr(frame_calibration, key, None)
    return int(value) if value is not None else None


def _offset_range(config: RegistrationSettings, model: MarkerModel) -> tuple[float, float]:
    """The range [a, b] (mm) of the sensor offset l: the pinhole's, or the given l (checked to lie in it)."""
    if config.sensor_offset_l_mm is None:
        return (model.pinhole_bottom_mm, model.pinhole_top_mm)
    if not model.pinhole_bottom_mm <= config.sensor_offset_l_mm <= model.pinhole_top_mm:
        raise EMRegError(f"[registration] sensor_offset_l_mm = {config.sensor_offset_l_mm:g} lies "
                         f"outside the marker's pinhole {model.pinhole_bottom_mm:g}..{model.pinhole_top_mm:g} mm: "
                         "the probe sensor cannot sit there")
    return (config.sensor_offset_l_mm, config.sensor_offset_l_mm)


@dataclass
class PairFit:
    """The sensor offset solved on the paired points, the residual of every pair (mm), which pairs
    are outliers and which were used in the fit, and the warnings of the fit."""

    solution: OffsetSolution
    residuals_mm: np.ndarray
    outlier: np.ndarray
    used: np.ndarray
    warnings: list[str]


def fit_pairs(points_reference: np.ndarray, origins_image: np.ndarray, axes_image: np.ndarray,
               l_range: tuple[float, float], config: RegistrationSettings) -> PairFit:
    """Solve l and ``ReferenceToImage`` on the paired points (Reference / image, row k paired with row k),
    flag outliers and, with ``exclude_outliers``, solve again without them (while enough pairs remain)."""
    def residuals_at(solution: OffsetSolution) -> np.ndarray:
        return residuals(solution.reference_to_image, points_reference, origins_image + solution.l_mm * axes_image)

    solution = solve_sensor_offset(points_reference, origins_image, axes_image, l_range)
    pair_residuals = residuals_at(solution)
    outlier = flag_outliers(pair_residuals, config)
    used = np.ones(len(points_reference), dtype=bool)
    warnings: list[str] = []
    if config.exclude_outliers and np.any(outlier) and np.count_nonzero(~outlier) >= config.pairing.min_pairs:
        used = ~outlier
        solution = solve_sensor_offset(points_reference[used], origins_image[used], axes_image[used], l_range)
        pair_residuals = residuals_at(solution)
        warnings.append(f"{np.count_nonzero(outlier)} outlier pair(s) left out of the fit")
    return PairFit(solution, pair_residuals, outlier, used, warnings)


#: A fixed l is said to disagree with the markers when the l they give is further than this many of its
#: standard errors away, and at least :data:`FIXED_L_TOLERANCE_MM`.
FIXED_L_SIGMAS = 3.0
FIXED_L_TOLERANCE_MM = 0.25


def _check_fixed_offset(points_reference: np.ndarray, origins_image: np.ndarray, axes_image: np.ndarray,
                        fixed_l_mm: float, model: MarkerModel) -> list[str]:
    """A warning when the paired markers determine l themselves (axes on more than one face) and put it
    elsewhere than the fixed ``[registration] sensor_offset_l_mm``: the predicted TRE takes the fixed l as exact,
    so a wrong one would make it optimistic (1 mm off doubled the error with markers on one face)."""
    if len(points_reference) < 4:
        return []
    free = solve_sensor_offset(points_reference, origins_image, axes_image,
                               (model.pinhole_bottom_mm, model.pinhole_top_mm))
    if not np.isfinite(free.l_std_mm):
        return []
    gap = abs(free.l_mm - fixed_l_mm)
    if gap <= max(FIXED_L_SIGMAS * free.l_std_mm, FIXED_L_TOLERANCE_MM):
        return []
    return [f"the fixed sensor offset l = {fixed_l_mm:.2f} mm ([registration] sensor_offset_l_mm) disagrees with "
            f"the markers, which put l at {free.l_mm:.2f} +/- {free.l_std_mm:.2f} mm: the predicted TRE takes the "
            "fixed l as exact; check the value, or leave l free"]


def _check_fre_and_offset(fre_value: float, solution: OffsetSolution, l_range: tuple[float, float],
                          config: RegistrationSettings) -> list[str]:
    """Refuse (:class:`NoSafeAnswerError`) an FRE above ``max_fre_mm`` or a solved l whose standard error
    is above ``max_l_std_mm``; the warnings about l (poorly determined, at an end of the pinhole)."""
    check_fre(fre_value, config, "the detected markers")
    if config.sensor_offset_l_mm is not None:
        return []
    warnings = []
    a, b = l_range
    if solution.l_std_mm > config.max_l_std_mm:
        raise NoSafeAnswerError(
            f"the sensor offset l is poorly determined (standard error {solution.l_std_mm:.2f} mm > "
            f"{config.max_l_std_mm:g} mm): the paired markers' axes are (nearly) parallel, so l trades off "
            "against a translation along them; give l in the settings ([registration] sensor_offset_l_mm) "
            "or use markers on more than one face"
        )
    if solution.l_std_mm > config.warn_l_std_mm:
        warnings.append(f"sensor offset l poorly determined: standard error {solution.l_std_mm:.2f} mm")
    if min(solution.l_mm - a, b - solution.l_mm) < 0.05:
        warnings.append(f"sensor offset l = {solution.l_mm:.2f} mm is at the end of the pinhole range "
                        f"[{a:g}, {b:g}] mm: check the marker model")
    return warnings


def check_fre(fre_value: float, config: RegistrationSettings, image_side: str) -> None:
    """Refuse (:class:`NoSafeAnswerError`) an FRE (mm) above ``[registration] max_fre_mm``; ``image_side`` names
    what to check besides the calibration recording."""
    if fre_value > config.max_fre_mm:
        raise NoSafeAnswerError(
            f"registration FRE {fre_value:.2f} mm is above the limit of {config.max_fre_mm:g} mm "
            f"([registration] max_fre_mm); check the calibration recording and {image_side}"
        )


def flag_outliers(pair_residuals: np.ndarray, config: RegistrationSettings) -> np.ndarray:
    """Residuals above ``outlier_factor`` x the robust RMS residual and above ``outlier_min_mm``."""
    if len(pair_residuals) < 4:
        return np.zeros(len(pair_residuals), dtype=bool)
    robust_rms = float(np.sqrt(np.median(pair_residuals**2) * 3.0 / _CHI2_3_MEDIAN))
    return (pair_residuals > config.outlier_factor * robust_rms) & (pair_residuals > config.outlier_min_mm)


def max_fre_from_settings(settings: Settings | None) -> float:
    """The FRE limit (mm) of the settings (``[registration] max_fre_mm``; the default without settings)."""
    return (settings or Settings()).registration.max_fre_mm
