"""Case folders (spec: ``ct.*`` or ``ct/`` (or ``fiducials.mrk.json`` instead of a CT), ``calibration.csv``,
``navigation.csv``, ``targets.mrk.json``, ``board.csv``, ``case.toml``) and their settings. The recordings may also
be PLUS sequence metafiles (``calibration.seq.mha`` ...; :mod:`EMRegModule.io.recording`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.tracking import TrackingRecording
from ..errors import EMRegError
from ..names import CASE_FIDUCIALS_FILE, CT_FILE_NAMES, CT_FOLDER_NAME, RECORDING_SUFFIXES, SETTINGS_FILE, TARGETS_FILE
from ..settings import Settings, load_settings
from .ct_checks import check_ct_path
from .markups import read_markups
from .recording import find_recording, read_recording


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
        return None if self.targets is None else read_targets(self.targets)

    def read_recording(self, role: str) -> TrackingRecording | None:
        """The tracking recording ``calibration``, ``navigation`` or ``board``, or None when absent."""
        path = getattr(self, role)
        if path is None:
            return None
        if path.name != role:  # ``role/``: a folder of sequence files, as 3D Slicer saves a recording
            _refuse_not_a_file(path, f"the {role} recording")
        return read_recording(path, self.settings)


def read_targets(path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray]:
    """The targets (labels, (K, 3) LPS mm) of a markups file; one without any defined point is an
    :class:`EMRegError` naming it (a TRE over no target is no evaluation)."""
    labels, positions = read_markups(path)
    if len(positions) == 0:
        raise EMRegError(f"{path}: the targets file holds no target points (no defined control point)")
    return labels, positions


def find_ct(case_dir: str | os.PathLike[str]) -> Path | None:
    """The CT of a case folder by the spec's names (a file, or a ``ct/`` DICOM folder), or None; one of those
    names that is a broken symbolic link or a link loop is an :class:`EMRegError` naming it (never skipped)."""
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


def run_ct_path(run: Any, case_dir: str | os.PathLike[str] | None = None) -> str | None:
    """The CT of a run's outputs: the one its ``run.json`` (``run``, parsed) names, as ``emreg run`` records it;
    else, for a folder of per-stage outputs (whose ``run.json`` names no CT), the CT of ``case_dir``, the case
    a report of it is given (``--case``), which is the CT that report shows; None without either."""
    ct = run.get("ct") if isinstance(run, dict) else None
    if isinstance(ct, str):
        return ct
    found = find_ct(case_dir) if case_dir is not None and Path(case_dir).is_dir() else None
    return str(found) if found is not None else None


def open_case(folder: str | os.PathLike[str], settings: Settings | None = None) -> Case:
    """Discover a case folder's files by the spec's names and read its ``case.toml`` (typed, checked);
    ``settings`` (``--settings FILE``) are used instead, and the case's own ``case.toml`` is then not read."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EMRegError(f"{folder}: case folder not found")

    def present(path: Path) -> Path | None:
        # a name held by a folder, a FIFO or a broken link is not "absent": kept, so that reading it says why
        return path if os.path.lexists(path) else None

    def recording(stem: str) -> Path | None:
        found = find_recording(folder, stem)
        return found or next((p for s in RECORDING_SUFFIXES if (p := present(folder / f"{stem}{s}"))), None)

    if settings is None:
        _refuse_not_a_file(folder / SETTINGS_FILE, "the case's settings")  # never "no settings, the defaults"
        settings = load_settings(folder / SETTINGS_FILE)
    return Case(
        folder=folder,
        ct=find_ct(folder),
        calibration=recording("calibration"),
        navigation=recording("navigation"),
        fiducials=present(folder / CASE_FIDUCIALS_FILE),
        targets=present(folder / TARGETS_FILE),
        board=recording("board"),
        settings=settings,
    )


def _refuse_not_a_file(path: Path, what: str) -> None:
    """Refuse (exit 2) a case file's name held by something that is not a regular file (a folder, a FIFO, a
    broken link): it is not absent, and treating it so would silently drop what the user meant to give."""
    if path.is_file() or not os.path.lexists(path):
        return
    kind = ("a folder" if path.is_dir() else "a broken symbolic link" if path.is_symlink() and not path.exists()
            else "not a regular file")
    raise EMRegError(f"{path}: {what} is {kind}; give a file under this name or remove it")
