"""One typed view of a run folder (OUT): what the stages wrote, read once by the stages' own readers, and its
record ``run.json``: every consumer reads it here (:func:`read_manifest`, :func:`recorded_run`; the one parser,
:func:`~EMRegModule.io.provenance.read_manifest`, sits below this module with the belonging check that needs it).

The report (:func:`EMRegModule.report.inputs.load_report_inputs`), the scene bundle
(:func:`EMRegModule.slicer_export.run_scene.collect_run`) and the 3D Slicer Logic (from the results it holds in
memory, the same fields) all work from a :class:`RunFolder`; none of them parses the files itself.

Frames and units: image space is the CT's LPS physical space (mm); the Reference frame is the reference sensor's
(mm). ``ReferenceToImage`` maps Reference to image space.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..core.calibration import FrameCalibration
from ..core.detection.result import DetectionResult
from ..core.evaluation import Evaluation
from ..core.registration import RegistrationResult
from ..errors import EMRegError
from ..names import (
    CHECKPOINTS_JSON,
    EVALUATION_JSON,
    FRAME_CALIBRATION_JSON,
    MARKERS_JSON,
    NAVIGATION_CSV,
    NAVIGATION_JSON,
    REGISTRATION_JSON,
    ROBOT_CALIBRATION_JSON,
    ROBOT_GO_JSON,
    ROBOT_TARGET_JSON,
    TRE_MAP_NRRD,
)
from ..stages import made_before_export
from .atomic import read_json
from .calibration_json import read_frame_calibration
from .evaluation_json import read_evaluation
from .markers_json import read_detection
from .navigation_csv import read_guidance_columns, read_navigation_csv
from .provenance import check_belongs
from .provenance import read_manifest as parse_manifest
from .registration_files import read_registration

T = TypeVar("T")

#: The robot's outputs a run folder may hold: field of :class:`RunFolder`, file name, what it is.
ROBOT_OUTPUTS = (("robot_calibration", ROBOT_CALIBRATION_JSON, "robot calibration"),
                 ("robot_target", ROBOT_TARGET_JSON, "robot target"),
                 ("robot_go", ROBOT_GO_JSON, "robot-go result"))


@dataclass(frozen=True, eq=False)
class RunFolder:
    """The outputs of one run; None where a file is absent (or, read tolerantly, turned down: see ``notes``).

    - ``out_dir``: the output folder (None: results held in memory, not yet written: the Slicer Logic's).
    - ``manifest``: ``run.json`` (the command, its inputs and their sha256, the outputs), as a JSON object.
    - ``detection``: ``markers.json``: marker origins and unit axes in image space (LPS, mm).
    - ``frame_calibration``: ``frame_calibration.json``: one pinhole point per marker, Reference frame (mm); a
      tool's ``TipToProbe`` (probe frame, mm) in its ``tool``.
    - ``registration``: ``registration.json``: ``ReferenceToImage`` (4x4, Reference -> image LPS, mm), the sensor
      offset l (mm), the pairs with their residuals (mm).
    - ``evaluation``: ``evaluation.json``: TRE at the targets (mm) and the board's edges.
    - ``navigation_positions``: ``navigation.csv``'s probe positions (N, 3; image LPS, mm), ``navigation_labels``
      its labels.
    - ``checkpoints``: ``checkpoints.json`` when it holds at least one checkpoint (errors in mm, times in s).
    - ``guidance``: ``navigation.json`` (a navigation with a plan: the plan, the predicted error at the target, the
      closest approach) and ``guidance_series``: the time and guidance columns of ``navigation.csv``
      (:func:`~EMRegModule.io.navigation_csv.read_guidance_columns`); None without a plan.
    - ``tre_map_path``: ``tre_map.nrrd`` (predicted TRE, mm, on an image-space grid) when it is there.
    - the robot's (issue 39), as JSON objects: ``robot_calibration`` (``robot_calibration.json`` of ``emreg handeye``
      or ``robot-calibrate``: ``SensorToFlange``, ``TrackerToBase``, 4x4 mm, ``time_offset_s``, the residuals and
      frames), ``robot_target`` (``robot_target.json``: ``FlangeToBase``, the guide's pose, the plan, the predicted
      error, mm) and ``robot_go`` (``robot_go.json``: the closed-loop measurements of ``emreg robot-go --out``).
    - ``notes``: why files were turned down (tolerant reading only), in the order read.
    """

    out_dir: Path | None
    manifest: Mapping[str, Any] | None = None
    detection: DetectionResult | None = None
    frame_calibration: FrameCalibration | None = None
    registration: RegistrationResult | None = None
    evaluation: Evaluation | None = None
    navigation_positions: np.ndarray | None = None
    navigation_labels: list[str] | None = None
    checkpoints: Mapping[str, Any] | None = None
    guidance: Mapping[str, Any] | None = None
    guidance_series: Mapping[str, np.ndarray] | None = None
    tre_map_path: Path | None = None
    robot_calibration: Mapping[str, Any] | None = None
    robot_target: Mapping[str, Any] | None = None
    robot_go: Mapping[str, Any] | None = None
    notes: tuple[str, ...] = ()

    @property
    def has_robot(self) -> bool:
        """True when the folder holds one of the robot's outputs."""
        return any(document is not None for document in (self.robot_calibration, self.robot_target, self.robot_go))


def read_manifest(out_dir: str | os.PathLike[str], notes: list[str] | None = None) -> dict[str, Any] | None:
    """``OUT/run.json`` as a JSON object (None when absent). ``notes`` given: an unreadable or damaged one is None
    and a note there; otherwise it raises :class:`EMRegError`."""
    return _noted(lambda: parse_manifest(out_dir), notes)


def recorded_run(out_dir: str | os.PathLike[str] | None) -> dict[str, Any] | None:
    """``OUT/run.json`` when there is one to read, for what is decided before a report or bundle starts (None
    otherwise: what is wrong is said by the command that reads OUT)."""
    if out_dir is None or not Path(out_dir).is_dir():
        return None
    try:
        return parse_manifest(out_dir)
    except EMRegError:
        return None


def read_run_folder(out_dir: str | os.PathLike[str], manifest: Mapping[str, Any] | None,
                    max_fre_mm: float = math.inf, tolerant: bool = True) -> RunFolder:
    """Read the stage outputs of OUT (``manifest``: its ``run.json``, from :func:`read_manifest`).

    ``registration.json`` is always checked (:func:`~.registration_files.read_registration`: finite, rigid,
    FRE at most ``max_fre_mm``, mm) and one that fails raises: it is never shown as if it could be trusted. The
    other files: ``tolerant``, one that its reader turns down is None with a note; else it raises
    :class:`EMRegError`. ``checkpoints.json`` that cannot be read is None (it only adds a chart).
    """
    out = Path(out_dir)
    notes: list[str] = []
    kept = notes if tolerant else None
    registration = read_registration(out / REGISTRATION_JSON, max_fre_mm) if (out / REGISTRATION_JSON).exists() \
        else None
    detection = _read(out / MARKERS_JSON, read_detection, kept)
    frame_calibration = _read(out / FRAME_CALIBRATION_JSON, read_frame_calibration, kept)
    evaluation = _read(out / EVALUATION_JSON, read_evaluation, kept)
    navigation = _read(out / NAVIGATION_CSV, read_navigation_csv, kept)
    positions, labels = navigation if navigation is not None else (None, None)
    guidance = _read(out / NAVIGATION_JSON, _read_json_object("navigation summary"), kept) \
        if navigation is not None else None
    series = _read(out / NAVIGATION_CSV, read_guidance_columns, kept) if guidance is not None else None
    robot = {name: _read(out / file, _read_json_object(what), kept) for name, file, what in ROBOT_OUTPUTS}
    return RunFolder(out_dir=out, manifest=manifest, detection=detection, frame_calibration=frame_calibration,
                     registration=registration, evaluation=evaluation, navigation_positions=positions,
                     navigation_labels=labels, checkpoints=_read_checkpoints(out / CHECKPOINTS_JSON),
                     guidance=guidance, guidance_series=series,
                     tre_map_path=out / TRE_MAP_NRRD if (out / TRE_MAP_NRRD).is_file() else None, **robot,
                     notes=tuple(notes))


def _read(path: Path, read: Callable[[Path], T], notes: list[str] | None) -> T | None:
    """``read(path)`` when the file exists; with ``notes``, its :class:`EMRegError` becomes one (and None)."""
    return _noted(lambda: read(path), notes) if path.is_file() else None


def _noted(read: Callable[[], T], notes: list[str] | None) -> T | None:
    """``read()``; with ``notes``, its :class:`EMRegError` becomes one there (and None), else it is raised."""
    try:
        return read()
    except EMRegError as exc:
        if notes is None:
            raise
        notes.append(str(exc))
        return None


def _read_json_object(what: str) -> Callable[[Path], dict[str, Any]]:
    def read(path: Path) -> dict[str, Any]:
        document = read_json(path, what)
        if not isinstance(document, dict):
            raise EMRegError(f"{path}: not a {what} (expected a JSON object)")
        return document

    return read


def _read_checkpoints(path: Path) -> dict[str, Any] | None:
    """``checkpoints.json`` when it holds at least one checkpoint (None otherwise, or unreadable)."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) and document.get("checkpoints") else None


def recorded_series_uid(record: Any) -> str | None:
    """The Series Instance UID of the DICOM series a run record (``run.json``) or ``markers.json`` names under
    ``ct_series``: the series the markers were detected in (None: none named)."""
    block = record.get("ct_series") if isinstance(record, dict) else None
    uid = block.get("series_instance_uid") if isinstance(block, dict) else None
    return str(uid) if uid else None


def check_outputs(folder: str | os.PathLike[str]) -> list[str]:
    """Check that every output in ``folder`` belongs to it (:func:`~EMRegModule.io.provenance.check_belongs`);
    returns the names of the stage outputs present (files), in workflow order."""
    folder = Path(folder)
    present = [n for n in made_before_export() if (folder / n).is_file()]
    for name in present:
        check_belongs(folder / name)
    return present
