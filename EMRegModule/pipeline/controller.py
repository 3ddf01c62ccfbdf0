"""The workflow controller: sequences the stages of :mod:`EMRegModule.stages` for the ``emreg`` command
and the 3D Slicer module's Logic.

It holds the inputs (CT, calibration recording, tool, sensor ports), refuses a step whose prerequisites are
missing (saying what is missing), and leaves the rest to its parts: the results and what a new input makes
stale (:class:`~EMRegModule.pipeline.results.WorkflowResults`, ``results``), the provenance of every output
saved (:class:`~EMRegModule.pipeline.recorder.RunRecorder`, ``recorder``), and the report and the scene bundle
(:class:`~EMRegModule.pipeline.exporters.Exporter`, ``exporter``).

All poses are in millimetres; ``ReferenceToImage`` maps Reference-sensor coordinates into the CT's LPS image
space.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import __version__
from ..errors import EMRegError, NoSafeAnswerError
from ..interrupts import interrupted_by, signals_held
from ..io.case import Case
from ..io.output_folder import OutputFolder, all_output_names, refuse_out_over_inputs
from ..marker_model import MarkerModel
from ..names import FRAME_CALIBRATION_JSON, MARKERS_JSON, REGISTRATION_JSON, TRE_MAP_NRRD
from ..progress import QUIET, Progress
from ..settings import Settings, choose_ports
from ..stages import STAGE, STAGES
from .background import import_in_background
from .exporters import Exporter
from .navigating import Planner, check_navigation
from .recorder import RunRecorder
from .results import WorkflowResults, offset_summary

if TYPE_CHECKING:  # the stage modules import heavy libraries; load them only when used
    import SimpleITK as sitk

    from ..core.calibration import FrameCalibration
    from ..core.detection import DetectionResult
    from ..core.error_model import ErrorModel
    from ..core.evaluation import Evaluation
    from ..core.fiducials import Fiducials
    from ..core.navigation import NavigationResult
    from ..core.registration import RegistrationResult
    from ..core.tool import ToolCalibration
    from ..core.tracking import TrackingRecording


class EMRegController:
    """Sequences the EMReg workflow; usable without any GUI.

    ``settings`` is the typed, checked ``case.toml`` (:class:`~EMRegModule.settings.Settings`;
    defaults when None); each stage gets its own table. ``command`` names the command in provenance and warnings.
    """

    def __init__(self, settings: Settings | None = None, progress: Progress | None = None,
                 command: str = "emreg") -> None:
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
        self._calibrated: FrameCalibration | None = None  # the one calibrate_frame made (its touches: tool tips)
        self.results = WorkflowResults()
        self.recorder = RunRecorder(self.settings, command)
        self.planner = Planner(self.results, self.recorder, self.settings)  # the plan guided to (``planner.plan``)
        self.exporter = Exporter(self.recorder, self.settings, self.progress)

    @classmethod
    def for_case(cls, case: Case, progress: Progress | None = None, command: str = "emreg") -> EMRegController:
        """A controller configured with a case folder's ``case.toml``."""
        return cls(case.settings, progress, command)

    # --- inputs -----------------------------------------------------------------------------
    def load_ct(self, path: str | os.PathLike[str]) -> sitk.Image:
        """Read the CT (file or DICOM folder); drops detection and everything after it."""
        from ..io.image import open_ct

        _warn_series_unused(self, path)
        with self.progress.step("reading CT"):
            fill = open_ct(path, _series_choice(self.settings))
            # during the read, after the scan (_open_and_detect)
            import_in_background("EMRegModule.core.detection.detect")
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
        from ..io.dicom_read import NarrowVoxelsError

        _warn_series_unused(self, path)
        try:
            return _open_and_detect(self, path, compact=True, keep_image=keep_image)
        except NarrowVoxelsError as exc:
            self.progress.message(f"[emreg] {exc}: reading the CT again with int32 voxels")
            return _open_and_detect(self, path, compact=False, keep_image=keep_image)

    def set_image(self, image: sitk.Image, source: str = "CT") -> None:
        """Use an image already in memory (e.g. a Slicer volume node converted to SimpleITK)."""
        from ..io.ct_checks import check_ct_image

        check_ct_image(image, source)  # geometry and voxel values (NaN / inf refused)
        self.image = image
        self.image_source = source
        self.ct_series = None
        self.results.drop("detect")

    def load_calibration_recording(self, path: str | os.PathLike[str]) -> TrackingRecording:
        """Read the frame-calibration recording; drops the frame calibration and what follows."""
        recording = self.read_recording(path)
        self.set_calibration_recording(recording)
        return recording

    def read_recording(self, path: str | os.PathLike[str]) -> TrackingRecording:
        """A tracking recording with this controller's ports and transform names (a tool's name is its
        transform's: ``Stylus`` reads ``StylusToTracker`` unless ``[sensors] probe_transform`` says otherwise)."""
        from ..io.recording import read_recording

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
        :func:`EMRegModule.io.tool_files.read_tool`), or ``auto`` (None: the tip is solved when the frame is
        calibrated); drops the frame calibration and what follows."""
        from ..io.tool_files import read_tool

        if str(path) == "auto":
            self.set_tool(None)
            self.tool_auto = True
            return None
        tool = read_tool(path, self.settings.tool.name)
        if self.settings.tool.name:
            tool.name = self.settings.tool.name
        self.recorder.note_inputs(tool=path)
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
        """Use a tool (None: the pinhole probe); drops the navigation and evaluation (they map its tip), and the frame
        calibration on when calibrate_frame made it from its touches (one read from a file stays)."""
        self.tool, self.tool_auto = tool, False
        made_here = self.results.frame_calibration is not None and self.results.frame_calibration is self._calibrated
        for stage in ("calibrate",) if made_here else ("navigate", "evaluate"):
            self.results.drop(stage)

    def set_calibration_recording(self, recording: TrackingRecording) -> None:
        self.calibration_recording = recording
        self.results.drop("calibrate")

    def set_sensors(self, reference_sensor: int | None = None, probe_sensor: int | None = None) -> None:
        """Change the sensor ports (checked as ``[sensors]``: 1..4, two different ports); a change drops
        the frame calibration and what follows."""
        current = self.settings.with_sensors(self.reference_sensor, self.probe_sensor)
        sensors = current.with_sensors(reference_sensor, probe_sensor).sensors
        if (sensors.reference, sensors.probe) != (self.reference_sensor, self.probe_sensor):
            self.reference_sensor, self.probe_sensor = sensors.reference, sensors.probe
            self.results.drop("calibrate")

    def use_ports(self, reference_given: int | None, probe_given: int | None,
                  source: str = REGISTRATION_JSON) -> list[str]:
        """The ports of a consumer of the current registration (navigate, evaluate): for each sensor the port the
        user gave (command line, else ``case.toml [sensors]``; None: not given), else the port the
        registration's calibration used, else the spec's default (reference 1, probe 2). A given port that
        differs from the registration's is used (a re-cabled tracker) with a one-line warning, returned."""
        self.results.require(registration=self.results.registration)
        recorded = (self.results.registration.reference_sensor, self.results.registration.probe_sensor)
        chosen, warnings = choose_ports((reference_given, probe_given), recorded, source)
        sensors = self.settings.with_sensors(*chosen).sensors  # checked as [sensors]; the registration stays
        self.reference_sensor, self.probe_sensor = sensors.reference, sensors.probe
        self.results.made("register")  # the navigation and the evaluation use the ports
        return warnings

    def detect_markers(self) -> DetectionResult:
        """Find the markers in the CT and estimate each one's pose (image space, LPS)."""
        self.results.require(image=self.image)
        from ..core.detection import detect_markers

        result = detect_markers(self.image, self.marker_model, self.settings.detection, self.progress)
        result.ct_series = self.ct_series
        self.set_detection(result)
        return result

    def set_detection(self, detection: DetectionResult) -> None:
        """Use detected markers (e.g. read from ``markers.json``); drops the registration (and fiducials)."""
        self.results.made("detect")
        self.results.detection = detection
        self.results.fiducials = None

    def load_fiducials(self, path: str | os.PathLike[str]) -> DetectionResult | Fiducials:
        """Use the fiducials of a Slicer markups file, a PLUS device-set XML's landmarks
        (:func:`~EMRegModule.io.fiducials.read_fiducials`), or a ``markers.json`` (read as :meth:`load_detection`
        does: the CT markers' pinhole route); drops the registration."""
        from ..io.fiducials import is_markers_file, read_fiducials

        if is_markers_file(path):
            return self.load_detection(path)
        fiducials = read_fiducials(path)
        self.recorder.note_inputs(fiducials=path)
        self.set_fiducials(fiducials)
        return fiducials

    def set_fiducials(self, fiducials: Fiducials) -> None:
        """Register onto fiducial points (a rigid point fit, no sensor offset) instead of CT markers; drops the
        registration and the detected markers."""
        self.results.drop("detect")
        self.results.fiducials = fiducials

    def calibrate_frame(self) -> FrameCalibration:
        """One point per marker pinhole in the Reference frame from the calibration recording."""
        self.results.require(calibration_recording=self.calibration_recording)
        from ..core.calibration import calibrate_frame

        with self.progress.step("calibrating frame"):
            result = calibrate_frame(
                self.calibration_recording, self.reference_sensor, self.probe_sensor,
                self.settings.calibration, probe_axis=self.settings.sensors.probe_axis or "auto",
                tool="auto" if self.tool_auto else self.tool, tool_still_radius_mm=self.settings.tool.still_radius_mm,
            )
        if result.solved_tool is not None:  # --tool auto: navigation and evaluation use the tip solved here
            self.tool = result.solved_tool
        self.set_frame_calibration(result)
        self._calibrated = result
        return result

    def set_frame_calibration(self, frame_calibration: FrameCalibration) -> None:
        """Use a frame calibration (e.g. read from ``frame_calibration.json``); drops the registration."""
        self.results.made("calibrate")
        self.results.frame_calibration = frame_calibration

    def register(self, targets_image: np.ndarray | None = None) -> RegistrationResult:
        """Pair markers with calibration points, solve the sensor offset l, fit ``ReferenceToImage``.

        ``targets_image`` (N, 3, LPS mm), when given, gets a predicted TRE in the result. With fiducials
        (:meth:`load_fiducials`) the fit is a plain rigid point fit without l
        (:func:`~EMRegModule.core.fiducial_registration.register_fiducials`).
        """
        self.results.require(detection=self.results.image_points, frame_calibration=self.results.frame_calibration)
        if self.results.detection is None:
            from ..core.fiducial_registration import register_fiducials

            with self.progress.step("pairing and registering onto the fiducials"):
                result = register_fiducials(self.results.fiducials, self.results.frame_calibration,
                                            self.settings.registration,
                                            targets_image)
            self.set_registration(result)
            return result
        from ..core.registration import register

        with self.progress.step("pairing and registering"):
            result = register(
                self.results.detection, self.results.frame_calibration, self.marker_model,
                self.settings.registration, targets_image=targets_image, probe_axis=self.settings.sensors.probe_axis,
            )
        self.set_registration(result)
        return result

    def set_registration(self, registration: RegistrationResult) -> None:
        """Use a registration (e.g. read from ``registration.json``)."""
        self.results.made("register")
        self.results.registration = registration

    def navigate_recording(self, recording: TrackingRecording) -> NavigationResult:
        """Map every probe sample of a recording into image space (paper Eq. 11-12)."""
        self.results.require(registration=self.results.registration)
        from ..core.navigation import navigate_recording, unpaired_probe_note

        result = navigate_recording(
            recording, self.results.registration.reference_to_image, self.reference_sensor, self.probe_sensor,
            None if self.tool is None else self.tool.tip_to_probe,
        )
        note = unpaired_probe_note(recording, result, self.probe_sensor)
        if note and note not in recording.warnings:  # said with the recording's own warnings
            recording.warnings.append(note)
        results = self.results
        results.checkpoints = check_navigation(results, self.settings, self.reference_sensor, result, recording)
        results.guidance = self.planner.guide(result, self.tool, error_model(results.registration, self.settings))
        self.results.navigation = result
        return result

    def pose_status(self, navigation: NavigationResult, recording: TrackingRecording) -> np.ndarray:
        """``OK`` / ``INVALID`` per pose of ``navigation`` (made from ``recording``), as ``navigation.csv`` has it (the
        checkpoints' warnings are navigate's: not repeated)."""
        check_navigation(self.results, self.settings, self.reference_sensor, navigation, recording, warn=False)
        return navigation.status

    def evaluate(self, navigation: TrackingRecording | None = None,
                 targets: tuple[list[str], np.ndarray] | None = None,
                 board: TrackingRecording | None = None, tolerant: bool = False,
                 not_evaluated: dict[str, str] | None = None) -> Evaluation:
        """TRE at ``targets`` (labels, (K, 3) LPS mm) from a navigation recording, and the board table
        from a board recording, with the current registration (``[evaluation]``, ``[board]`` settings).

        ``tolerant`` (a run): a part that cannot be evaluated is "not evaluated" with its reason in the
        result instead of an error; ``not_evaluated``: parts whose recording could not be read, and why. The poses
        that ``navigation.csv`` marks INVALID (the checkpoints and tracker flags of :meth:`navigate_recording`) are
        left out of the TRE and counted."""
        self.results.require(registration=self.results.registration)
        from ..core.evaluation import evaluate

        with self.progress.step("evaluating"):
            self.results.evaluation = evaluate(self.results.registration.reference_to_image, self.reference_sensor,
                                       self.probe_sensor, self.settings.evaluation, navigation=navigation,
                                       targets=targets, board=board, nominal_edges_mm=self.settings.board.edges_mm,
                                       error_model=error_model(self.results.registration, self.settings),
                                       tolerant=tolerant, not_evaluated=not_evaluated,
                                       tip_to_probe=None if self.tool is None else self.tool.tip_to_probe,
                                       settings_file=self.settings.source, pose_status=self.pose_status)
        return self.results.evaluation

    # --- outputs ------------------------------------------------------------------------------

    def load_detection(self, path: str | os.PathLike[str]) -> DetectionResult:
        """Use the markers of a ``markers.json`` (file or folder), checked to belong with its folder."""
        from ..io.markers_json import read_detection

        path = Path(path)
        path = path / MARKERS_JSON if path.is_dir() else path
        detection = read_detection(path)
        self.recorder.read_output(MARKERS_JSON, path, detection.provenance)
        self.set_detection(detection)
        return detection

    def load_frame_calibration(self, path: str | os.PathLike[str]) -> FrameCalibration:
        """Use the points of a ``frame_calibration.json``, checked to belong with its folder."""
        from ..io.calibration_json import read_frame_calibration

        calibration = read_frame_calibration(path)
        self.recorder.read_output(FRAME_CALIBRATION_JSON, Path(path), calibration.provenance)
        self.set_frame_calibration(calibration)
        return calibration

    def load_registration(self, path: str | os.PathLike[str]) -> RegistrationResult:
        """Use the transform of a ``registration.json``, checked as every consumer checks it (finite, rigid,
        FRE within ``[registration] max_fre_mm``) and to belong with its folder (a stale registration left
        in a reused output folder is refused)."""
        from ..io.registration_files import read_registration

        path = Path(path)
        path = path / REGISTRATION_JSON if path.is_dir() else path
        registration = read_registration(path, self.settings.registration.max_fre_mm)
        self.recorder.read_output(REGISTRATION_JSON, path, registration.provenance)
        self.set_registration(registration)
        return registration

    def save(self, stage: str, folder: OutputFolder) -> None:
        """Write ``stage``'s current result (``detect`` ... ``evaluate``) into ``folder``, recorded with provenance."""
        self.recorder.save(stage, folder, self.results)

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
        recorder = self.recorder
        recorder.command = recorder.command if recorder.command != "emreg" else "emreg run"
        self.recorder.note_inputs(**inputs)
        if self.tool is None and not self.tool_auto:
            self.load_tool_from_settings()  # [tool] calibration = "FILE" (a --tool given first wins)
        self.planner.for_run(case)  # [navigation] plan = "FILE" (a --plan given first wins)
        folder = OutputFolder(out, recorder.command)
        summary: list[str] = []
        stage = "start"
        stages = [s.name for s in STAGES if report or not s.export]
        steps = [(name, PREPARE[name]) for name in stages if name in PREPARE] + [(name, STEPS[name]) for name in stages]
        try:
            folder.start_run(_run_record(self, case, summary))
            for name, step in steps:
                stage = name  # named in run.json if this stage fails
                step(self, case, folder, summary)
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


def _run_record(controller: EMRegController, case: Case, summary: list[str]) -> dict[str, Any]:
    return {"case": str(case.folder.resolve()), "ct": str(case.ct.resolve()) if case.ct is not None else None,
            **({"fiducials": str(case.fiducials.resolve())} if case.ct is None else {}),
            "emreg_version": __version__,
            "reference_sensor": controller.reference_sensor, "probe_sensor": controller.probe_sensor,
            "summary": summary, "not_evaluated": {}, "settings_file": controller.settings.source,
            "settings_sha256": controller.settings.digest(), "settings": controller.settings.to_json()}


def _run_detect(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    if case.ct is None:  # a fiducial case: the image side is read, nothing to detect
        fiducials = controller.load_fiducials(case.fiducials)
        summary.append(f"detect: skipped (no CT): {len(fiducials)} fiducials from {case.fiducials.name}")
        return
    detection = controller.load_ct_and_detect(case.ct)
    controller.planner.check_in_ct(str(case.ct))  # a plan outside this CT: refused before any output is written
    controller.save("detect", folder)
    if detection.ct_series is not None:
        folder.manifest["ct_series"] = detection.ct_series
    summary.append(f"detect: {len(detection.markers)} markers, {len(detection.rejected)} rejected")


def _run_read_calibration(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    """Read the calibration recording and check its ports before the CT is: a malformed file or a wrong
    port is refused at once rather than after a detection (seconds to minutes on a large scan)."""
    if case.calibration is None:
        return
    from ..core.tracking import sensor_pair

    recording = controller.load_calibration_recording(case.calibration)
    sensor_pair(recording, controller.reference_sensor, controller.probe_sensor)


def _run_calibrate(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    if case.calibration is None:  # a detection-only run: say so, a forgotten file is the likelier story
        note = (f"no calibration recording in {case.folder} (calibration.csv or calibration.seq.mha): the "
                "markers are detected, nothing is registered")
        controller.recorder.warn([note])
        summary.append(f"calibrate: {note}")
        return
    calibration = controller.calibrate_frame()  # from the recording read before the CT
    controller.save("calibrate", folder)
    if controller.results.detection is None:  # otherwise the registration repeats them
        controller.recorder.warn(calibration.warnings)
    summary.append(f"calibrate: {len(calibration.points)} {'pinholes' if controller.tool is None else 'touches'}")


def _run_register(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    if controller.results.image_points is None or controller.results.frame_calibration is None:
        return
    try:
        targets = case.read_targets()
    except NoSafeAnswerError:
        raise
    except EMRegError:  # optional: only the TRE and its prediction use them; the evaluation says why
        targets = None
    registration = controller.register(None if targets is None else targets[1])
    controller.save("register", folder)
    controller.recorder.warn(registration.warnings)
    summary.append(f"register: FRE {registration.fre_mm:.2f} mm, {offset_summary(registration)}, "
                   f"{len(registration.pairs)} pairs")


def _run_navigate(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    if controller.results.registration is None or case.navigation is None:
        return
    try:
        recording = controller.case_recording(case, "navigation")
        navigation = controller.navigate_recording(recording)
    except NoSafeAnswerError:
        raise
    except EMRegError as exc:  # the registration stands; an unusable navigation recording is reported
        folder.manifest["not_evaluated"]["navigation"] = str(exc)
        controller.recorder.warn([f"navigation not made: {exc}"])
        summary.append(f"navigate: not made: {exc}")
        return
    controller.recorder.warn(recording.warnings)
    controller.save("navigate", folder)
    checkpoints = controller.results.checkpoints
    guided = controller.results.guidance
    summary.append(f"navigate: {len(navigation)} probe samples" + ("" if checkpoints is None else
                                                                   f"; {checkpoints.summary()}")
                   + ("" if guided is None else f"; {guided.summary()}"))


def _run_evaluate(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    """The optional evaluation: a part that cannot be made is "not evaluated" with its reason in
    ``run.json``, ``evaluation.json``, the report and on stderr; the run goes on."""
    if controller.results.registration is None or (
            case.navigation is None and case.board is None and case.targets is None):
        return
    unreadable: dict[str, str] = {}
    inputs: dict[str, Any] = {}
    if (case.navigation is None) != (case.targets is None):  # the TRE needs both: say which one is missing
        unreadable["tre"] = (f"{case.folder}: a navigation recording but no targets.mrk.json"
                             if case.targets is None else
                             f"{case.folder}: targets.mrk.json but no navigation recording (navigation.csv or "
                             "navigation.seq.mha)")
    for part, read in (("tre", lambda: (controller.case_recording(case, "navigation"), case.read_targets())),
                       ("board", lambda: controller.case_recording(case, "board"))):
        if part in unreadable or (part == "board" and case.board is None):
            continue
        try:
            inputs[part] = read()
        except NoSafeAnswerError:
            raise
        except EMRegError as exc:  # an unreadable optional recording: that part is not evaluated
            unreadable[part] = str(exc)
    navigation, targets = inputs.get("tre") or (None, None)
    evaluation = controller.evaluate(navigation, targets, inputs.get("board"), tolerant=True, not_evaluated=unreadable)
    for part, reason in evaluation.not_evaluated.items():
        folder.manifest["not_evaluated"][part] = reason
        controller.recorder.warn([f"{'TRE' if part == 'tre' else part} not evaluated: {reason}"])
    if evaluation.tre is not None:
        controller.recorder.warn(evaluation.tre.warnings)  # what the measured TRE says of the prediction
    if inputs.get("board") is not None:  # the navigation recording's were said when it was read
        controller.recorder.warn(inputs["board"].warnings)  # rows left out, time segments: kept in evaluation.json too
    controller.save("evaluate", folder)
    summary.extend(evaluation.summary())

def _run_tre_map(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    """``tre_map.nrrd``: the predicted RMS TRE over the CT's space (with the measured tracking error)."""
    results = controller.results
    model = error_model(results.registration, controller.settings)
    if model is None or results.detection is None:  # the map covers the CT's space: none without a CT
        return
    from ..core.tre_map import predicted_tre_map
    from ..io.tre_map import write_tre_map

    evaluation = results.evaluation
    tracking_rms = evaluation.tre.tracking_rms_mm if evaluation is not None and evaluation.tre else None
    write_tre_map(folder.path / TRE_MAP_NRRD, predicted_tre_map(model, results.detection.image,
                                                                None if tracking_rms is None else tracking_rms**2))
    controller.recorder.record(folder, "tre_map", controller.recorder.provenance("tre_map"))


def _run_report(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    page = controller.exporter.save_report(folder, case.folder, controller)
    summary.append(f"report: {page}")


def _run_bundle(controller: EMRegController, case: Case, folder: OutputFolder, summary: list[str]) -> None:
    summary.append(controller.exporter.save_bundle(folder, case.folder, controller))


#: How ``emreg run`` executes each stage of :data:`~EMRegModule.stages.STAGES` (in the table's order), and
#: what it checks first, before the long stages: the calibration recording is read and its ports checked before
#: the CT is (a malformed file or a wrong port is refused at once rather than after a detection).
Step = Callable[[EMRegController, Case, OutputFolder, list[str]], None]
STEPS: dict[str, Step] = {"detect": _run_detect, "calibrate": _run_calibrate, "register": _run_register,
                          "navigate": _run_navigate, "evaluate": _run_evaluate, "tre_map": _run_tre_map,
                          "report": _run_report, "bundle": _run_bundle}
PREPARE: dict[str, Step] = {"calibrate": _run_read_calibration}
assert set(STEPS) == set(STAGE), "every stage of the table runs"


def error_model(registration: RegistrationResult | None, settings: Settings) -> ErrorModel | None:
    """The end-to-end error model of ``registration`` (``[evaluation]`` priors), or None."""
    if registration is None or registration.error is None:
        return None
    from ..core.error_model import ErrorModel

    priors = settings.evaluation
    return ErrorModel.with_priors(registration.reference_to_image, registration.error, priors.reference_error_mm,
                                  priors.reference_error_deg, priors.placement_error_mm)


def _series_choice(settings: Settings) -> str | None:
    """``[ct] series`` (a Series Instance UID or a series number) forcing the DICOM series, or None."""
    value = settings.ct.series
    return None if value is None else str(value)


def check_case_image_side(case: Case) -> None:
    """A case registers onto its CT's markers or onto ``fiducials.mrk.json``: refused (one line) with neither
    or both."""
    if case.ct is None and case.fiducials is None:
        raise EMRegError(f"{case.folder}: no CT found (ct.nrrd, ct.nii.gz, ct.mha or a ct/ DICOM folder) and no "
                         "fiducials.mrk.json")
    if case.ct is not None and case.fiducials is not None:
        raise EMRegError(f"{case.folder}: holds both a CT ({case.ct.name}) and fiducials.mrk.json: register onto one "
                         "of them; move the other out of the case folder")




def _open_and_detect(controller: EMRegController, path: str | os.PathLike[str], compact: bool,
                     keep_image: bool) -> DetectionResult:
    """:meth:`EMRegController.load_ct_and_detect` with one voxel type (``compact``: int16 where it fits)."""
    from ..io.image import open_ct

    with controller.progress.step("opening CT"):
        fill = open_ct(path, _series_choice(controller.settings), compact=compact, voxels_only=not keep_image)
    # The detection stage (scipy, VTK: ~0.4 s holding the GIL) is imported while the slices are read (or, for a
    # DICOM series indexed in its files, the folder hashed), not while open_ct scans a DICOM folder's headers: every
    # file the scan opens gives the GIL away and waits up to a switch interval to take it back from the import (a
    # 653-file series: emreg detect 2.41 -> 2.34 s alternated directly, 2.31 -> 2.29 s in bench_read_ct's rounds;
    # medians of 11). A CT refused while it is opened is refused before the import starts.
    # all of it: detection may fork (.detection.examiners)
    import_in_background("EMRegModule.core.detection.detect").wait()
    from ..core.detection import detect_markers

    try:
        result = detect_markers(fill, controller.marker_model, controller.settings.detection, controller.progress)
        image = fill.result()  # the checksum is verified only at the end
    except BaseException as exc:
        fill.cancel()
        if isinstance(exc, EMRegError):
            read_error = fill.read_error()  # a bad file explains a failed detection: report the file
            if isinstance(read_error, EMRegError) and read_error is not exc:
                raise read_error from None
        raise
    if fill.voxels is None:
        controller.set_image(image, str(path))
    else:  # read for the detection only (``keep_image=False``): ``image`` is only the geometry, nothing kept
        controller.image, controller.image_source = None, str(path)
        controller.results.drop("detect")
    controller.ct_series = result.ct_series = fill.series
    controller.set_detection(result)
    return result


def _warn_series_unused(controller: EMRegController, path: str | os.PathLike[str]) -> None:
    """A series forced (``--series``, ``[ct] series``) for a CT that is one image, not a DICOM folder, is said
    to be ignored rather than silently ignored."""
    if _series_choice(controller.settings) is not None and not Path(path).is_dir():
        controller.recorder.warn([f"the series {_series_choice(controller.settings)!r} was asked for, but {path} is "
                                  "one image, not a DICOM "
                   "folder: it is read as it is"])

