"""What a reviewer must see first: refused steps, outliers, unpaired points, suspicious figures.

The checks apply the stages' own policies with the case's own settings rather than rules of
the report's: outliers by :func:`EMRegModule.core.registration.flag_outliers` (``outlier_factor``
x the robust RMS residual and above ``outlier_min_mm``), the FRE limit ``max_fre_mm`` of
:class:`~EMRegModule.core.registration.RegistrationSettings`, a moving probe by the dwell's
``still_radius_mm`` (:class:`~EMRegModule.core.dwell.DwellSettings`). What a stage already warned
about (its ``warnings``) is shown once, in its own words.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..core.ct import image_geometry
from ..core.registration import RegistrationResult, RegistrationSettings, flag_outliers
from .derived import MarkerRow
from .inputs import ReportInputs


@dataclass
class ReportWarning:
    """One warning of the report: ``kind`` is "refused", "warning" or "note"."""

    kind: str
    text: str


def _registration_settings(inputs: ReportInputs) -> RegistrationSettings:
    return inputs.settings.registration


def run_checks(inputs: ReportInputs) -> list[ReportWarning]:
    """Refused steps of ``run.json``, unreadable inputs, parts ``run.json`` records as not made (that
    ``evaluation.json`` does not already say), a registration missing for no stated reason."""
    found: list[ReportWarning] = []
    summary = [str(line) for line in (inputs.run or {}).get("summary", [])]
    refused = [line for line in summary if ": refused:" in line]
    found.extend(ReportWarning("refused", line) for line in refused)
    found.extend(ReportWarning("warning", f"could not read: {note}") for note in inputs.notes)
    said = set(inputs.evaluation.not_evaluated) if inputs.evaluation is not None else set()  # in its warnings
    for part, reason in ((inputs.run or {}).get("not_evaluated") or {}).items():
        if part not in said:  # as emreg run printed it
            what = {"navigation": "navigation not made", "tre": "TRE not evaluated"}.get(part, f"{part} not evaluated")
            found.append(ReportWarning("warning", f"{what}: {reason}"))
    if inputs.registration is None and inputs.detection is not None and inputs.frame_calibration is not None \
            and not refused:
        found.append(ReportWarning("warning", "no registration.json although markers and a frame calibration exist: "
                                              "the registration step refused or was not run"))
    return found


def stage_warnings(inputs: ReportInputs) -> list[ReportWarning]:
    """The warnings each stage wrote into its own output."""
    texts = []
    if inputs.frame_calibration is not None:
        texts += inputs.frame_calibration.warnings
    if inputs.registration is not None:
        texts += inputs.registration.warnings
    texts += list(inputs.evaluation.warnings) if inputs.evaluation is not None else []
    # once each: registration.json repeats the calibration's warnings (so that it tells them alone)
    found = [ReportWarning("warning", text) for text in dict.fromkeys(map(str, texts))]
    axis = inputs.registration.probe_axis if inputs.registration is not None else None
    if axis and not inputs.registration.point_fit:  # fiducial points have no axis to compare the probe's with
        found.append(ReportWarning("note", f"probe orientation: {axis.get('note') or axis.get('detected')} "
                                           f"(probe_axis setting {axis.get('setting')}, detected "
                                           f"{axis.get('detected')}, pairing by {axis.get('pairing')})"))
    return found


def outlier_warnings(registration: RegistrationResult, rows: list[MarkerRow],
                     settings: RegistrationSettings) -> list[ReportWarning]:
    """Pairs the registration's outlier rule flags (or the file flags) that its own warnings do not name."""
    paired = [r for r in rows if r.residual_mm is not None]
    residuals = np.array([r.residual_mm for r in paired], dtype=float)
    flagged = flag_outliers(residuals, settings) if len(paired) else np.zeros(0, dtype=bool)
    already = " ".join(w for w in registration.warnings if "outlier" in w)
    median = float(np.median(residuals)) if residuals.size else 0.0
    return [ReportWarning("warning", f"outlier: marker {r.id} (calibration point {r.calibration_label}) has a "
                                     f"residual of {r.residual_mm:.2f} mm (median {median:.2f} mm)")
            for r, policy in zip(paired, flagged, strict=True)
            if (policy or r.outlier) and f"{r.id}/" not in already]


def offset_warnings(inputs: ReportInputs, curve: tuple[np.ndarray, np.ndarray] | None) -> list[ReportWarning]:
    """An l at an end of the pinhole range, or away from the minimum of the FRE(l) curve shown."""
    registration = inputs.registration
    found = []
    l_mm = float(registration.sensor_offset_l_mm)
    a, b = inputs.model.pinhole_bottom_mm, inputs.model.pinhole_top_mm
    said = any("end of the pinhole range" in w for w in registration.warnings)
    if not said and not registration.sensor_offset_fixed and (l_mm <= a + 0.05 or l_mm >= b - 0.05):
        found.append(ReportWarning(
            "warning", f"the sensor offset l = {l_mm:.2f} mm sits at an end of the pinhole range [{a:.1f}, {b:.1f}] "
                       "mm: check the marker model and that the probe reached the pinhole's floor"))
    if curve is not None:
        l_values, values = curve
        l_best = float(l_values[int(np.argmin(values))])
        step = float(l_values[1] - l_values[0])
        if abs(l_best - l_mm) > 2 * step + 0.05:
            found.append(ReportWarning("warning", f"the FRE(l) curve of the reported pairs is lowest at l = "
                                                  f"{l_best:.2f} mm, not at the reported {l_mm:.2f} mm"))
    return found


def registration_checks(inputs: ReportInputs, rows: list[MarkerRow],
                        curve: tuple[np.ndarray, np.ndarray] | None) -> list[ReportWarning]:
    """Outliers, an FRE above the registration's limit, unpaired points, a doubtful sensor offset."""
    registration = inputs.registration
    if registration is None:
        return []
    settings = _registration_settings(inputs)
    found = outlier_warnings(registration, rows, settings)
    if np.isfinite(registration.fre_mm) and registration.fre_mm > settings.max_fre_mm:
        found.append(ReportWarning("warning", f"FRE {registration.fre_mm:.2f} mm is above "
                                              f"{settings.max_fre_mm:.1f} mm"))
    said = [w for w in registration.warnings if "paired with no" in w]  # the registration's own, shown already
    for names, what, its_words in ((registration.unpaired_image_markers, "detected marker(s)", "CT marker(s) "),
                                   (registration.unpaired_calibration_points, "calibration point(s)",
                                    "calibration point(s) ")):
        names = [str(n) for n in names if not any(w.startswith(its_words) and re.search(
            rf"(?<![\w-]){re.escape(str(n))}(?![\w-])", w.split(" paired with no", 1)[0]) for w in said)]
        if names:
            found.append(ReportWarning("warning", f"{len(names)} {what} not paired: " + ", ".join(names)))
    return found + offset_warnings(inputs, curve)


def calibration_checks(inputs: ReportInputs) -> list[ReportWarning]:
    """Calibration dwells whose spread exceeds the dwell's own stillness radius (the probe moved)."""
    if inputs.frame_calibration is None:
        return []
    limit = inputs.settings.calibration.still_radius_mm
    return [ReportWarning("warning", f"calibration point {p.label}: the probe moved during the dwell "
                                     f"(spread {p.std_mm:.2f} mm)")
            for p in inputs.frame_calibration.points if np.isfinite(p.std_mm) and p.std_mm > limit]


def ct_checks(inputs: ReportInputs) -> list[ReportWarning]:
    """A CT whose geometry is not the one detection saw, or no CT at all."""
    if inputs.detection is None:
        return []
    if inputs.ct is None:
        return [ReportWarning("note", "no CT available (give the case with --case): the CT slices and the CT "
                                      "surface are left out")]
    recorded = inputs.detection.image
    if not recorded:
        return []
    actual = image_geometry(inputs.ct.image)  # the geometry is known before the voxels arrive
    if list(recorded.get("size", [])) != list(actual["size"]) or not np.allclose(
            recorded.get("spacing", actual["spacing"]), actual["spacing"], atol=1e-4):
        return [ReportWarning("warning", "the CT found for this report does not have the geometry recorded in "
                                         "markers.json: the slices may show another image")]
    return []


def collect_warnings(inputs: ReportInputs, rows: list[MarkerRow],
                     curve: tuple[np.ndarray, np.ndarray] | None) -> list[ReportWarning]:
    """Every warning of the report, refusals first."""
    return (run_checks(inputs) + stage_warnings(inputs) + registration_checks(inputs, rows, curve)
            + calibration_checks(inputs) + ct_checks(inputs))
