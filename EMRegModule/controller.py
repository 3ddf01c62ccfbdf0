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
import dataclasses
import enum
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import __version__
from .errors import EMRegError, NoSafeAnswerError
from .io.case import Case
from .marker_model import MarkerModel
from .outputs import (
    STAGE_OUTPUTS,
    OutputFolder,
    all_output_names,
    check_outputs,
    interrupted_by,
    refuse_out_over_inputs,
    signals_held,
)
from .progress import QUIET, Progress
from .provenance import InputDigest, Provenance, check_belongs, check_inputs_match, file_sha256
from .settings import Settings, choose_ports

if TYPE_CHECKING:  # the stage modules import heavy libraries; load them only when used
    import SimpleITK as sitk

    from .calibration import FrameCalibration
    from .detection import DetectionResult
    from .error_model import ErrorModel
    from .evaluation import Evaluation
    from .io.fiducials import Fiducials
    from .navigation import NavigationResult
    from .registration import RegistrationResult
    from .tool import ToolCalibration
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
        self.tool: ToolCalibration | None = None  # a tracked tool's tip (None: the paper's pinhole probe)
        self.tool_auto = False  # --tool auto: the tip is solved from the calibration recording's pivoting touches
        self.detection: DetectionResult | None = None
        #: Fiducial points instead of CT markers (``--fiducials``, a case's ``fiducials.mrk.json``), or None.
        self.fiducials: Fiducials | None = None
        self.frame_calibration: FrameCalibration | None = None
        self.registration: RegistrationResult | None = None
        self.navigation: NavigationResult | None = None
        #: The checkpoints, reference jumps and pose status of ``navigation`` (:mod:`EMRegModule.checkpoints`).
        self.checkpoints: Any = None
        self.evaluation: Evaluation | None = None
        #: The command this controller serves (in warnings and provenance).
        self.command = "emreg"
        self._inputs: dict[str, tuple[str, str | InputDigest]] = {}  # role -> (path, sha256)
        self._made_from: dict[str, Provenance] = {}  # output name -> provenance of the result held
        self._output_sha: dict[str, str] = {}  # output name -> sha256 of the file written or read
        self._report_image: sitk.Image | None = None  # the CT the report read, for the Slicer bundle
        #: Keep the CT in memory to the end of :meth:`run` (the Slicer Logic shows it afterwards). False
        #: (``emreg run``): it is let go before the Slicer bundle when the bundle copies it from its file.
        self.keep_ct = True

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
        if self._image_points is not None and self.frame_calibration is not None:
            return WorkflowState.READY_TO_REGISTER
        if self._image_points is not None:
            return WorkflowState.MARKERS_DETECTED
        if self.frame_calibration is not None:
            return WorkflowState.FRAME_CALIBRATED
        return WorkflowState.EMPTY

    @property
    def _image_points(self) -> object:
        """What the calibration points register onto: the detected CT markers, else fiducials (or None)."""
        return self.detection if self.detection is not None else self.fiducials

    def _require(self, **needed: object) -> None:
        missing = [what for what, value in needed.items() if value is None]
        if missing:
            names = {
                "image": "a CT (load_ct)",
                "calibration_recording": "a calibration recording (load_calibration_recording)",
                "detection": "detected markers (detect_markers or set_detection) or fiducials (load_fiducials)",
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
        self.evaluation = None

    # --- inputs -----------------------------------------------------------------------------

    def load_ct(self, path: str | os.PathLike[str]) -> sitk.Image:
        """Read the CT (file or DICOM folder); drops detection and everything after it."""
        from .io.image import open_ct

        _import_in_background("EMRegModule.detection.detect")  # overlaps the import with the file read
        self._warn_series_unused(path)
        with self.progress.step("reading CT"):
            fill = open_ct(path, self.ct_series_choice)
            image = fill.result()
        self.set_image(image, str(path))
        self.ct_series = fill.series
        return image

    def load_ct_and_detect(self, path: str | os.PathLike[str], keep_image: bool = True) -> DetectionResult:
        """``load_ct`` then ``detect_markers``, detecting on the slices already read while the rest arrives.

        The same result as the two calls, sooner. Nothing changes when reading or detection fails.
        A DICOM series is read compact (int16 where its headers would take int32: half the memory to
        fill, the same values), and read again exactly in the rare CT whose values do not fit.
        ``keep_image=False`` (``emreg detect``, which writes only the markers): the CT is not kept (``image`` is
        None afterwards), so a DICOM series is read without a SimpleITK image (``open_ct``'s ``voxels_only``).
        """
        from .io.dicom_series import NarrowVoxelsError

        _import_in_background("EMRegModule.detection.detect")  # overlaps the import with the start of the read
        self._warn_series_unused(path)
        try:
            return self._load_ct_and_detect(path, compact=True, keep_image=keep_image)
        except NarrowVoxelsError as exc:
            self.progress.message(f"[emreg] {exc}: reading the CT again with int32 voxels")
            return self._load_ct_and_detect(path, compact=False, keep_image=keep_image)

    def _load_ct_and_detect(self, path: str | os.PathLike[str], compact: bool, keep_image: bool) -> DetectionResult:
        from .io.image import open_ct

        with self.progress.step("opening CT"):
            fill = open_ct(path, self.ct_series_choice, compact=compact, voxels_only=not keep_image)
        from .detection import detect_markers

        try:
            result = detect_markers(fill.image, self.marker_model, self.settings.detection, self.progress,
                                    wait_for_slices=fill.wait_for_slices, voxels=fill.voxels)
            image = fill.result()  # the checksum is verified only at the end
        except BaseException as exc:
            fill.cancel()
            if isinstance(exc, EMRegError):
                read_error = fill.read_error()  # a bad file explains a failed detection: report the file
                if isinstance(read_error, EMRegError) and read_error is not exc:
                    raise read_error from None
            raise
        if fill.voxels is None:
            self.set_image(image, str(path))
        else:  # read for the detection only (``keep_image=False``): ``image`` is only the geometry, nothing kept
            self.image, self.image_source = None, str(path)
            self._invalidate(detection=True)
        self.ct_series = result.ct_series = fill.series
        self.set_detection(result)
        return result

    def _warn_series_unused(self, path: str | os.PathLike[str]) -> None:
        """A series forced (``--series``, ``[ct] series``) for a CT that is one image, not a DICOM folder, is said
        to be ignored rather than silently ignored."""
        if self.ct_series_choice is not None and not Path(path).is_dir():
            self.warn([f"the series {self.ct_series_choice!r} was asked for, but {path} is one image, not a DICOM "
                       "folder: it is read as it is"])

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
        recording = self.read_recording(path)
        self.set_calibration_recording(recording)
        return recording

    def read_recording(self, path: str | os.PathLike[str]) -> TrackingRecording:
        """A tracking recording with this controller's ports and transform names (a tool's name is its
        transform's: ``Stylus`` reads ``StylusToTracker`` unless ``[sensors] probe_transform`` says otherwise)."""
        from .io.recording import read_recording

        settings = self.settings
        named_by_tool = self.tool is not None and self.tool.name and settings.sensors.probe_transform is None
        if named_by_tool:
            settings = dataclasses.replace(settings, sensors=dataclasses.replace(
                settings.sensors, probe_transform=f"{self.tool.name}ToTracker"))
        try:
            return read_recording(path, settings, self.reference_sensor, self.probe_sensor)
        except EMRegError as exc:
            if named_by_tool and f"{self.tool.name}ToTrackerTransform" in str(exc):
                raise EMRegError(f"{exc} (the tool file {self.tool.source} names the tool {self.tool.name})") from None
            raise

    def case_recording(self, case: Case, role: str) -> TrackingRecording | None:
        """A case's recording ``role`` (``navigation``, ``board``); with a tool, read with its transform name."""
        if self.tool is None:
            return case.read_recording(role)
        path = getattr(case, role)
        return None if path is None else self.read_recording(path)

    def load_tool(self, path: str | os.PathLike[str]) -> ToolCalibration | None:
        """Use the tool of a tool file (``tool_calibration.json``, ITK transform, PLUS device set;
        :func:`EMRegModule.tool.read_tool`), or ``auto`` (None: the tip is solved when the frame is calibrated);
        drops the frame calibration and what follows."""
        from .tool import read_tool

        if str(path) == "auto":
            self.set_tool(None)
            self.tool_auto = True
            return None
        tool = read_tool(path, self.settings.tool.name)
        if self.settings.tool.name:
            tool.name = self.settings.tool.name
        self.note_inputs(tool=path)
        self.set_tool(tool)
        return tool

    def load_tool_from_settings(self) -> ToolCalibration | None:
        """The tool of ``[tool] calibration`` (relative to ``case.toml``'s folder), if the settings name one."""
        name = self.settings.tool.calibration
        if not name:
            return None
        path = Path(name)
        if name != "auto" and not path.is_absolute() and self.settings.source:
            path = Path(self.settings.source).parent / path
        return self.load_tool(path)

    def set_tool(self, tool: ToolCalibration | None) -> None:
        """Use a tool (None: the pinhole probe); drops the frame calibration and what follows."""
        self.tool = tool
        self.tool_auto = False
        self._invalidate(frame_calibration=True)

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

    def use_ports(self, reference_given: int | None, probe_given: int | None,
                  source: str = "registration.json") -> list[str]:
        """The ports of a consumer of the current registration (navigate, evaluate): for each sensor the port the
        user gave (command line, else ``case.toml [sensors]``; None: not given), else the port the
        registration's calibration used, else the spec's default (reference 1, probe 2). A given port that
        differs from the registration's is used (a re-cabled tracker) with a one-line warning, returned."""
        self._require(registration=self.registration)
        recorded = (self.registration.reference_sensor, self.registration.probe_sensor)
        chosen, warnings = choose_ports((reference_given, probe_given), recorded, source)
        sensors = self.settings.with_sensors(*chosen).sensors  # checked as [sensors]; the registration stays
        self.reference_sensor, self.probe_sensor = sensors.reference, sensors.probe
        self.navigation = self.evaluation = None
        return warnings

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
        """Use detected markers (e.g. read from ``markers.json``); drops the registration (and fiducials)."""
        self._invalidate()
        self.detection = detection
        self.fiducials = None

    def load_fiducials(self, path: str | os.PathLike[str]) -> DetectionResult | Fiducials:
        """Use the fiducials of a Slicer markups file, a PLUS device-set XML's landmarks
        (:func:`~EMRegModule.io.fiducials.read_fiducials`), or a ``markers.json`` (read as :meth:`load_detection`
        does: the CT markers' pinhole route); drops the registration."""
        from .io.fiducials import is_markers_file, read_fiducials

        if is_markers_file(path):
            return self.load_detection(path)
        fiducials = read_fiducials(path)
        self.note_inputs(fiducials=path)
        self.set_fiducials(fiducials)
        return fiducials

    def set_fiducials(self, fiducials: Fiducials) -> None:
        """Register onto fiducial points (a rigid point fit, no sensor offset) instead of CT markers; drops the
        registration and the detected markers."""
        self._invalidate(detection=True)
        self.fiducials = fiducials

    def calibrate_frame(self) -> FrameCalibration:
        """One point per marker pinhole in the Reference frame from the calibration recording."""
        self._require(calibration_recording=self.calibration_recording)
        from .calibration import calibrate_frame

        with self.progress.step("calibrating frame"):
            result = calibrate_frame(
                self.calibration_recording, self.reference_sensor, self.probe_sensor,
                self.settings.calibration, probe_axis=self.probe_axis or "auto",
                tool="auto" if self.tool_auto else self.tool, tool_still_radius_mm=self.settings.tool.still_radius_mm,
            )
        if result.solved_tool is not None:  # --tool auto: navigation and evaluation use the tip solved here
            self.tool = result.solved_tool
        self.set_frame_calibration(result)
        return result

    def set_frame_calibration(self, frame_calibration: FrameCalibration) -> None:
        """Use a frame calibration (e.g. read from ``frame_calibration.json``); drops the registration."""
        self._invalidate()
        self.frame_calibration = frame_calibration

    def register(self, targets_image: np.ndarray | None = None) -> RegistrationResult:
        """Pair markers with calibration points, solve the sensor offset l, fit ``ReferenceToImage``.

        ``targets_image`` (N, 3, LPS mm), when given, gets a predicted TRE in the result. With fiducials
        (:meth:`load_fiducials`) the fit is a plain rigid point fit without l
        (:func:`~EMRegModule.fiducial_registration.register_fiducials`).
        """
        self._require(detection=self._image_points, frame_calibration=self.frame_calibration)
        if self.detection is None:
            from .fiducial_registration import register_fiducials

            with self.progress.step("pairing and registering onto the fiducials"):
                result = register_fiducials(self.fiducials, self.frame_calibration, self.settings.registration,
                                            targets_image)
            self.registration = result
            self.navigation = None
            return result
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
        from .navigation import navigate_recording, unpaired_probe_note

        result = navigate_recording(
            recording, self.registration.reference_to_image, self.reference_sensor, self.probe_sensor,
            None if self.tool is None else self.tool.tip_to_probe,
        )
        note = unpaired_probe_note(recording, result, self.probe_sensor)
        if note and note not in recording.warnings:  # said with the recording's own warnings
            recording.warnings.append(note)
        self.checkpoints = self._check_navigation(result, recording)
        self.navigation = result
        return result

    def _check_navigation(self, result: NavigationResult, recording: TrackingRecording) -> Any:
        """Checkpoints at the detected markers' pinholes, reference jumps and the pose status of ``result``
        (:mod:`EMRegModule.checkpoints`); their warnings join the recording's."""
        from .checkpoints import check_navigation, pinholes_from_detection

        pinholes = (None if self.detection is None else
                    pinholes_from_detection(self.detection, self.registration.sensor_offset_l_mm))
        report = check_navigation(result, recording, pinholes, self.reference_sensor, self.settings.navigation)
        if pinholes is None:  # a point fit onto fiducials, or a registration folder without its markers
            report.note = "no detected markers (markers.json) beside the registration: no pinholes to check at"
        recording.warnings.extend(n for n in report.warnings() if n not in recording.warnings)
        return report

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
            self.evaluation = evaluate(self.registration.reference_to_image, self.reference_sensor,
                                       self.probe_sensor, self.settings.evaluation, navigation=navigation,
                                       targets=targets, board=board, nominal_edges_mm=self.settings.board.edges_mm,
                                       error_model=self.error_model, tolerant=tolerant, not_evaluated=not_evaluated,
                                       tip_to_probe=None if self.tool is None else self.tool.tip_to_probe,
                                       settings_file=self.settings.source)
        return self.evaluation

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

    # --- provenance and persistence -----------------------------------------------------------

    def note_inputs(self, **paths: str | os.PathLike[str] | None) -> None:
        """Record input files by role (``ct``, ``calibration``, ``navigation``, ``targets``, ``board``) for the
        provenance of the outputs made from them; a CT's sha256 is the one its read computes in the same pass
        (:class:`~EMRegModule.provenance.InputDigest`)."""
        for role, path in paths.items():
            if path is None:
                continue
            path = Path(path)
            digest: str | InputDigest = InputDigest(path) if role == "ct" else file_sha256(path)
            self._inputs[role] = (str(path), digest)

    def _provenance(self, roles: tuple[str, ...], uses: tuple[str, ...]) -> Provenance:
        """The provenance of an output made from the inputs ``roles`` and the upstream outputs ``uses``."""
        inputs: dict[str, dict[str, str]] = {}
        for name in uses:
            if name in self._made_from:
                inputs.update(self._made_from[name].inputs)
        for role in roles:
            if role in self._inputs:
                path, digest = self._inputs[role]
                inputs[role] = {"path": path, "sha256": digest if isinstance(digest, str) else digest.result()}
        used = {name: self._output_sha[name] for name in uses if name in self._output_sha}
        return Provenance(inputs, used, self.settings.digest(), self.settings.source, made_by=self.command)

    def _recorded(self, folder: OutputFolder, stage: str, provenance: Provenance,
                  sha256: dict[str, str] | None = None) -> None:
        folder.record(STAGE_OUTPUTS[stage], provenance, sha256)
        for name in STAGE_OUTPUTS[stage]:
            if (folder.path / name).exists():
                self._made_from[name] = provenance
                self._output_sha[name] = folder.sha256(name)

    def _read_output(self, name: str, path: Path, document_provenance: dict[str, Any] | None) -> None:
        """An upstream output read from a file: checked to belong where it lies, remembered for provenance."""
        check_belongs(path)
        provenance = Provenance.from_json(document_provenance)
        if provenance is not None:
            self._made_from[name] = provenance
        self._output_sha[name] = file_sha256(path)

    def load_detection(self, path: str | os.PathLike[str]) -> DetectionResult:
        """Use the markers of a ``markers.json`` (file or folder), checked to belong with its folder."""
        from .detection import read_detection

        path = Path(path)
        path = path / "markers.json" if path.is_dir() else path
        detection = read_detection(path)
        self._read_output("markers.json", path, detection.provenance)
        self.set_detection(detection)
        return detection

    def load_frame_calibration(self, path: str | os.PathLike[str]) -> FrameCalibration:
        """Use the points of a ``frame_calibration.json``, checked to belong with its folder."""
        from .calibration import read_frame_calibration

        calibration = read_frame_calibration(path)
        self._read_output("frame_calibration.json", Path(path), calibration.provenance)
        self.set_frame_calibration(calibration)
        return calibration

    def load_registration(self, path: str | os.PathLike[str]) -> RegistrationResult:
        """Use the transform of a ``registration.json``, checked as every consumer checks it (finite, rigid,
        FRE within ``[registration] max_fre_mm``) and to belong with its folder (a stale registration left
        in a reused output folder is refused)."""
        from .registration import read_registration

        path = Path(path)
        path = path / "registration.json" if path.is_dir() else path
        registration = read_registration(path, self.settings.registration.max_fre_mm)
        self._read_output("registration.json", path, registration.provenance)
        self.set_registration(registration)
        return registration

    def check_case_inputs(self, name: str, path: str | os.PathLike[str], case: Case) -> None:
        """Refuse an upstream output (read with ``load_*``) made from another calibration recording, CT or
        fiducials file than ``case``'s own."""
        check_inputs_match(path, self._made_from.get(name), {"calibration": case.calibration, "ct": case.ct,
                                                             "fiducials": case.fiducials})

    def save_detection(self, folder: OutputFolder) -> None:
        """``markers.json`` and ``markers.mrk.json`` into ``folder`` (atomic, recorded with provenance)."""
        from .detection import write_detection

        self._require(detection=self.detection)
        provenance = self._provenance(("ct",), ())
        self.detection.provenance = provenance.to_json()
        write_detection(self.detection, folder.path)
        self._recorded(folder, "detect", provenance)

    def save_frame_calibration(self, folder: OutputFolder) -> None:
        """``frame_calibration.json`` into ``folder``."""
        from .calibration import write_frame_calibration

        self._require(frame_calibration=self.frame_calibration)
        provenance = self._provenance(("calibration", "tool"), ())
        self.frame_calibration.provenance = provenance.to_json()
        write_frame_calibration(self.frame_calibration, folder.path / "frame_calibration.json")
        if self.frame_calibration.solved_tool is not None:  # --tool auto: the tip solved, for later commands
            from .tool import write_tool_calibration

            write_tool_calibration(self.frame_calibration.solved_tool, folder.path)
        self._recorded(folder, "calibrate", provenance)

    def save_registration(self, folder: OutputFolder) -> None:
        """``registration.json`` and ``ReferenceToImage.h5`` into ``folder``."""
        from .registration import write_registration

        self._require(registration=self.registration)
        provenance = self._provenance(("targets", "fiducials"), ("markers.json", "frame_calibration.json"))
        self.registration.provenance = provenance.to_json()
        write_registration(self.registration, folder.path)
        self._recorded(folder, "register", provenance)

    def save_navigation(self, folder: OutputFolder) -> None:
        """``navigation.csv`` into ``folder`` (its provenance lives in the folder's ``run.json``)."""
        from .navigation import write_navigation_csv

        self._require(navigation=self.navigation)
        provenance = self._provenance(("navigation", "tool"), ("registration.json",))
        write_navigation_csv(self.navigation, folder.path / "navigation.csv")
        if self.checkpoints is not None:
            from .checkpoints import CHECKPOINTS_JSON, write_checkpoints

            self.checkpoints.provenance = provenance.to_json()
            write_checkpoints(self.checkpoints, folder.path / CHECKPOINTS_JSON)
        self._recorded(folder, "navigate", provenance)

    def save_evaluation(self, folder: OutputFolder, evaluation: Evaluation) -> None:
        """``evaluation.json`` into ``folder``."""
        from .evaluation import write_evaluation

        provenance = self._provenance(("navigation", "targets", "board"), ("registration.json",))
        evaluation.provenance = provenance.to_json()
        write_evaluation(evaluation, folder.path / "evaluation.json")
        self._recorded(folder, "evaluate", provenance)

    def save_report(self, folder: OutputFolder, case_dir: Path | None, ct_read: Any = None) -> Path:
        """The verification report of ``folder`` (its outputs checked to belong together first); the CT
        the report read is kept for the Slicer bundle (:meth:`save_bundle`). ``ct_read``: a streamed read of the
        CT started earlier (:func:`EMRegModule.io.ct_stream.start_streamed_read`), used when it is the report's CT."""
        from .io.slicer_scene import bundle_needs_ct_image
        from .report.writer import HandedCT, write_report_keeping_ct

        used = self._adopt_outputs(folder)
        # else the report streams a CT it reads itself
        keep = bundle_needs_ct_image(_manifest_ct(folder.manifest, case_dir))
        image: Any = self.image if self.image is not None else ct_read
        if self.image is not None and not keep and not self.keep_ct:  # nothing needs the CT after the report: it is
            self.image, image = None, HandedCT(image)  # freed once used, before the rendering libraries load
        page, self._report_image = write_report_keeping_ct(folder.path, case_dir=case_dir, progress=self.progress,
                                                           image=image, keep_ct=keep, settings=self.settings)
        self._recorded(folder, "report", self._provenance((), tuple(used)))
        return page

    def record_report_outputs(self, folder: OutputFolder, bundle_sha256: str | None) -> None:
        """List a report written into ``folder`` by another process (``emreg report --batch``'s jobs) in its
        ``run.json``, with their sha256 and provenance, and its scene bundle when one was written
        (``bundle_sha256``: its sha256, computed as it was written)."""
        used = self._adopt_outputs(folder)
        provenance = self._provenance((), tuple(used))
        self._recorded(folder, "report", provenance)
        if bundle_sha256 is not None:
            self._recorded(folder, "bundle", self._bundle_provenance(provenance, folder, None),
                           dict.fromkeys(STAGE_OUTPUTS["bundle"], bundle_sha256))
            return
        outputs = folder.manifest.get("outputs")  # an earlier bundle is gone (not renewed): no longer listed
        if isinstance(outputs, dict) and any([outputs.pop(name, None) for name in STAGE_OUTPUTS["bundle"]]):
            folder.save()

    def _adopt_outputs(self, folder: OutputFolder) -> list[str]:
        """The outputs present in ``folder``, checked to belong together; their sha256 kept for provenance."""
        used = check_outputs(folder.path)
        for name in used:
            self._output_sha.setdefault(name, folder.sha256(name))
        return used

    def start_bundle(self, folder: OutputFolder, case_dir: Path | None, started: Any = None) -> Any:
        """Start writing ``EMReg.mrb`` in a separate process, to go on while the report renders (pass the
        result to :meth:`save_bundle`); None when it must be written here (no slicer-core, or a CT the bundle
        cannot copy from its file). ``started``: a bundle process started earlier for ``folder`` and held
        (:func:`~EMRegModule.io.slicer_scene.start_bundle_process`), released here once the outputs are checked
        (the caller cancels it if this raises)."""
        from .io.slicer_scene import start_bundle_process

        used = self._adopt_outputs(folder)
        job = started if started is not None else start_bundle_process(folder.path, case_dir)
        if job is not None:
            job.used = used
            job.release()
        return job

    def kept_bundle(self, folder: OutputFolder, case_dir: Path | None) -> Any:
        """``folder``'s ``EMReg.mrb`` when it is still the bundle :meth:`save_bundle` would write
        (:mod:`EMRegModule.bundle_state`; pass it to :meth:`save_bundle`), else None."""
        from .bundle_state import current_bundle

        kept = current_bundle(folder.path, folder.manifest, case_dir, self.settings.digest())
        return kept.start_check() if kept is not None else None

    def save_bundle(self, folder: OutputFolder, case_dir: Path | None, job: Any = None, kept: Any = None) -> str:
        """``EMReg.mrb``, the 3D Slicer scene of ``folder``'s outputs; a summary line. Optional: without
        slicer-core, or when it cannot be written, the other outputs stand and a warning says why.
        ``job``: the bundle started by :meth:`start_bundle` (waited for here). ``kept``: the bundle
        :meth:`kept_bundle` found up to date, kept when its file is confirmed unchanged (else written again)."""
        from .io.slicer_scene import bundle_needs_ct_image, write_run_bundle_hashed

        if kept is not None and kept.confirmed():
            return f"bundle: {kept.path} (up to date: kept)"
        if job is not None:
            with self.progress.step("writing the 3D Slicer scene bundle (in parallel)"):
                path, message, sha = job.result()
            used = job.used
        else:
            used = self._adopt_outputs(folder)
            image = self.image if self.image is not None else self._report_image  # the CT is not read again
            self._report_image = None
            if not bundle_needs_ct_image(_manifest_ct(folder.manifest, case_dir)):
                image = None  # the bundle copies the CT from its file: its memory is freed before slicer-core loads
                if not self.keep_ct:
                    self.image = None
            with self.progress.step("writing the 3D Slicer scene bundle"):
                path, message, sha = write_run_bundle_hashed(folder.path, case_dir, image)
        if path is None:
            self.warn([message])
        else:
            provenance = self._bundle_provenance(self._provenance((), tuple(used)), folder, case_dir)
            self._recorded(folder, "bundle", provenance, {path.name: sha} if sha else None)
        return f"bundle: {message}"

    @staticmethod
    def _bundle_provenance(provenance: Provenance, folder: OutputFolder, case_dir: Path | None) -> Provenance:
        """A bundle is made from the CT and the targets too: named, a later report keeps it while none of what
        it was made from changed (:mod:`EMRegModule.bundle_state`)."""
        from .bundle_state import bundle_inputs

        return dataclasses.replace(provenance, inputs={**provenance.inputs, **bundle_inputs(folder.manifest, case_dir)})

    # --- a whole run ---------------------------------------------------------------------------

    def run(self, case: Case, out: str | os.PathLike[str], report: bool = True) -> list[str]:
        """Every stage the case allows, in order, into the output folder ``out``; returns summary lines.

        OUT is refused when it would overwrite an input of the case; the outputs of an earlier run are
        moved to ``OUT/previous/`` before anything is written; every output is written atomically and
        listed with its provenance in ``OUT/run.json``, which also records the case, the CT, the ports,
        the summary and how the run ended (``status``: finished, refused, failed, interrupted). A stage
        that refuses (no safe answer) leaves none of its own or later outputs. An evaluation that cannot
        be made does not stop the run: the reason goes to ``run.json``, ``evaluation.json`` and stderr.
        ``report=False`` leaves out the report and the Slicer bundle (3D Slicer without pyvista).
        """
        check_case_image_side(case)
        inputs = {"ct": case.ct, "calibration": case.calibration, "navigation": case.navigation,
                  "targets": case.targets, "board": case.board, "fiducials": case.fiducials}
        settings_file = Path(self.settings.source) if self.settings.source else None
        refuse_out_over_inputs(out, [p for p in (*inputs.values(), settings_file) if p],
                               all_output_names(), case.folder)
        self.command = self.command if self.command != "emreg" else "emreg run"
        self.note_inputs(**inputs)
        if self.tool is None and not self.tool_auto:
            self.load_tool_from_settings()  # [tool] calibration = "FILE" (a --tool given first wins)
        folder = OutputFolder(out, self.command)
        summary: list[str] = []
        stage = "start"
        steps = (("calibrate", self._run_read_calibration), ("detect", self._run_detect),
                 ("calibrate", self._run_calibrate), ("register", self._run_register),
                 ("navigate", self._run_navigate), ("evaluate", self._run_evaluate), ("tre_map", self._run_tre_map))
        if report:
            steps += (("report", self._run_report), ("bundle", self._run_bundle))
        try:
            folder.start_run(self._run_record(case, summary))
            for name, step in steps:
                stage = name  # named in run.json if this stage fails
                step(case, folder, summary)
        except NoSafeAnswerError as exc:
            folder.remove_from(stage)
            summary.append(f"{stage}: refused: {exc}")
            folder.finish("refused", f"{stage}: {exc}")
            raise
        except (EMRegError, OSError) as exc:
            with contextlib.suppress(OSError):  # on a full disk even run.json may not be written
                folder.drop_unrecorded()  # a stage's outputs written before it failed (figures without their page)
                folder.finish("failed", f"{stage}: {exc}")
            raise
        except KeyboardInterrupt as exc:
            with signals_held(redeliver=False):  # a second Ctrl-C does not cut the record short
                folder.drop_unrecorded()  # an output written as the signal came, before run.json listed it
                folder.finish("interrupted", f"{stage}: interrupted ({str(exc) or 'SIGINT'})")
            raise
        except Exception:
            signal_name = interrupted_by()  # the signal's exception was lost in a VTK callback: still an interrupt
            if signal_name is None:
                raise
            with signals_held(redeliver=False):
                folder.drop_unrecorded()
                folder.finish("interrupted", f"{stage}: interrupted ({signal_name})")
            raise
        with signals_held() as pending:  # run.json says what the exit code says, even for a signal right now
            folder.finish("finished")
            if pending:
                folder.finish("interrupted", f"{stage}: interrupted as the run recorded its end (every output "
                                             "listed is complete)")
        return summary

    def _run_record(self, case: Case, summary: list[str]) -> dict[str, Any]:
        return {"case": str(case.folder.resolve()), "ct": str(case.ct.resolve()) if case.ct is not None else None,
                **({"fiducials": str(case.fiducials.resolve())} if case.ct is None else {}),
                "emreg_version": __version__,
                "reference_sensor": self.reference_sensor, "probe_sensor": self.probe_sensor,
                "summary": summary, "not_evaluated": {}, "settings_file": self.settings.source,
                "settings_sha256": self.settings.digest(), "settings": self.settings.to_json()}

    def _run_detect(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        if case.ct is None:  # a fiducial case: the image side is read, nothing to detect
            fiducials = self.load_fiducials(case.fiducials)
            summary.append(f"detect: skipped (no CT): {len(fiducials)} fiducials from {case.fiducials.name}")
            return
        detection = self.load_ct_and_detect(case.ct)
        self.save_detection(folder)
        if detection.ct_series is not None:
            folder.manifest["ct_series"] = detection.ct_series
        summary.append(f"detect: {len(detection.markers)} markers, {len(detection.rejected)} rejected")

    def _run_read_calibration(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        """Read the calibration recording and check its ports before the CT is: a malformed file or a wrong
        port is refused at once rather than after a detection (seconds to minutes on a large scan)."""
        if case.calibration is None:
            return
        from .tracking import sensor_pair

        recording = self.load_calibration_recording(case.calibration)
        sensor_pair(recording, self.reference_sensor, self.probe_sensor)

    def _run_calibrate(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        if case.calibration is None:  # a detection-only run: say so, a forgotten file is the likelier story
            note = (f"no calibration recording in {case.folder} (calibration.csv or calibration.seq.mha): the "
                    "markers are detected, nothing is registered")
            self.warn([note])
            summary.append(f"calibrate: {note}")
            return
        calibration = self.calibrate_frame()  # from the recording read before the CT
        self.save_frame_calibration(folder)
        if self.detection is None:  # otherwise the registration repeats them
            self.warn(calibration.warnings)
        summary.append(f"calibrate: {len(calibration.points)} {'pinholes' if self.tool is None else 'touches'}")

    def _run_register(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        if self._image_points is None or self.frame_calibration is None:
            return
        try:
            targets = case.read_targets()
        except NoSafeAnswerError:
            raise
        except EMRegError:  # optional: only the TRE and its prediction use them; the evaluation says why
            targets = None
        registration = self.register(None if targets is None else targets[1])
        self.save_registration(folder)
        self.warn(registration.warnings)
        summary.append(f"register: FRE {registration.fre_mm:.2f} mm, {offset_summary(registration)}, "
                       f"{len(registration.pairs)} pairs")

    def _run_navigate(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        if self.registration is None or case.navigation is None:
            return
        try:
            recording = self.case_recording(case, "navigation")
            navigation = self.navigate_recording(recording)
        except NoSafeAnswerError:
            raise
        except EMRegError as exc:  # the registration stands; an unusable navigation recording is reported
            folder.manifest["not_evaluated"]["navigation"] = str(exc)
            self.warn([f"navigation not made: {exc}"])
            summary.append(f"navigate: not made: {exc}")
            return
        self.warn(recording.warnings)
        self.save_navigation(folder)
        summary.append(f"navigate: {len(navigation)} probe samples"
                       + ("" if self.checkpoints is None else f"; {self.checkpoints.summary()}"))

    def _run_evaluate(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        """The optional evaluation: a part that cannot be made is "not evaluated" with its reason in
        ``run.json``, ``evaluation.json``, the report and on stderr; the run goes on."""
        if self.registration is None or (case.navigation is None and case.board is None and case.targets is None):
            return
        unreadable: dict[str, str] = {}
        inputs: dict[str, Any] = {}
        if (case.navigation is None) != (case.targets is None):  # the TRE needs both: say which one is missing
            unreadable["tre"] = (f"{case.folder}: a navigation recording but no targets.mrk.json"
                                 if case.targets is None else
                                 f"{case.folder}: targets.mrk.json but no navigation recording (navigation.csv or "
                                 "navigation.seq.mha)")
        for part, read in (("tre", lambda: (self.case_recording(case, "navigation"), case.read_targets())),
                           ("board", lambda: self.case_recording(case, "board"))):
            if part in unreadable or (part == "board" and case.board is None):
                continue
            try:
                inputs[part] = read()
            except NoSafeAnswerError:
                raise
            except EMRegError as exc:  # an unreadable optional recording: that part is not evaluated
                unreadable[part] = str(exc)
        navigation, targets = inputs.get("tre") or (None, None)
        evaluation = self.evaluate(navigation, targets, inputs.get("board"), tolerant=True, not_evaluated=unreadable)
        for part, reason in evaluation.not_evaluated.items():
            folder.manifest["not_evaluated"][part] = reason
            self.warn([f"{'TRE' if part == 'tre' else part} not evaluated: {reason}"])
        if evaluation.tre is not None:
            self.warn(evaluation.tre.warnings)  # what the measured TRE says of the prediction
        if inputs.get("board") is not None:  # the navigation recording's were said when it was read
            self.warn(inputs["board"].warnings)  # rows left out, time segments: kept in evaluation.json too
        self.save_evaluation(folder, evaluation)
        summary.extend(evaluation.summary())

    def _run_tre_map(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        """``tre_map.nrrd``: the predicted RMS TRE over the CT's space (with the measured tracking error)."""
        if self.error_model is None or self.detection is None:  # the map covers the CT's space: none without a CT
            return
        from .tre_map import write_tre_map

        evaluation = self.evaluation
        tracking_rms = evaluation.tre.tracking_rms_mm if evaluation is not None and evaluation.tre else None
        write_tre_map(folder.path / "tre_map.nrrd", self.error_model, self.detection.image,
                      None if tracking_rms is None else tracking_rms**2)
        uses = ("registration.json", "evaluation.json") if evaluation is not None else ("registration.json",)
        self._recorded(folder, "tre_map", self._provenance((), uses))

    def _run_report(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        page = self.save_report(folder, case.folder)
        summary.append(f"report: {page}")

    def _run_bundle(self, case: Case, folder: OutputFolder, summary: list[str]) -> None:
        summary.append(self.save_bundle(folder, case.folder))

    def warn(self, warnings: list[str]) -> None:
        """A stage's warnings (also kept in its output) on stderr, one line each (even when quiet)."""
        for warning in warnings:
            print(f"{self.command}: warning: {warning}", file=sys.stderr)

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


def offset_summary(registration: RegistrationResult) -> str:
    """The sensor offset of a summary line: ``l = 14.20 mm``, or that a point fit onto fiducials has none."""
    if getattr(registration, "point_fit", False):  # (a registration-like object without it: the pinhole route)
        return "point fit onto fiducials (no sensor offset)"
    return f"l = {registration.sensor_offset_l_mm:.2f} mm"


def check_case_image_side(case: Case) -> None:
    """A case registers onto its CT's markers or onto ``fiducials.mrk.json``: refused (one line) with neither
    or both."""
    if case.ct is None and case.fiducials is None:
        raise EMRegError(f"{case.folder}: no CT found (ct.nrrd, ct.nii.gz, ct.mha or a ct/ DICOM folder) and no "
                         "fiducials.mrk.json")
    if case.ct is not None and case.fiducials is not None:
        raise EMRegError(f"{case.folder}: holds both a CT ({case.ct.name}) and fiducials.mrk.json: register onto one "
                         "of them; move the other out of the case folder")


def _manifest_ct(run: Any, case_dir: Path | None = None) -> str | None:
    """The CT path a run record (``run.json``'s content, e.g. an :class:`OutputFolder`'s manifest) names, else
    the CT of ``case_dir`` (a report's ``--case`` over per-stage outputs): :func:`~EMRegModule.io.case.run_ct_path`."""
    from .io.case import run_ct_path

    return run_ct_path(run, case_dir)


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

