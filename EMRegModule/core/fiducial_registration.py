"""Registration onto fiducial points: planned landmarks, points placed in Slicer, a PLUS phantom definition.

The CT route (:func:`EMRegModule.core.registration.register`) pairs calibration points with CT markers, each a
segment of possible pinhole points ``origin + l * axis``, and solves the sensor's depth l in the pinhole. A
fiducial here is a point, with no axis: the calibration points are the places the tool touched, in the
Reference frame (with a tool: its tip, ``TipToProbe`` applied by the calibration; without one, the
tracked sensor itself, a pointer whose tip is its sensor), and the registration is a plain least-squares
rigid fit of them onto the fiducials, with no l:

1. pairing: the distance-graph pairing of :mod:`EMRegModule.core.pairing` with a zero-length segment per
   fiducial (l fixed at 0) and no directions: unordered, with missing and extra points on either side;
   an ambiguous layout is refused (:class:`NoSafeAnswerError`);
2. the rigid fit of the paired points, outliers flagged (and left out with ``exclude_outliers``) as on the
   CT route, FRE above ``max_fre_mm`` refused;
3. the error model without an l term (6 parameters: :func:`EMRegModule.core.error_model.registration_error`
   with l fixed), so the predicted TRE at the targets is the fit's own.

``ReferenceToImage`` then maps the Reference frame into the fiducials' frame (image space LPS for Slicer
markups, the phantom's frame for PLUS landmarks); each pair's ``image_marker`` is the fiducial's label.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..settings import RegistrationSettings
from .calibration import FrameCalibration
from .error_model import registration_error
from .fiducials import Fiducials
from .pairing import pair_markers
from .registration import (
    RegistrationResult,
    calibration_port,
    check_distortion,
    check_fre,
    distortion_of_fit,
    fit_pairs,
    pairing_record,
    predicted_registration_tre,
)

#: The pinhole "range" of a fiducial: a point (the sensor offset l is not a parameter of a point fit).
NO_OFFSET = (0.0, 0.0)


def calibration_tool(frame_calibration: FrameCalibration) -> Any:
    """The tool whose tip made the calibration points (``frame_calibration.tool``, set when a ``TipToProbe`` was
    applied), or None: the points are the probe sensor's own positions.

    This is where a tool's tip enters the fiducial route: the calibration applies ``TipToProbe`` to every sample
    before it averages a touch, so its points are tip positions in the Reference frame and are fitted as they are.
    """
    return getattr(frame_calibration, "tool", None)


def register_fiducials(fiducials: Fiducials, frame_calibration: FrameCalibration,
                       settings: RegistrationSettings | None = None,
                       targets_image: np.ndarray | None = None) -> RegistrationResult:
    """Pair the calibration points (Reference frame, mm) with the fiducials and fit ``ReferenceToImage``
    (Reference -> the fiducials' frame, mm) rigidly, with no sensor offset (see the module docstring).

    ``settings``: the ``[registration]`` table (FRE limit, outliers, pairing tolerances; ``sensor_offset_l_mm``
    does not apply); ``targets_image`` (K, 3), in the fiducials' frame: targets for the predicted TRE. Raises
    :class:`NoSafeAnswerError` for an ambiguous pairing, too few pairs or an FRE above ``max_fre_mm``.
    """
    config = settings or RegistrationSettings()
    fiducial_points = np.asarray(fiducials.positions, dtype=float).reshape(-1, 3)
    no_axes = np.zeros_like(fiducial_points)
    points = frame_calibration.positions
    labels = frame_calibration.labels
    pairing = pair_markers(fiducial_points, np.tile([0.0, 0.0, 1.0], (len(fiducial_points), 1)), points, None,
                           NO_OFFSET, config.pairing)
    fiducial_index = np.array([j for j, _ in pairing.pairs])
    cal_index = np.array([i for _, i in pairing.pairs])
    fit = fit_pairs(points[cal_index], fiducial_points[fiducial_index], no_axes[fiducial_index], NO_OFFSET, config)
    used, residuals = fit.used, fit.residuals_mm
    warnings = list(fit.warnings)
    if np.any(fit.outlier):
        warnings.append("outlier pair(s): " + ", ".join(
            f"{fiducials.labels[j]}/{labels[i]} ({r:.2f} mm)"
            for j, i, r, o in zip(fiducial_index, cal_index, residuals, fit.outlier, strict=True) if o))
    fre_value = float(np.sqrt(np.mean(residuals[used] ** 2)))
    check_fre(fre_value, config, f"the fiducials ({fiducials.source})")
    n_used = int(np.count_nonzero(used))
    distortion = distortion_of_fit(fit.solution, points[cal_index[used]], fiducial_points[fiducial_index[used]],
                                   no_axes[fiducial_index[used]], True, config,
                                   [frame_calibration.points[i] for i in cal_index[used]],
                                   [fiducials.labels[j] for j in fiducial_index[used]],
                                   points[sorted(set(range(len(points))) - set(cal_index.tolist()))])
    warnings += check_distortion(distortion, config)
    error = registration_error(points[cal_index[used]], fiducial_points[fiducial_index[used]],
                               no_axes[fiducial_index[used]], 0.0, False, residuals[used], distortion=distortion)
    targets, predicted = predicted_registration_tre(error, targets_image)
    unpaired_fiducials = [m for k, m in enumerate(fiducials.labels) if k not in set(fiducial_index.tolist())]
    unpaired_points = [p for k, p in enumerate(labels) if k not in set(cal_index.tolist())]
    warnings += _unpaired_warnings(unpaired_fiducials, unpaired_points)
    tool = calibration_tool(frame_calibration)
    if tool is None:
        warnings.append("the calibration points are the probe sensor's own positions (no tool tip applied): they "
                        "are taken as the touched points, right for a pointer whose tip is its sensor; for a stylus "
                        "give its tip calibration (--tool)")
    return RegistrationResult(
        reference_to_image=fit.solution.reference_to_image,
        sensor_offset_l_mm=0.0,
        fre_mm=fre_value,
        pairs=[{"image_marker": fiducials.labels[j], "calibration_point": labels[i], "residual_mm": float(r),
                "outlier": bool(o)}
               for j, i, r, o in zip(fiducial_index, cal_index, residuals, fit.outlier, strict=True)],
        unpaired_image_markers=unpaired_fiducials,
        unpaired_calibration_points=unpaired_points,
        sensor_offset_l_std_mm=0.0,
        sensor_offset_range_mm=NO_OFFSET,
        sensor_offset_fixed=True,
        fle_mm=fre_value * np.sqrt(n_used / (n_used - 2)) if n_used > 2 else float("nan"),
        targets_image=targets,
        predicted_tre_mm=predicted,
        error=error,
        warnings=warnings + list(frame_calibration.warnings),
        pairing=pairing_record(pairing, config.pairing),
        probe_axis={"setting": "none", "detected": "none", "pairing": "distances only",
                    "note": "fiducials are points: there is no marker axis to compare the probe's with"},
        reference_sensor=calibration_port(frame_calibration, "reference_sensor"),
        probe_sensor=calibration_port(frame_calibration, "probe_sensor"),
        fiducials={**fiducials.to_json(),
                   "fit": "rigid point fit of the calibration points onto the fiducials (no sensor offset l)",
                   "calibration_points": "tool tip" if tool is not None else "probe sensor (no tool tip applied)"},
    )


def _unpaired_warnings(fiducial_labels: list[str], calibration_labels: list[str]) -> list[str]:
    """One line per kind of point left out of the fit, naming them."""
    lines = []
    if calibration_labels:
        lines.append(f"calibration point(s) {', '.join(calibration_labels)} paired with no fiducial, left out of the "
                     "registration: likely a pause of the tool away from the fiducials, or a fiducial missing from "
                     "the fiducials file")
    if fiducial_labels:
        lines.append(f"fiducial(s) {', '.join(fiducial_labels)} paired with no calibration point, left out of the "
                     "registration: likely not touched in the calibration recording (or the touch not found)")
    return lines
