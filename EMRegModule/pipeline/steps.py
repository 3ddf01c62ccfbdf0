"""The work of each stage of the table (:mod:`EMRegModule.pipeline.stages`): how it runs (``run_*``: a
:class:`~.job.Job` in, a :class:`~.job.Made` out), how its result is read from its file (``read_*``) and written
into an output folder (``write_*``).

A ``run_*`` given a case (``emreg run``, the 3D Slicer module) takes its optional inputs from it and skips what
the case does not allow (a summary line says so where a forgotten file is the likelier story); given none (a
per-stage command) it takes them from the job's options and refuses a missing prerequisite
(:class:`~.results.WorkflowError`).

All poses are in millimetres; ``ReferenceToImage`` maps Reference-sensor coordinates into the CT's LPS image space.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .. import names
from ..core.calibration import calibrate_frame
from ..core.detection import DetectionResult
from ..core.evaluation import Evaluation, evaluate
from ..core.fiducial_registration import register_fiducials
from ..core.navigation import NavigationResult, navigate_recording, unpaired_probe_note
from ..core.registration import register
from ..core.tracking import TrackingRecording, sensor_pair
from ..core.tre_map import predicted_tre_map
from ..errors import EMRegError, NoSafeAnswerError
from ..io.atomic import atomic_write_json
from ..io.calibration_json import read_frame_calibration, write_frame_calibration
from ..io.checkpoints_json import write_checkpoints
from ..io.dicom_read import NarrowVoxelsError
from ..io.evaluation_json import write_evaluation
from ..io.fiducials import is_markers_file, read_fiducials
from ..io.image import open_ct
from ..io.markers_json import read_detection, write_detection
from ..io.navigation_csv import write_navigation_csv
from ..io.provenance import Provenance
from ..io.registration_files import read_registration, write_registration
from ..io.tool_files import write_tool_calibration
from ..settings import Settings
from .background import import_in_background
from .inputs import (
    Inputs,
    case_recording,
    check_plan_in_ct,
    checked_image,
    read_recording,
    series_choice,
    series_unused,
)
from .job import Job, Made, Read
from .navigating import check_navigation, error_model, guide
from .results import WorkflowResults, offset_summary

# --- detect: the markers in the CT (image space, LPS) --------------------------------------------------------------


def run_detect(job: Job) -> Made:
    """The markers of the CT, each one's origin and axis (image space, LPS mm). ``emreg run`` (a case): the case's
    CT read and detected at once, or, without a CT, its fiducials read. Options: ``ct`` (a path: read and detected
    on the slices read as the rest arrives, the same result as reading then detecting, sooner; without it the CT in
    memory is detected) and ``keep_image`` (False: the CT is not kept, ``emreg detect`` writes only the markers)."""
    case = job.case
    if case is not None and case.ct is None:  # a fiducial case: the image side is read, nothing to detect
        read = read_detect(case.fiducials, job.inputs.settings)
        found = next(iter(read.results.values()))
        return Made(read.results, read=read,
                    summary=(f"detect: skipped (no CT): {len(found)} fiducials from {case.fiducials.name}",))
    ct = case.ct if case is not None else job.options.get("ct")
    if ct is None:
        return Made({"detection": _detect_in_memory(job)})
    job.warn(series_unused(job.inputs.settings, ct))
    keep_image = job.options.get("keep_image", True)
    try:
        detection, inputs = _open_and_detect(job, ct, compact=True, keep_image=keep_image)
    except NarrowVoxelsError as exc:
        job.progress.message(f"[emreg] {exc}: reading the CT again with int32 voxels")
        detection, inputs = _open_and_detect(job, ct, compact=False, keep_image=keep_image)
    if case is not None:  # a plan outside this CT: refused before any output is written
        check_plan_in_ct(inputs.plan, detection, str(ct))
    return Made({"detection": detection}, inputs=inputs,
                summary=(f"detect: {len(detection.markers)} markers, {len(detection.rejected)} rejected",),
                manifest={} if detection.ct_series is None else {"ct_series": detection.ct_series})


def _detect_in_memory(job: Job) -> DetectionResult:
    """Detection on the CT held in memory (``inputs.image``)."""
    inputs = job.inputs
    WorkflowResults.require(image=inputs.image)
    from ..core.detection.detect import detect_markers  # scipy and VTK: see DEFERRED_IMPORTS

    result = detect_markers(inputs.image, inputs.marker_model, inputs.settings.detection, job.progress)
    result.ct_series = inputs.ct_series
    return result


def _open_and_detect(job: Job, path: str | os.PathLike[str], compact: bool,
                     keep_image: bool) -> tuple[DetectionResult, Inputs]:
    """The markers of the CT at ``path`` read with one voxel type (``compact``: int16 where it fits), and the inputs
    holding the CT read (``keep_image=False``: only where it was read from: the CT was read for the detection)."""
    inputs = job.inputs
    with job.progress.step("opening CT"):
        fill = open_ct(path, series_choice(inputs.settings), compact=compact, voxels_only=not keep_image)
    # The detection stage (scipy, VTK: ~0.4 s holding the GIL) is imported while the slices are read (or, for a
    # DICOM series indexed in its files, the folder hashed), not while open_ct scans a DICOM folder's headers: every
    # file the scan opens gives the GIL away and waits up to a switch interval to take it back from the import (a
    # 653-file series: emreg detect 2.41 -> 2.34 s alternated directly, 2.31 -> 2.29 s in bench_read_ct's rounds;
    # medians of 11). A CT refused while it is opened is refused before the import starts.
    # all of it: detection may fork (.detection.examiners)
    import_in_background("EMRegModule.core.detection.detect").wait()
    from ..core.detection.detect import detect_markers  # scipy and VTK: see DEFERRED_IMPORTS

    try:
        result = detect_markers(fill, inputs.marker_model, inputs.settings.detection, job.progress)
        image = fill.result()  # the checksum is verified only at the end
    except BaseException as exc:
        fill.cancel()
        if isinstance(exc, EMRegError):
            read_error = fill.read_error()  # a bad file explains a failed detection: report the file
            if isinstance(read_error, EMRegError) and read_error is not exc:
                raise read_error from None
        raise
    kept = checked_image(image, str(path)) if fill.voxels is None else None  # voxels only: nothing kept
    result.ct_series = fill.series
    return result, inputs.replace(image=kept, image_source=str(path), ct_series=fill.series)


def read_detect(path: str | os.PathLike[str], settings: Settings) -> Read:
    """The image side from a file: the markers of a ``markers.json`` (file or folder; the CT markers' pinhole
    route), or the fiducials of a Slicer markups file or a PLUS device-set XML's landmarks
    (:func:`~EMRegModule.io.fiducials.read_fiducials`: a rigid point fit onto them, no sensor offset)."""
    path = Path(path)
    if is_markers_file(path):
        path = path / names.MARKERS_JSON if path.is_dir() else path
        detection = read_detection(path)
        return Read({"detection": detection}, path, names.MARKERS_JSON, detection.provenance)
    return Read({"fiducials": read_fiducials(path)}, path, input_role="fiducials")


def write_detect(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    results.require(detection=results.detection)
    results.detection.provenance = provenance.to_json()
    write_detection(results.detection, out)


# --- calibrate: one point per marker pinhole in the Reference frame ------------------------------------------------


def prepare_calibrate(job: Job) -> Inputs:
    """Read the case's calibration recording and check its ports before the CT is: a malformed file or a wrong
    port is refused at once rather than after a detection (seconds to minutes on a large scan)."""
    case, inputs = job.case, job.inputs
    if case is None or case.calibration is None:
        return inputs
    recording = read_recording(case.calibration, inputs)
    sensor_pair(recording, inputs.reference_sensor, inputs.probe_sensor)
    return inputs.replace(calibration_recording=recording)


def run_calibrate(job: Job) -> Made:
    """The frame calibration of the calibration recording (``--tool auto``: the tool's tip solved from its
    pivoting touches, which the navigation and the evaluation then use)."""
    case, inputs = job.case, job.inputs
    if case is not None and case.calibration is None:  # a detection-only run: a forgotten file is likelier
        note = (f"no calibration recording in {case.folder} (calibration.csv or calibration.seq.mha): the "
                "markers are detected, nothing is registered")
        job.warn([note])
        return Made(summary=(f"calibrate: {note}",))
    WorkflowResults.require(calibration_recording=inputs.calibration_recording)
    settings = inputs.settings
    with job.progress.step("calibrating frame"):
        result = calibrate_frame(
            inputs.calibration_recording, inputs.reference_sensor, inputs.probe_sensor, settings.calibration,
            probe_axis=settings.sensors.probe_axis or "auto", tool="auto" if inputs.tool_auto else inputs.tool,
            tool_still_radius_mm=settings.tool.still_radius_mm,
        )
    if result.solved_tool is not None:
        inputs = inputs.replace(tool=result.solved_tool)
    if case is not None and job.results.detection is None:  # otherwise the registration repeats them
        job.warn(result.warnings)
    return Made({"frame_calibration": result, "calibrated_here": True}, inputs=inputs,
                summary=(f"calibrate: {len(result.points)} {'pinholes' if inputs.tool is None else 'touches'}",))


def read_calibrate(path: str | os.PathLike[str], settings: Settings) -> Read:
    calibration = read_frame_calibration(path)
    return Read({"frame_calibration": calibration}, Path(path), names.FRAME_CALIBRATION_JSON, calibration.provenance)


def write_calibrate(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    results.require(frame_calibration=results.frame_calibration)
    results.frame_calibration.provenance = provenance.to_json()
    write_frame_calibration(results.frame_calibration, out / names.FRAME_CALIBRATION_JSON)
    if results.frame_calibration.solved_tool is not None:  # --tool auto: the tip solved, for later commands
        write_tool_calibration(results.frame_calibration.solved_tool, out)


# --- register: pairing, the sensor offset l, ReferenceToImage ------------------------------------------------------


def run_register(job: Job) -> Made:
    """Pair markers with calibration points, solve the sensor offset l, fit ``ReferenceToImage``; onto fiducials, a
    plain rigid point fit without l (:func:`~EMRegModule.core.fiducial_registration.register_fiducials`). Option
    ``targets`` ((N, 3) LPS mm; a case's ``targets.mrk.json``): a predicted TRE at them in the result."""
    results, inputs = job.results, job.inputs
    if job.case is not None:
        if results.image_points is None or results.frame_calibration is None:
            return Made()
        try:
            targets = job.case.read_targets()
        except NoSafeAnswerError:
            raise
        except EMRegError:  # optional: only the TRE and its prediction use them; the evaluation says why
            targets = None
        targets_image = None if targets is None else targets[1]
    else:
        targets_image = job.options.get("targets")
    results.require(detection=results.image_points, frame_calibration=results.frame_calibration)
    settings = inputs.settings
    if results.detection is None:
        with job.progress.step("pairing and registering onto the fiducials"):
            result = register_fiducials(results.fiducials, results.frame_calibration, settings.registration,
                                        targets_image)
    else:
        with job.progress.step("pairing and registering"):
            result = register(results.detection, results.frame_calibration, inputs.marker_model,
                              settings.registration, targets_image=targets_image,
                              probe_axis=settings.sensors.probe_axis)
    if job.case is not None:
        job.warn(result.warnings)
    return Made({"registration": result}, summary=(
        f"register: FRE {result.fre_mm:.2f} mm, {offset_summary(result)}, {len(result.pairs)} pairs",))


def read_register(path: str | os.PathLike[str], settings: Settings) -> Read:
    """A ``registration.json`` (file or folder), checked as every consumer checks it (finite, rigid, FRE within
    ``[registration] max_fre_mm``)."""
    path = Path(path)
    path = path / names.REGISTRATION_JSON if path.is_dir() else path
    registration = read_registration(path, settings.registration.max_fre_mm)
    return Read({"registration": registration}, path, names.REGISTRATION_JSON, registration.provenance)


def write_register(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    results.require(registration=results.registration)
    results.registration.provenance = provenance.to_json()
    write_registration(results.registration, out)


# --- navigate: every probe sample into image space (paper Eq. 11-12) -----------------------------------------------


def run_navigate(job: Job) -> Made:
    """The probe samples of a recording (option ``recording``; a case's navigation recording) in image space, with
    their checkpoints and, with a plan, the guidance numbers. In a case, a recording that cannot be navigated
    leaves the registration standing: it is reported (not made) and the run goes on."""
    case = job.case
    if case is None:
        return _navigate(job, job.options["recording"])
    if job.results.registration is None or case.navigation is None:
        return Made()
    try:
        recording = case_recording(case, "navigation", job.inputs)
        made = _navigate(job, recording)
    except NoSafeAnswerError:
        raise
    except EMRegError as exc:
        job.warn([f"navigation not made: {exc}"])
        return Made(not_evaluated={"navigation": str(exc)}, summary=(f"navigate: not made: {exc}",))
    job.warn(recording.warnings)
    return made


def _navigate(job: Job, recording: TrackingRecording) -> Made:
    results, inputs = job.results, job.inputs
    results.require(registration=results.registration)
    result = navigate_recording(recording, results.registration.reference_to_image, inputs.reference_sensor,
                                inputs.probe_sensor, inputs.tip_to_probe)
    note = unpaired_probe_note(recording, result, inputs.probe_sensor)
    if note and note not in recording.warnings:  # said with the recording's own warnings
        recording.warnings.append(note)
    checkpoints = check_navigation(results, inputs.settings, inputs.reference_sensor, result, recording)
    guided = guide(inputs.plan, result, inputs.tool, error_model(results.registration, inputs.settings))
    line = (f"navigate: {len(result)} probe samples; {checkpoints.summary()}"
            + ("" if guided is None else f"; {guided.summary()}"))
    return Made({"navigation": result, "checkpoints": checkpoints, "guidance": guided}, summary=(line,))


def write_navigate(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    """``navigation.csv`` (its provenance lives in the folder's ``run.json``), ``checkpoints.json`` and, with a
    plan, ``navigation.json``."""
    results.require(navigation=results.navigation)
    write_navigation_csv(results.navigation, out / names.NAVIGATION_CSV)
    if results.checkpoints is not None:
        results.checkpoints.provenance = provenance.to_json()
        write_checkpoints(results.checkpoints, out / names.CHECKPOINTS_JSON)
    if results.guidance is not None:
        atomic_write_json(out / names.NAVIGATION_JSON, {**results.guidance.to_json(),
                                                        "provenance": provenance.to_json()})


# --- evaluate: the TRE at the targets and the board table ----------------------------------------------------------


def run_evaluate(job: Job) -> Made:
    """TRE at the targets (labels, (K, 3) LPS mm) from a navigation recording, and the board table from a board
    recording, with the current registration (``[evaluation]``, ``[board]`` settings). Options: ``navigation``,
    ``targets``, ``board``. In a case the evaluation is optional: a part that cannot be made is "not evaluated"
    with its reason (in ``run.json``, ``evaluation.json``, the report and on stderr) and the run goes on."""
    case = job.case
    if case is None:
        options = job.options
        return Made({"evaluation": _evaluate(job, options.get("navigation"), options.get("targets"),
                                             options.get("board"))})
    if job.results.registration is None or (case.navigation is None and case.board is None and case.targets is None):
        return Made()
    unreadable: dict[str, str] = {}
    inputs: dict[str, Any] = {}
    if (case.navigation is None) != (case.targets is None):  # the TRE needs both: say which one is missing
        unreadable["tre"] = (f"{case.folder}: a navigation recording but no targets.mrk.json"
                             if case.targets is None else
                             f"{case.folder}: targets.mrk.json but no navigation recording (navigation.csv or "
                             "navigation.seq.mha)")
    for part, read in (("tre", lambda: (case_recording(case, "navigation", job.inputs), case.read_targets())),
                       ("board", lambda: case_recording(case, "board", job.inputs))):
        if part in unreadable or (part == "board" and case.board is None):
            continue
        try:
            inputs[part] = read()
        except NoSafeAnswerError:
            raise
        except EMRegError as exc:  # an unreadable optional recording: that part is not evaluated
            unreadable[part] = str(exc)
    navigation, targets = inputs.get("tre") or (None, None)
    evaluation = _evaluate(job, navigation, targets, inputs.get("board"), tolerant=True, not_evaluated=unreadable)
    for part, reason in evaluation.not_evaluated.items():
        job.warn([f"{'TRE' if part == 'tre' else part} not evaluated: {reason}"])
    if evaluation.tre is not None:
        job.warn(evaluation.tre.warnings)  # what the measured TRE says of the prediction
    if inputs.get("board") is not None:  # the navigation recording's were said when it was read
        job.warn(inputs["board"].warnings)  # rows left out, time segments: kept in evaluation.json too
    return Made({"evaluation": evaluation}, not_evaluated=dict(evaluation.not_evaluated),
                summary=tuple(evaluation.summary()))


def _evaluate(job: Job, navigation: TrackingRecording | None, targets: Any, board: TrackingRecording | None,
              tolerant: bool = False, not_evaluated: dict[str, str] | None = None) -> Evaluation:
    """The evaluation (``tolerant``: a part that cannot be evaluated is "not evaluated" with its reason instead of
    an error; ``not_evaluated``: parts whose recording could not be read, and why). The poses that
    ``navigation.csv`` marks INVALID (the checkpoints and tracker flags of the navigation) are left out of the TRE
    and counted."""
    results, inputs = job.results, job.inputs
    results.require(registration=results.registration)
    settings = inputs.settings

    def pose_status(navigated: NavigationResult, recording: TrackingRecording) -> Any:
        """``OK`` / ``INVALID`` per pose, as ``navigation.csv`` has it (the checkpoints' warnings are navigate's)."""
        check_navigation(results, settings, inputs.reference_sensor, navigated, recording, warn=False)
        return navigated.status

    with job.progress.step("evaluating"):
        return evaluate(results.registration.reference_to_image, inputs.reference_sensor, inputs.probe_sensor,
                        settings.evaluation, navigation=navigation, targets=targets, board=board,
                        nominal_edges_mm=settings.board.edges_mm,
                        error_model=error_model(results.registration, settings), tolerant=tolerant,
                        not_evaluated=not_evaluated, tip_to_probe=inputs.tip_to_probe,
                        settings_file=settings.source, pose_status=pose_status)


def write_evaluate(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    results.require(evaluation=results.evaluation)
    results.evaluation.provenance = provenance.to_json()
    write_evaluation(results.evaluation, out / names.EVALUATION_JSON)


# --- tre_map: the predicted RMS TRE over the CT's space ------------------------------------------------------------


def run_tre_map(job: Job) -> Made:
    """The predicted RMS TRE over the CT's space (with the measured tracking error); none without a CT (the map
    covers its space) or an error model."""
    results, settings = job.results, job.inputs.settings
    model = error_model(results.registration, settings)
    if model is None or results.detection is None:
        return Made()
    evaluation = results.evaluation
    tracking_rms = evaluation.tre.tracking_rms_mm if evaluation is not None and evaluation.tre else None
    return Made({"tre_map": predicted_tre_map(model, results.detection.image,
                                              None if tracking_rms is None else tracking_rms**2)})


def write_tre_map_file(results: WorkflowResults, out: Path, provenance: Provenance) -> None:
    """``tre_map.nrrd`` (its provenance lives in the folder's ``run.json``)."""
    from ..io.tre_map import write_tre_map  # SimpleITK: see DEFERRED_IMPORTS

    write_tre_map(out / names.TRE_MAP_NRRD, results.tre_map)


# --- report and bundle: written and recorded by the exporter -------------------------------------------------------


def _case_dir(job: Job) -> Path | None:
    return job.case.folder if job.case is not None else job.options.get("case_dir")


def run_report(job: Job) -> Made:
    """The verification report of the output folder (its outputs checked to belong together first)."""
    page = job.exporter.save_report(job.folder, _case_dir(job), job.ct)
    return Made(summary=(f"report: {page}",))


def run_bundle(job: Job) -> Made:
    """``EMReg.mrb``, the 3D Slicer scene of the output folder (optional: a warning says why when it is not)."""
    return Made(summary=(job.exporter.save_bundle(job.folder, _case_dir(job), job.ct),))
