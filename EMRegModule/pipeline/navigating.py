"""The navigation's helpers: the guidance to a plan (:func:`guide`), the per-pose checks of a navigation
(:func:`check_navigation`: checkpoints, reference jumps, pose status), and the end-to-end error model of a
registration (:func:`error_model`).

Frames and units: image space (the CT's LPS physical space, mm); ``ReferenceToImage`` the registration; a tool's
``TipToProbe`` (mm) makes the navigated point its tip (``TipToImage``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.checkpoints import CheckpointReport, pinholes_from_detection
from ..core.checkpoints import check_navigation as check
from ..core.error_model import ErrorModel
from ..core.guidance import GuidanceReport, guidance, guidance_report, predicted_at, shaft_in_tip
from ..core.navigation import NavigationResult
from ..core.plan import Plan
from ..core.registration import RegistrationResult
from ..core.tool import ToolCalibration
from ..core.tracking import TrackingRecording
from ..settings import Settings

if TYPE_CHECKING:
    from .results import WorkflowResults


def error_model(registration: RegistrationResult | None, settings: Settings) -> ErrorModel | None:
    """The end-to-end error model of ``registration`` (``[evaluation]`` priors), or None."""
    if registration is None or registration.error is None:
        return None
    priors = settings.evaluation
    return ErrorModel.with_priors(registration.reference_to_image, registration.error, priors.reference_error_mm,
                                  priors.reference_error_deg, priors.placement_error_mm)


def guide(plan: Plan | None, result: NavigationResult, tool: ToolCalibration | None,
          model: ErrorModel | None) -> GuidanceReport | None:
    """With a plan: the guidance numbers of every sample of ``result`` (set on it as ``result.guidance``) and
    their report (the closest approach among the OK samples; the predicted error at the plan's target, mm: the
    error model's end-to-end RMS TRE there, the tool's own calibration RMS and its lever arm in quadrature, with the
    95 % radius, when there is an error model)."""
    if plan is None:
        return None
    tip_to_probe = None if tool is None else tool.tip_to_probe
    result.guidance = guidance(result.probe_to_image, plan, shaft_in_tip(tip_to_probe))
    ok = None if result.status is None else np.asarray(result.status) == "OK"
    prediction = None if model is None else predicted_at(model, plan.target_mm, tool)
    return guidance_report(plan, result.guidance, result.time_s, result.position_mm, ok, prediction,
                           tool_summary(tool))


def tool_summary(tool: ToolCalibration | None) -> dict[str, Any] | None:
    """What ``navigation.json`` says of the navigated tool (None: the pinhole probe's sensor is navigated); its tip
    in its sensor's frame (mm), its calibration RMS (mm) and whether it has an axis (a shaft) for the angle."""
    if tool is None:
        return None
    return {"source": tool.source, "name": tool.name, "tip_mm": [round(float(v), 4) for v in tool.tip_mm],
            "calibration_rms_mm": None if tool.rms_mm is None else round(float(tool.rms_mm), 4),
            "has_axis": shaft_in_tip(tool.tip_to_probe) is not None}


def check_navigation(results: WorkflowResults, settings: Settings, reference_sensor: int, result: NavigationResult,
                     recording: TrackingRecording, warn: bool = True) -> CheckpointReport:
    """Checkpoints at the detected markers' pinholes, reference jumps and the pose status of ``result``
    (:mod:`EMRegModule.core.checkpoints`); their warnings join the recording's (``warn``)."""
    pinholes = (None if results.detection is None else
                pinholes_from_detection(results.detection, results.registration.sensor_offset_l_mm,
                                        results.registration))  # judged against the error model
    report = check(result, recording, pinholes, reference_sensor, settings.navigation)
    if pinholes is None:  # a point fit onto fiducials, or a registration folder without its markers
        report.note = "no detected markers (markers.json) beside the registration: no pinholes to check at"
    if warn:
        recording.warnings.extend(n for n in report.warnings() if n not in recording.warnings)
    return report
