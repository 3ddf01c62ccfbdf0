"""The workflow controller: calibration -> detection -> pairing/registration -> navigation.

A small state machine shared by the ``emreg`` command and the 3D Slicer module's Logic.
It holds the inputs and the results of each stage, refuses a step whose prerequisites are
missing (saying what is missing), and drops every result that a new input makes stale:

    CT image ──────────────> detection ─┐
                                         ├─> registration ─> navigation / evaluation
    calibration recording -> frame calibration ─┘

All poses are in millimetres; ``ReferenceToImage`` maps Reference-sensor coordinates into
the CT's LPS image space.
"""

from __future__ import annotations

import contextlib
import enum
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import EMRegError
from .io.case import Case
from .marker_model import MarkerModel
from .progress import QUIET, Progress
from .settings import Settings

if TYPE_CHECKING:  # the stage modules import heavy libraries; load them only when used
    import SimpleITK as sitk

    from .calibration import FrameCalibration
    from .detection import DetectionResult
    from .error_model import ErrorModel
    from .evaluation import Evaluation
    from .navigation import NavigationResult
    from .registration import RegistrationResult
    from .tracking import TrackingRecording


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


class EMRegController:
    """Sequences the EMReg workflow; usable without any GUI.

    ``settings`` is the typed, checked ``case.toml`` (:class:`~EMRegModule.settings.Settings`;
    defaults when None); each stage gets its own table.
    """

    def __init__(self, settings: Settings | None = None, progress: Progress | None = None) -> None:
        if settings is not None and not isinstance(settings, Settings):
            raise TypeError("EMRegController takes a Settings object (EMRegModule.settings.load_settings)")
        self.settings: Settings = settings or Settings()
        self.progress = progress or QUIET
        self.marker_model: MarkerModel = self.settings.marker
        self.reference_sensor: int = self.settings.sensors.reference
        self.probe_sensor: int = self.settings.sensors.probe
        self.image: sitk.Image | None = None
        self.image_source: str | None = None
        self.ct_series: dict[str, Any] | None = None  # a DICOM CT: the series used and the others
        self.calibration_recording: TrackingRecording | None = None
        self.detection: DetectionResult | None = None
        self.frame_calibration: FrameCalibration | None = None
        self.registration: RegistrationResult | None = None
        self.navigation: NavigationResult | None = None

    @classmethod
    def for_case(cls, case: Case, progress: Progress | None = None) -> EMRegController:
        """A controller configured with a case folder's ``case.toml``."""
        return cls(case.settings, progress)

    # --- state ----------------------------------------------------------------------------

    @property
    def state(self) -> WorkflowState:
        """The furthest state reached."""
        if self.navigation is not None:
            return WorkflowState.NAVIGATING
        if self.registration is not None:
            return WorkflowState.REGISTERED
        if self.detection is not None and self.frame_calibration is not None:
            return WorkflowState.READY_TO_REGISTER
        if self.detection is not None:
            return WorkflowState.MARKERS_DETECTED
        if self.frame_calibration is not None:
            return WorkflowState.FRAME_CALIBRATED
        return WorkflowState.EMPTY

    def _require(self, **needed: object) -> None:
        missing = [what for what, value in needed.items() if value is None]
        if missing:
            names = {
                "image": "a CT (load_ct)",
                "calibration_recording": "a calibration recording (load_calibration_recording)",
                "detection": "detected markers (detect_markers or set_detection)",
                "frame_calibration": "a frame calibration (calibrate_frame or set_frame_calibration)",
                "registration": "a registration (register or set_registration)",
            }
            raise WorkflowError("this step needs " + " and ".join(names[m] for m in missing) + " first")

    def _invalidate(self, *, detection: bool = False, frame_calibration: bool = False) -> None:
        if detection:
            self.detection = None
        if frame_calibration:
            self.frame_calibration = None
        self.registration = None
        self.navigation = None

    # --- inputs -----------------------------------------------------------------------------

    def load_ct(self, path: str | os.PathLike[str]) -> sitk.Image:
        """Read the CT (file or DICOM folder); drops detection and everything after it."""
        from .io.image import open_ct

        _import_in_background("EMRegModule.detection")  # overlaps the import with the file read
        with self.progress.step("reading CT"):
            fill = open_ct(path, self.ct_series_choice)
            image = fill.result()
        self.set_image(image, str(path))
        self.ct_series = fill.series
        return image

    def load_ct_and_detect(self, path: str | os.PathLike[str]) -> DetectionResult:
        """``load_ct`` then ``detect_markers``, detecting on the slices already read while the rest arrives.

        The same result as the two calls, sooner. Nothing changes when reading or detection fails.
        """
        from .io.image import open_ct

        _import_in_background("EMRegModule.detection")  # overlaps the import with the start of the read
        with self.progress.step("opening CT"):
            fill = open_ct(path, self.ct_series_choice)
        from .detection import detect_markers

        try:
            result = detect_markers(fill.image, self.marker_model, self.settings.detection, self.progress,
                                    wait_for_slices=fill.wait_for_slices)
            image = fill.result()  # the checksum is verified only at the end
        except BaseException as exc:
            fill.cancel()
            if isinstance(exc, EMRegError):
                read_error = fill.read_error()  # a bad file explains a failed detection: report the file
                if isinstance(read_error, EMRegError) and read_error is not exc:
                    raise read_error from None
            raise
        self.set_image(image, str(path))
        self.ct_series = result.ct_series = fill.series
        self.set_detection(result)
        return result

    @property
    def ct_series_choice(self) -> str | None:
        """``[ct] series`` (a Series Instance UID or a series number) forcing the DICOM series, or None."""
        value = self.settings.ct.series
        return None if value is None else str(value)

    def set_image(self, image: sitk.Image, source: str = "CT") -> None:
        """Use an image already in memory (e.g. a Slicer volume node converted to SimpleITK)."""
        from .io.ct_checks import check_ct_image

        check_ct_image(image, source)  # geometry and voxel values (NaN / inf refused)
        self.image = image
        self.image_source = source
        self.ct_series = None
        self._invalidate(detection=True)

    def load_calibration_recording(self, path: str | os.PathLike[str]) -> TrackingRecording:
        """Read the frame-calibration recording; drops the frame calibration and what follows."""
        from .io.recording import read_recording

        recording = read_recording(path, self.settings, self.reference_sensor, self.probe_sensor)
        self.set_calibration_recording(recording)
        return recording

    def set_calibration_recording(self, recording: TrackingRecording) -> None:
        self.calibration_recording = recording
        self._invalidate(frame_calibration=True)

    def set_sensors(self, reference_sensor: int | None = None, probe_sensor: int | None = None) -> None:
        """Change the sensor ports (checked as ``[sensors]``: 1..4, two different ports); a change drops
        the frame calibration and what follows."""
        current = self.settings.with_sensors(self.reference_sensor, self.probe_sensor)
        sensors = current.with_sensors(reference_sensor, probe_sensor).sensors
        if (sensors.reference, sensors.probe) != (self.reference_sensor, self.probe_sensor):
            self.reference_sensor, self.probe_sensor = sensors.reference, sensors.probe
            self._invalidate(frame_calibration=True)

    # --- stages -----------------------------------------------------------------------------

    def detect_markers(self) -> DetectionResult:
        """Find the markers in the CT and estimate each one's pose (image space, LPS)."""
        self._require(image=self.image)
        from .detection import detect_markers

        result = detect_markers(self.image, self.marker_model, self.settings.detection, self.progress)
        result.ct_series = self.ct_series
        self.set_detection(result)
        return result

    def set_detection(self, detection: DetectionResult) -> None:
        """Use detected markers (e.g. read from ``markers.json``); drops the registration."""
        self._invalidate()
        self.detection = detection

    def calibrate_frame(self) -> FrameCalibration:
        """One point per marker pinhole in the Reference frame from the calibration recording."""
        self._require(calibration_recording=self.calibration_recording)
        from .calibration import calibrate_frame

        with self.progress.step("calibrating frame"):
            result = calibrate_frame(
                self.calibration_recording, self.reference_sensor, self.probe_sensor,
                self.settings.calibration, probe_axis=self.probe_axis or "auto",
            )
        self.set_frame_calibration(result)
        return result

    def set_frame_calibration(self, frame_calibration: FrameCalibration) -> None:
        """Use a frame calibration (e.g. read from ``frame_calibration.json``); drops the registration."""
        self._invalidate()
        self.frame_calibration = frame_calibration

    def register(self, targets_image: np.ndarray | None = None) -> RegistrationResult:
        """Pair markers with calibration points, solve the sensor offset l, fit ``ReferenceToImage``.

        ``targets_image`` (N, 3, LPS mm), when given, gets a predicted TRE in the result.
        """
        self._require(detection=self.detection, frame_calibration=self.frame_calibration)
        from .registration import register

        with self.progress.step("pairing and registering"):
            result = register(
                self.detection, self.frame_calibration, self.marker_model,
                self.settings.registration, targets_image=targets_image, probe_axis=self.probe_axis,
            )
        self.registration = result
        self.navigation = None
        return result

    def set_registration(self, registration: RegistrationResult) -> None:
        """Use a registration (e.g. read from ``registration.json``)."""
        self.registration = registration
        self.navigation = None

    def navigate_recording(self, recording: TrackingRecording) -> NavigationResult:
        """Map every probe sample of a recording into image space (paper Eq. 11-12)."""
        self._require(registration=self.registration)
        from .navigation import navigate_recording

        result = navigate_recording(
            recording, self.registration.reference_to_image, self.reference_sensor, self.probe_sensor
        )
        self.navigation = result
        return result

    def evaluate(self, navigation: TrackingRecording | None = None,
                 targets: tuple[list[str], np.ndarray] | None = None,
                 board: TrackingRecording | None = None, tolerant: bool = False,
                 not_evaluated: dict[str, str] | None = None) -> Evaluation:
        """TRE at ``targets`` (labels, (K, 3) LPS mm) from a navigation recording, and the board table
        from a board recording, with the current registration (``[evaluation]``, ``[board]`` settings).

        ``tolerant`` (a run): a part that cannot be evaluated is "not evaluated" with its reason in the
        result instead of an error; ``not_evaluated``: parts whose recording could not be read, and why."""
        self._require(registration=self.registration)
        from .evaluation import evaluate

        with self.progress.step("evaluating"):
            return evaluate(self.registration.reference_to_image, self.reference_sensor, self.probe_sensor,
                            self.settings.evaluation, navigation=navigation, targets=targets, board=board,
                            nominal_edges_mm=self.settings.board.edges_mm, error_model=self.error_model,
                            tolerant=tolerant, not_evaluated=not_evaluated)

    @property
    def probe_axis(self) -> str | None:
        """``[sensors] probe_axis`` when set (None: ``auto`` for a calibration, the calibration's own
        setting for a registration)."""
        return self.settings.sensors.probe_axis

    @property
    def reference_to_image(self) -> np.ndarray:
        """The current ``ReferenceToImage`` (4x4, mm); a :class:`WorkflowError` before registration."""
        self._require(registration=self.registration)
        return self.registration.reference_to_image

    @property
    def error_model(self) -> ErrorModel | None:
        """The end-to-end error model of the current registration (``[evaluation]`` priors), or None."""
        if self.registration is None or self.registration.error is None:
            return None
        from .error_model import ErrorModel

        priors = self.settings.evaluation
        return ErrorModel.with_priors(self.registration.reference_to_image, self.registration.error,
                                      priors.reference_error_mm, priors.reference_error_deg,
                                      priors.placement_error_mm)

    def describe(self) -> str:
        """A one-line summary of the state for logs and the Slicer module's status label."""
        parts = [f"state: {self.state.value}"]
        if self.detection is not None:
            parts.append(f"{len(self.detection.markers)} markers detected")
        if self.frame_calibration is not None:
            parts.append(f"{len(self.frame_calibration.points)} pinholes calibrated")
        if self.registration is not None:
            parts.append(f"FRE {self.registration.fre_mm:.2f} mm, l = {self.registration.sensor_offset_l_mm:.2f} mm")
        return "; ".join(parts)


def _import_in_background(module: str) -> None:
    """Start importing a heavy module on a thread; a later ``import`` waits for it or finds it done.

    SimpleITK's reader releases the GIL, so importing the detection stage (scipy, VTK) while a
    large CT is read takes its ~0.5 s off the critical path. Import errors surface later, where
    the module is really imported.
    """
    import importlib
    import threading

    def run() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(module)

    threading.Thread(target=run, name=f"import {module}", daemon=True).start()

