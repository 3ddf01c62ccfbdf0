"""Case folders (spec: ``ct.*`` or ``ct/``, ``calibration.csv``, ``navigation.csv``,
``targets.mrk.json``, ``board.csv``, ``case.toml``) and their settings. The recordings may also
be PLUS sequence metafiles (``calibration.seq.mha`` ...; :mod:`EMRegModule.io.recording`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import EMRegError
from ..settings import Settings, load_settings
from ..tracking import TrackingRecording
from .markups import read_markups

CT_FILE_NAMES = ("ct.nrrd", "ct.nii.gz", "ct.nii", "ct.mha", "ct.mhd", "ct.nhdr")  # .nhdr: 3D Slicer's detached NRRD
CT_FOLDER_NAME = "ct"


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
    """The CT of a case folder by the spec's names (a file, or a ``ct/`` DICOM folder), or None."""
    case_dir = Path(case_dir)
    for name in CT_FILE_NAMES:
        if (case_dir / name).is_file():
            return case_dir / name
    if (case_dir / CT_FOLDER_NAME).is_dir():
        return case_dir / CT_FOLDER_NAME
    return None


def run_ct_path(run: Any, case_dir: str | os.PathLike[str] | None = None) -> str | None:
    """The CT of a run's outputs: the one its ``run.json`` (``run``, parsed) names, as ``emreg run`` records it;
    else, for a folder of per-stage outputs (whose ``run.json`` names no CT), the CT of ``case_dir``, the case
    a report of it is given (``--case``), which is the CT that report shows; None without either."""
    ct = run.get("ct") if isinstance(run, dict) else None
    if isinstance(ct, str):
        return ct
    found = find_ct(case_dir) if case_dir is not None and Path(case_dir).is_dir() else None
    return str(found) if found is not None else None


def open_case(folder: str | os.PathLike[str]) -> Case:
    """Discover a case folder's files by the spec's names and read its ``case.toml`` (typed, checked)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EMRegError(f"{folder}: case folder not found")

    def optional(name: str) -> Path | None:
        return folder / name if (folder / name).is_file() else None

    from .recording import find_recording

    return Case(
        folder=folder,
        ct=find_ct(folder),
        calibration=find_recording(folder, "calibration"),
        navigation=find_recording(folder, "navigation"),
        targets=optional("targets.mrk.json"),
        board=find_recording(folder, "board"),
        settings=load_settings(folder / "case.toml"),
    )
