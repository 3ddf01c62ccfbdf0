"""What a report is made of: the typed outputs of a run (:class:`~EMRegModule.io.run_folder.RunFolder`, read back by
the stages' own readers), the case's settings and targets, and its CT.

A file that is missing is None; one that a reader turns down is None with a note
(shown as a warning), never a crash. The CT starts being read as soon as it is known
(:func:`EMRegModule.io.image.open_ct`, on a background thread) so that the rest of the report
is prepared while its voxels arrive.

Frames: positions are image space (CT LPS, mm) unless they say Reference.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.calibration import FrameCalibration
from ..core.detection.result import DetectionResult
from ..core.evaluation import Evaluation
from ..core.registration import RegistrationResult
from ..errors import EMRegError
from ..io.case import find_ct, open_case
from ..io.ct_handle import CTHandle
from ..io.ct_stream import start_streamed_read
from ..io.image import open_ct
from ..io.markups import read_markups
from ..io.run_folder import RunFolder, read_manifest, read_run_folder, recorded_series_uid
from ..marker_model import MarkerModel
from ..names import (
    EVALUATION_JSON,
    FRAME_CALIBRATION_JSON,
    MARKERS_JSON,
    NAVIGATION_CSV,
    REGISTRATION_JSON,
    ROBOT_CALIBRATION_JSON,
    ROBOT_GO_JSON,
    ROBOT_TARGET_JSON,
    RUN_JSON,
)
from ..settings import Settings
from .ct_memo import load_ct_memo, memo_candidates, recorded_ct_sha256

if TYPE_CHECKING:
    import SimpleITK as sitk

    from ..io.ct_handle import CTHandle

INPUT_NAMES = (MARKERS_JSON, FRAME_CALIBRATION_JSON, REGISTRATION_JSON, NAVIGATION_CSV, EVALUATION_JSON, RUN_JSON,
               ROBOT_CALIBRATION_JSON, ROBOT_TARGET_JSON, ROBOT_GO_JSON)


@dataclass
class ReportInputs:
    """Everything found for one report; None where absent. Positions in image space (LPS mm).

    ``folder`` is the run's outputs (the stage results below are its); ``ct`` is the case's CT, possibly still
    being read (``ct.result()`` waits for it); ``settings`` the case's checked ``case.toml`` (defaults when
    unreadable); ``notes`` the inputs that could not be read.
    """

    out_dir: Path
    case_dir: Path | None = None
    run: dict | None = None
    folder: RunFolder = None  # type: ignore[assignment]  # set in __post_init__: OUT read, nothing in it yet
    ct: CTHandle | None = None
    ct_path: Path | None = None
    ct_series: str | int | None = None  # a DICOM folder's series, as ``--series`` takes it
    targets_labels: list[str] | None = None
    targets_positions: np.ndarray | None = None
    settings: Settings = field(default_factory=Settings)
    model: MarkerModel = field(default_factory=MarkerModel)
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.folder is None:
            self.folder = RunFolder(self.out_dir)

    @property
    def detection(self) -> DetectionResult | None:
        return self.folder.detection

    @property
    def frame_calibration(self) -> FrameCalibration | None:
        return self.folder.frame_calibration

    @property
    def registration(self) -> RegistrationResult | None:
        return self.folder.registration

    @property
    def evaluation(self) -> Evaluation | None:
        return self.folder.evaluation

    @property
    def navigation_positions(self) -> np.ndarray | None:
        """The probe path (N, 3), image space LPS mm."""
        return self.folder.navigation_positions

    @property
    def navigation_labels(self) -> list[str] | None:
        return self.folder.navigation_labels

    @property
    def image(self) -> sitk.Image | None:
        """The whole CT (waits for its read to finish), or None without one."""
        return None if self.ct is None else self.ct.result()

    def read_ct_exactly(self) -> None:
        """Read the DICOM CT again at the voxel type its headers call for (int32), after its compact read
        (int16) met a slice beyond int16 (:class:`~EMRegModule.io.dicom_read.NarrowVoxelsError`)."""

        self.ct = open_ct(self.ct_path, self.ct_series)


def has_report_inputs(folder: str | os.PathLike[str]) -> bool:
    """True when a folder holds at least one output of a run (something to report).

    A case folder's ``navigation.csv`` is its tracking recording, not a run's mapped probe path: in a folder
    that holds a case's CT it counts only beside another output (a run written into its case folder)."""

    folder = Path(folder)
    if not folder.is_dir():
        return False
    present = [name for name in INPUT_NAMES if (folder / name).is_file()]
    return bool(present) and (present != [NAVIGATION_CSV] or find_ct(folder) is None)


def require_report_inputs(out_dir: str | os.PathLike[str]) -> Path:
    """``out_dir`` as a path when it holds something to report (:func:`has_report_inputs`); else
    :class:`EMRegError` saying what is missing."""
    out = Path(out_dir)
    if not out.is_dir():
        raise EMRegError(f"{out}: output folder not found")
    if not has_report_inputs(out):
        raise EMRegError(f"{out}: nothing to report (none of {', '.join(INPUT_NAMES)}); run emreg run CASE --out "
                         f"{out} first")
    return out


def _max_fre_mm(settings: Settings | None) -> float | None:
    """The case's ``[registration] max_fre_mm`` (the default without settings)."""
    return (settings or Settings()).registration.max_fre_mm


def _resolve_case_dir(out_dir: Path, case_dir: Path | None, run: dict | None, notes: list[str]) -> Path | None:
    if case_dir is not None:
        case_dir = Path(case_dir)
        if not case_dir.is_dir():
            raise EMRegError(f"{case_dir}: case folder not found (give the folder of the CT with --case)")
        return case_dir
    recorded = (run or {}).get("case")
    if not recorded:
        return None
    for candidate in (Path(recorded), out_dir / recorded):
        if candidate.is_dir():
            return candidate
    notes.append(f"{out_dir / RUN_JSON}: the recorded case folder {recorded} is not there any more; "
                 "give it with --case to see the CT")
    return None


def _read_case(inputs: ReportInputs) -> None:
    """Settings, CT path, targets and marker model of the case folder (problems become notes)."""
    try:
        case = open_case(inputs.case_dir)
    except EMRegError as exc:
        inputs.notes.append(str(exc))
        return
    inputs.settings = case.settings
    inputs.ct_path = case.ct
    if case.targets is not None:
        try:
            inputs.targets_labels, inputs.targets_positions = read_markups(case.targets)
        except EMRegError as exc:
            inputs.notes.append(str(exc))


def _start_ct(inputs: ReportInputs, image: sitk.Image | CTHandle | None, read_image: bool, keep_ct: bool) -> None:
    handle = image if isinstance(image, CTHandle) else None
    early = handle if handle is not None and not handle.is_complete else None  # a read started before the report
    if early is not None and (keep_ct or inputs.ct_path is None or early.path != inputs.ct_path.resolve()):
        early.cancel()  # not the CT this report shows (or the caller wants the whole CT): read that one
        image = handle = None
    if image is not None:
        inputs.ct = handle if handle is not None else CTHandle.of_image(image)
    elif read_image and inputs.ct_path is not None:

        # a DICOM folder: the series the run detected in
        inputs.ct_series = recorded_series_uid(inputs.run) or inputs.settings.ct.series
        if keep_ct or not _use_kept_ct_products(inputs):
            open_report_ct(inputs, keep_ct)


def _use_kept_ct_products(inputs: ReportInputs) -> bool:
    """Take the CT's products an earlier report of this run kept (:mod:`.ct_memo`) instead of reading the CT: its
    file is only hashed (and checked against ``run.json`` before the page is written)."""

    recorded = recorded_ct_sha256(inputs.run, inputs.ct_path)
    memo = next(filter(None, (load_ct_memo(path, recorded, inputs.settings.marker)
                              for path in memo_candidates(inputs.out_dir))), None)
    if memo is None:
        return False
    inputs.ct = memo.ct_handle(inputs.ct_path)
    return True


def open_report_ct(inputs: ReportInputs, keep_ct: bool = False) -> None:
    """Start reading the case's CT into ``inputs.ct`` (also after all, when the products an earlier report kept
    were made for other markers): streamed when nothing needs it whole and it is a plain file, else whole; a CT
    that cannot be read becomes a note (and no CT)."""

    try:
        streamed = None if keep_ct or inputs.ct_path.is_dir() else start_streamed_read(inputs.ct_path)
        # a DICOM series stored as 16 bits with an intercept is read as int16 (the detection's compact
        # read: half the memory of int32, the same values); prepare_ct_products reads it again if need be
        inputs.ct = streamed if streamed is not None else open_ct(inputs.ct_path, inputs.ct_series, compact=True)
    except EMRegError as exc:
        inputs.notes.append(str(exc))
        inputs.ct = None


def load_report_inputs(out_dir: str | os.PathLike[str], case_dir: str | os.PathLike[str] | None = None,
                       read_image: bool = True, image: sitk.Image | CTHandle | None = None, keep_ct: bool = True,
                       settings: Settings | None = None) -> ReportInputs:
    """Gather what exists in OUT and the case folder. Unreadable files become notes, not errors.

    ``image`` (a ``SimpleITK.Image``) is the case's CT when the caller already holds it in memory
    (``emreg run``); otherwise, when ``read_image``, the CT starts being read from the case folder
    in the background (``inputs.image`` waits for it). ``keep_ct=False``: nothing needs the whole CT
    afterwards, so a plain CT file is streamed (:mod:`EMRegModule.io.ct_stream`: its slices are let
    go once binned and sampled, and ``inputs.image`` is then None). ``settings``: the settings to report with
    (the command's, e.g. from ``--settings``); by default the case's ``case.toml``.

    Raises :class:`EMRegError` when OUT is missing or holds none of the run's outputs, or
    when an explicitly given ``case_dir`` does not exist.
    """
    out = require_report_inputs(out_dir)
    inputs = ReportInputs(out_dir=out)
    notes = inputs.notes
    inputs.run = read_manifest(out, notes)
    inputs.case_dir = _resolve_case_dir(out, Path(case_dir) if case_dir is not None else None, inputs.run, notes)
    if inputs.case_dir is not None:
        _read_case(inputs)
    if settings is not None:  # the command's own (``--settings``): those its provenance names
        inputs.settings = settings
    # A registration that cannot be trusted (corrupt, non-finite, not rigid, FRE above the limit) is
    # never drawn as if it were: the report is refused (exit 2, or 3 for the FRE), not annotated.
    inputs.folder = read_run_folder(out, inputs.run, _max_fre_mm(inputs.settings))
    _start_ct(inputs, image, read_image, keep_ct)
    notes.extend(inputs.folder.notes)
    inputs.model = inputs.settings.marker
    return inputs
