"""The results of the workflow, an immutable value: a new result or a new input gives a new
:class:`WorkflowResults` (what it makes stale dropped, from the stage table), never one changed in place.

All poses are in millimetres; ``ReferenceToImage`` maps Reference-sensor coordinates into the CT's LPS image
space.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

from ..errors import EMRegError
from ..stages import DEPENDENTS, STAGE, STAGES

if TYPE_CHECKING:
    import numpy as np

    from ..core.calibration import FrameCalibration
    from ..core.checkpoints import CheckpointReport
    from ..core.detection import DetectionResult
    from ..core.evaluation import Evaluation
    from ..core.fiducials import Fiducials
    from ..core.guidance import GuidanceReport
    from ..core.navigation import NavigationResult
    from ..core.registration import RegistrationResult
    from ..core.tre_map import TreMap


class WorkflowState(enum.Enum):
    """How far the workflow has come (each state implies the ones before it)."""

    EMPTY = "empty"
    FRAME_CALIBRATED = "frame calibrated"
    MARKERS_DETECTED = "markers detected"
    READY_TO_REGISTER = "frame calibrated and markers detected"
    REGISTERED = "paired and registered"
    NAVIGATING = "navigating"


class WorkflowError(EMRegError):
    """A step was asked for before its prerequisites exist."""


#: What to do first when a result is missing (in :meth:`WorkflowResults.require`'s message).
_HOW_TO_MAKE = {
    "image": "a CT",
    "calibration_recording": "a calibration recording",
    "detection": "detected markers (detect, or markers.json) or fiducials",
    "frame_calibration": "a frame calibration (calibrate, or frame_calibration.json)",
    "registration": "a registration (register, or registration.json)",
    "navigation": "a navigation (navigate)",
    "evaluation": "an evaluation (evaluate)",
}


@dataclass(frozen=True)
class WorkflowResults:
    """The result of each stage (None: not made, or stale). ``fiducials`` are the image-side points of a case
    without a CT (a rigid point fit onto them replaces the markers' pinhole route). ``calibrated_here``: the frame
    calibration was made from this workflow's recording (with its tool's touches), not read from a file."""

    detection: DetectionResult | None = None
    fiducials: Fiducials | None = None
    frame_calibration: FrameCalibration | None = None
    calibrated_here: bool = False
    registration: RegistrationResult | None = None
    navigation: NavigationResult | None = None
    #: The checkpoints, reference jumps and pose status of ``navigation`` (:mod:`EMRegModule.core.checkpoints`).
    checkpoints: CheckpointReport | None = None
    #: With a plan: the predicted error at its target and the closest approach (:mod:`EMRegModule.core.guidance`).
    guidance: GuidanceReport | None = None
    evaluation: Evaluation | None = None
    #: The predicted-TRE map over the CT's space (:mod:`EMRegModule.core.tre_map`), to be written.
    tre_map: TreMap | None = None

    def without(self, *stages: str) -> WorkflowResults:
        """The results once ``stages`` have a new input: their results, and every result made from them, dropped."""
        return dataclasses.replace(self, **{f: _DEFAULTS[f] for stage in stages
                                            for later in (stage, *DEPENDENTS[stage]) for f in STAGE[later].results})

    def made(self, stage: str, **result: Any) -> WorkflowResults:
        """The results once ``stage`` has made ``result`` (its fields, :attr:`~.stages.Stage.results`; those not
        given are reset): every result made from it (:data:`~.stages.DEPENDENTS`) dropped."""
        unknown = set(result) - set(STAGE[stage].results)
        if unknown:
            raise ValueError(f"{stage} makes {', '.join(STAGE[stage].results)}, not {', '.join(sorted(unknown))}")
        return dataclasses.replace(self.without(stage), **result)

    @property
    def image_points(self) -> DetectionResult | Fiducials | None:
        """What the calibration points register onto: the detected CT markers, else fiducials (or None)."""
        return self.detection if self.detection is not None else self.fiducials

    @property
    def state(self) -> WorkflowState:
        """The furthest state reached."""
        if self.navigation is not None:
            return WorkflowState.NAVIGATING
        if self.registration is not None:
            return WorkflowState.REGISTERED
        if self.image_points is not None and self.frame_calibration is not None:
            return WorkflowState.READY_TO_REGISTER
        if self.image_points is not None:
            return WorkflowState.MARKERS_DETECTED
        if self.frame_calibration is not None:
            return WorkflowState.FRAME_CALIBRATED
        return WorkflowState.EMPTY

    def available(self, has_image: bool, has_calibration_recording: bool) -> list[str]:
        """The stages that can run on their own now, in workflow order (the 3D Slicer module's buttons): ``detect``
        with a CT, ``calibrate`` with a calibration recording, a later stage once every stage it needs has a result
        (``report`` once any has). ``tre_map`` and ``bundle`` are made by ``run`` and ``report``, never alone."""
        made = {"detect": self.image_points is not None, "calibrate": self.frame_calibration is not None,
                "register": self.registration is not None, "navigate": self.navigation is not None,
                "evaluate": self.evaluation is not None}
        inputs = {"detect": has_image, "calibrate": has_calibration_recording,
                  "report": made["detect"] or made["calibrate"]}
        return [stage.name for stage in STAGES if stage.name not in ("tre_map", "bundle")
                and (inputs[stage.name] if stage.name in inputs else all(made[need] for need in stage.needs))]

    @staticmethod
    def require(**needed: object) -> None:
        """Refuse (:class:`WorkflowError`) a step whose inputs (by name, None: missing) are not there yet."""
        missing = [what for what, value in needed.items() if value is None]
        if missing:
            raise WorkflowError("this step needs " + " and ".join(_HOW_TO_MAKE[m] for m in missing) + " first")

    @property
    def reference_to_image(self) -> np.ndarray:
        """The current ``ReferenceToImage`` (4x4, mm); a :class:`WorkflowError` before registration."""
        self.require(registration=self.registration)
        return self.registration.reference_to_image

    def describe(self) -> str:
        """A one-line summary of the state for logs and the Slicer module's status label."""
        parts = [f"state: {self.state.value}"]
        if self.detection is not None:
            parts.append(f"{len(self.detection.markers)} markers detected")
        if self.fiducials is not None:
            parts.append(f"{len(self.fiducials)} fiducials")
        if self.frame_calibration is not None:
            parts.append(f"{len(self.frame_calibration.points)} pinholes calibrated")
        if self.registration is not None:
            parts.append(f"FRE {self.registration.fre_mm:.2f} mm, {offset_summary(self.registration)}")
        return "; ".join(parts)


def results_lines(results: WorkflowResults, evaluation: Evaluation | None = None,
                  report_path: object = None) -> list[str]:
    """A few lines of figures (the 3D Slicer module's panel): the FRE, unpaired points, the TRE (of ``evaluation``),
    the guidance to a plan (closest approach, predicted error at the target, mm), the report's path."""
    lines = []
    registration = results.registration
    if registration is not None:
        lines.append(f"FRE {registration.fre_mm:.2f} mm over {len(registration.pairs)} pairs; "
                     f"{offset_summary(registration)}")
        if registration.unpaired_image_markers or registration.unpaired_calibration_points:
            lines.append(f"unpaired: {len(registration.unpaired_image_markers)} markers, "
                         f"{len(registration.unpaired_calibration_points)} calibration points")
    tre = evaluation.tre if evaluation is not None else None
    if tre is not None:
        lines.append(f"TRE {tre.mean_mm:.2f} +/- {tre.std_mm:.2f} mm")
    if results.guidance is not None:
        lines.append(f"guidance: {results.guidance.summary()}")
    if report_path is not None:
        lines.append(f"report: {report_path}")
    return lines


def offset_summary(registration: RegistrationResult) -> str:
    """The sensor offset of a summary line: ``l = 14.20 mm``, or that a point fit onto fiducials has none."""
    if getattr(registration, "point_fit", False):  # (a registration-like object without it: the pinhole route)
        return "point fit onto fiducials (no sensor offset)"
    return f"l = {registration.sensor_offset_l_mm:.2f} mm"


#: Each field's value when not made.
_DEFAULTS: dict[str, Any] = {f.name: f.default for f in fields(WorkflowResults)}
assert {f for stage in STAGES for f in stage.results} == set(_DEFAULTS), "every result belongs to one stage"
