"""The controller's navigation helpers: the plan it guides to (:class:`Planner`), and the per-pose checks of a
navigation (:func:`check_navigation`: checkpoints, reference jumps, pose status).

Frames and units: image space (the CT's LPS physical space, mm); ``ReferenceToImage`` the registration; a tool's
``TipToProbe`` (mm) makes the navigated point its tip (``TipToImage``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EMRegError

if TYPE_CHECKING:
    from ..core.checkpoints import CheckpointReport
    from ..core.error_model import ErrorModel
    from ..core.guidance import GuidanceReport, Plan, TargetPrediction
    from ..core.navigation import NavigationResult
    from ..core.tool import ToolCalibration
    from ..core.tracking import TrackingRecording
    from ..io.case import Case
    from ..settings import Settings
    from .recorder import RunRecorder
    from .results import WorkflowResults


class Planner:
    """The plan a controller guides to (``plan``: image space, LPS mm; None: no plan, no guidance numbers).

    A new plan drops the navigation (its guidance numbers). A plan is refused (:class:`EMRegError`, one line) outside
    the CT of the detected markers when they are known (:meth:`check_in_ct`)."""

    def __init__(self, results: WorkflowResults, recorder: RunRecorder, settings: Settings) -> None:
        self.results = results
        self.recorder = recorder
        self.settings = settings
        self.plan: Plan | None = None

    def load(self, path: str | os.PathLike[str]) -> Plan:
        """Use the plan of a Slicer markups file (:func:`EMRegModule.io.plan_markups.read_plan`: a Line Entry -> Target,
        points labelled Entry and Target, or one target point; LPS or RAS as the file declares)."""
        from ..io.plan_markups import read_plan

        plan = read_plan(path)
        self.set(plan)
        self.recorder.note_inputs(plan=path)
        return plan

    def load_from_settings(self) -> Plan | None:
        """The plan of ``[navigation] plan`` (relative to ``case.toml``'s folder), if the settings name one."""
        name = self.settings.navigation.plan
        if not name:
            return None
        path = Path(name)
        if not path.is_absolute() and self.settings.source:
            path = Path(self.settings.source).parent / path
        return self.load(path)

    def set(self, plan: Plan | None, ct_name: str = "the CT") -> None:
        """Use ``plan`` (None: none), checked against the CT when its geometry is known; drops the navigation."""
        previous, self.plan = self.plan, plan
        try:
            self.check_in_ct(ct_name)
        except EMRegError:
            self.plan = previous
            raise
        self.results.drop("navigate")

    def for_run(self, case: Case) -> None:
        """Before ``emreg run``: the plan of ``[navigation] plan`` unless one was given, refused (one line) when the
        case has no calibration recording to register with (a plan needs a registration)."""
        if self.plan is None:
            self.load_from_settings()
        if self.plan is not None and case.calibration is None:
            raise EMRegError(f"{self.plan.source}: a plan needs a registration, and {case.folder} has no calibration "
                             "recording (calibration.csv or calibration.seq.mha) to register with; add it or leave "
                             "the plan out")

    def check_in_ct(self, ct_name: str = "the CT") -> None:
        """Refuse a plan outside the extent of the CT the markers were detected in (nothing to check without a plan
        or without detected markers: a registration onto fiducials has no CT)."""
        detection = self.results.detection
        if self.plan is None or detection is None or not getattr(detection, "image", None):
            return
        from ..core.plan import check_plan_in_image

        check_plan_in_image(self.plan, detection.image, ct_name)

    def predicted_at_target(self, model: ErrorModel | None, tool: ToolCalibration | None) -> TargetPrediction | None:
        """The predicted error at the plan's target (mm): the error model's end-to-end RMS TRE there, the tool's own
        calibration RMS (its file's ``rms_mm`` / PLUS ``Error``) and its lever arm (:mod:`EMRegModule.core.guidance`),
        in
        quadrature, with the 95 % radius; None without a plan or without an error model."""
        if self.plan is None or model is None:
            return None
        from ..core.guidance import predicted_at

        return predicted_at(model, self.plan.target_mm, tool)

    def guide(self, result: NavigationResult, tool: ToolCalibration | None,
              model: ErrorModel | None) -> GuidanceReport | None:
        """With a plan: the guidance numbers of every sample of ``result`` (set on it as ``result.guidance``) and
        their report (the closest approach among the OK samples, the predicted error at the target)."""
        if self.plan is None:
            return None
        from ..core.guidance import guidance, guidance_report, shaft_in_tip

        tip_to_probe = None if tool is None else tool.tip_to_probe
        result.guidance = guidance(result.probe_to_image, self.plan, shaft_in_tip(tip_to_probe))
        ok = None if result.status is None else np.asarray(result.status) == "OK"
        return guidance_report(self.plan, result.guidance, result.time_s, result.position_mm, ok,
                               self.predicted_at_target(model, tool), tool_summary(tool))


def tool_summary(tool: ToolCalibration | None) -> dict[str, Any] | None:
    """What ``navigation.json`` says of the navigated tool (None: the pinhole probe's sensor is navigated); its tip
    in its sensor's frame (mm), its calibration RMS (mm) and whether it has an axis (a shaft) for the angle."""
    if tool is None:
        return None
    from ..core.guidance import shaft_in_tip

    return {"source": tool.source, "name": tool.name, "tip_mm": [round(float(v), 4) for v in tool.tip_mm],
            "calibration_rms_mm": None if tool.rms_mm is None else round(float(tool.rms_mm), 4),
            "has_axis": shaft_in_tip(tool.tip_to_probe) is not None}


def check_navigation(results: WorkflowResults, settings: Settings, reference_sensor: int, result: NavigationResult,
                     recording: TrackingRecording, warn: bool = True) -> CheckpointReport:
    """Checkpoints at the detected markers' pinholes, reference jumps and the pose status of ``result``
    (:mod:`EMRegModule.core.checkpoints`); their warnings join the recording's (``warn``)."""
    from ..core.checkpoints import check_navigation as check
    from ..core.checkpoints import pinholes_from_detection

    pinholes = (None if results.detection is None else
                pinholes_from_detection(results.detection, results.registration.sensor_offset_l_mm,
                                        results.registration))  # judged against the error model
    report = check(result, recording, pinholes, reference_sensor, settings.navigation)
    if pinholes is None:  # a point fit onto fiducials, or a registration folder without its markers
        report.note = "no detected markers (markers.json) beside the registration: no pinholes to check at"
    if warn:
        recording.warnings.extend(n for n in report.warnings() if n not in recording.warnings)
    return report
