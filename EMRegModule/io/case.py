"""Case folders (spec: ``ct.*`` or ``ct/`` (or ``fiducials.mrk.json`` instead of a CT), ``calibration.csv``,
``navigation.csv``, ``targets.mrk.json``, ``board.csv``, ``case.toml``) and their settings. The recordings may also
be PLUS sequence metafiles (``calibration.seq.mha`` ...; :mod:`EMRegModule.io.recording`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import EMRegError
from ..settings import Settings, load_settings
from ..tracking import TrackingRecording
from .fiducials import CASE_FIDUCIALS_NAME
from .markups import read_markups
from .recording import RECORDING_SUFFIXES, find_recording

CT_FILE_NAMES = ("ct.nrrd", "ct.nii.gz", "ct.nii", "ct.mha", "ct.mhd", "ct.nhdr")  # .nhdr: 3D Slicer's detached NRRD
CT_FOLDER_NAME = "ct"
RECORDING_ROLES = ("calibration", "navigation", "board")
TARGETS_FILE = "targets.mrk.json"
SETTINGS_FILE = "case.toml"
#: Every name a case folder is read from (an output folder equal to the case must write none of them).
CASE_INPUT_NAMES = (CT_FOLDER_NAME, *CT_FILE_NAMES,
                    *(role + suffix for role in RECORDING_ROLES for suffix in RECORDING_SUFFIXES),
                    TARGETS_FILE, SETTINGS_FILE, CASE_FIDUCIALS_NAME)


@dataclass
class Case:
    """The files of one case folder (None where absent) and its ``case.toml`` settings (typed, checked)."""

    folder: Path
    ct: Path | None
    calibration: Path | None
    navigation: Path | None
    targets: Path | None
    board: Path | None
    settings: Settings = field(default_factory=Settings)
    #: ``fiducials.mrk.json``: fiducial points instead of a CT (:mod:`EMRegModule.io.fiducials`), or None.
    fiducials: Path | None = None

    @property
    def reference_sensor(self) -> int:
        return self.settings.sensors.reference

    @property
    def probe_sensor(self) -> int:
        return self.settings.sensors.probe

    def read_targets(self) -> tuple[list[str], np.ndarray] | None:
        """The targets (labels, (K, 3) LPS mm) of ``targets.mrk.json``, or None when absent."""
        return None if self.targets is None else read_markups(self.targets)

    def read_recording(self, role: str) -> TrackingRecording | None:
        """The tracking recording ``calibration``, ``navigation`` or ``board``, or None when absent."""
        from .recording import read_recording

        path = getattr(self, role)
        return None if path is None else read_recording(path, self.settings)


def find_ct(case_dir: str | os.PathLike[str]) -> Path | None:
    """The CT of a case folder by the spec's names (a file, or a ``ct/`` DICOM folder), or None; one of those
    names that is a broken symbolic link or a link loop is an :class:`EMRegError` naming it (never skipped)."""
    from .ct_checks import check_ct_path

    case_dir = Path(case_dir)
    for name in (*CT_FILE_NAMES, CT_FOLDER_NAME):
        if (case_dir / name).is_symlink():
            check_ct_path(case_dir / name)
    for name in CT_FILE_NAMES:
        if (case_dir / name).is_file():
            return case_dir / name
    if (case_dir / CT_FOLDER_NAME).is_dir():
        return case_dir / CT_FOLDER_NAME
    return None


def open_case(folder: str | os.PathLike[str]) -> Case:
    """Discover a case folder's files by the spec's names and read its ``case.toml`` (typed, checked)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EMRegError(f"{folder}: case folder not found")

    def optional(name: str) -> Path | None:
        return folder / name if (folder / name).is_file() else None

    return Case(
        folder=folder,
        ct=find_ct(folder),
        fiducials=optional(CASE_FIDUCIALS_NAME),
        calibration=find_recording(folder, "calibration"),
        navigation=find_recording(folder, "navigation"),
        targets=optional(TARGETS_FILE),
        board=find_recording(folder, "board"),
        settings=load_settings(folder / SETTINGS_FILE),
    )
