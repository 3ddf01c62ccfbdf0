"""Quantities the report derives from the typed inputs: markers with their pairs, FRE(l), predicted TRE.

Frames: image space (CT LPS, mm) unless a name says Reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core import sensor_offset
from ..core.calibration import CalibrationPoint, FrameCalibration
from ..core.detection.result import DetectedMarker, DetectionResult
from ..core.registration import RegistrationResult
from ..core.transforms import apply_transform
from .inputs import ReportInputs

if TYPE_CHECKING:
    from ..core.evaluation import Evaluation

#: Samples of the FRE(l) curve over the pinhole range [a, b] when the registration stored none.
FRE_CURVE_SAMPLES = 151


def tre_figures(evaluation: Evaluation | None) -> dict[str, Any]:
    """The TRE block of ``evaluation.json`` as the evaluation writes it (:meth:`TargetEvaluation.to_json`:
    overall mean, std, n, RMS, max and predicted RMS over the dwell errors as written, and per target its
    statistics, RMS and prediction); empty without a TRE or without dwells."""
    tre = evaluation.tre if evaluation is not None else None
    return tre.to_json() if tre is not None and tre.dwells else {}


def finite_or_none(value: object) -> float | None:
    """``value`` as a finite float, or None (missing, NaN, not a number)."""
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


@dataclass
class MarkerRow:
    """One detected marker with its pair in the registration (image space, LPS mm)."""

    marker: DetectedMarker
    calibration_label: str | None = None
    residual_mm: float | None = None
    outlier: bool = False

    @property
    def id(self) -> str:
        return self.marker.id

    @property
    def origin(self) -> np.ndarray:
        return self.marker.origin

    @property
    def axis(self) -> np.ndarray:
        return self.marker.axis

    @property
    def marker_to_image(self) -> np.ndarray:
        return self.marker.marker_to_image

    @property
    def volume_mm3(self) -> float | None:
        return finite_or_none(self.marker.volume_mm3)

    @property
    def fit_rms_mm(self) -> float | None:
        return finite_or_none(self.marker.fit_rms_mm)

    def sensor_point(self, l_mm: float) -> np.ndarray:
        """The probe sensor's centre in this marker's pinhole at offset ``l_mm`` (image space)."""
        return self.origin + l_mm * self.axis


def marker_rows(detection: DetectionResult | None, registration: RegistrationResult | None) -> list[MarkerRow]:
    """Every detected marker, joined with its pair (calibration label, residual, outlier flag) when paired."""
    rows = [MarkerRow(m) for m in (detection.markers if detection is not None else [])]
    by_id = {r.id: r for r in rows}
    for pair in registration.pairs if registration is not None else []:
        row = by_id.get(str(pair.get("image_marker")))
        if row is not None:
            row.calibration_label = str(pair.get("calibration_point"))
            row.residual_mm = finite_or_none(pair.get("residual_mm"))
            row.outlier = bool(pair.get("outlier", False))
    return rows


def calibration_points(frame_calibration: FrameCalibration | None) -> dict[str, CalibrationPoint]:
    """The calibrated pinholes by label (positions in the Reference frame, mm)."""
    return {p.label: p for p in (frame_calibration.points if frame_calibration is not None else [])}


def fre_curve(rows: Sequence[MarkerRow], points: dict[str, CalibrationPoint], l_range: tuple[float, float],
              samples: int = FRE_CURVE_SAMPLES) -> tuple[np.ndarray, np.ndarray] | None:
    """FRE(l) (paper Eq. 10, :func:`EMRegModule.core.sensor_offset.fre_curve`) over the pinhole range for the
    paired markers: (l values, FRE values) in mm; None with fewer than 3 pairs."""
    paired = [r for r in rows if r.calibration_label in points]
    if len(paired) < 3:
        return None
    curve = sensor_offset.fre_curve(np.linspace(l_range[0], l_range[1], samples),
                                    np.stack([points[r.calibration_label].position for r in paired]),
                                    np.stack([r.origin for r in paired]), np.stack([r.axis for r in paired]))
    return curve.l_mm, curve.fre_mm


def stored_fre_curve(registration: RegistrationResult) -> tuple[np.ndarray, np.ndarray] | None:
    """The FRE(l) curve the registration stored, if it is a usable curve (increasing l, matching lengths)."""
    l_values, values = (np.asarray(v, dtype=float) for v in registration.fre_curve)
    if l_values.ndim != 1 or l_values.shape != values.shape or len(l_values) < 2 or np.ptp(l_values) <= 0:
        return None
    return l_values, values


def report_fre_curve(inputs: ReportInputs, rows: Sequence[MarkerRow], points: dict[str, CalibrationPoint]
                     ) -> tuple[tuple[np.ndarray, np.ndarray] | None, bool]:
    """The FRE(l) curve to show and whether the registration stored it (else recomputed from the pairs)."""
    if inputs.registration is None:
        return None, False
    stored = stored_fre_curve(inputs.registration)
    if stored is not None:
        return stored, True
    return fre_curve(rows, points, (inputs.model.pinhole_bottom_mm, inputs.model.pinhole_top_mm)), False


def predicted_tre_by_target(inputs: ReportInputs) -> dict[str, float]:
    """Fitzpatrick's predicted TRE (mm) per target label, from the registration when it has one.

    The registration stores ``targets_image`` with ``predicted_tre_mm``; labels come from the
    case's ``targets.mrk.json`` (matched by position) or, without it, T1, T2, ... in order.
    """
    registration = inputs.registration
    if registration is None or registration.predicted_tre_mm is None or registration.targets_image is None:
        return {}
    predicted = np.asarray(registration.predicted_tre_mm, dtype=float).reshape(-1)
    targets = np.asarray(registration.targets_image, dtype=float).reshape(-1, 3)
    if len(predicted) != len(targets):
        return {}
    result = {}
    for i, (target, value) in enumerate(zip(targets, predicted, strict=True)):
        label = f"T{i + 1}"
        if inputs.targets_positions is not None and len(inputs.targets_positions):
            distance = np.linalg.norm(inputs.targets_positions - target, axis=1)
            k = int(np.argmin(distance))
            if distance[k] > 0.01:
                continue
            label = inputs.targets_labels[k]
        result[label] = float(value)
    return result


def calibration_points_in_image(inputs: ReportInputs, points: dict[str, CalibrationPoint]) -> np.ndarray | None:
    """Every calibration point mapped into image space by ``ReferenceToImage`` (None without a registration)."""
    if inputs.registration is None or not points:
        return None
    return apply_transform(inputs.registration.reference_to_image, np.stack([p.position for p in points.values()]))
