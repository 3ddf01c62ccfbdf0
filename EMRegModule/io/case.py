"""Case folders (spec: ``ct.*`` or ``ct/``, ``calibration.csv``, ``navigation.csv``,
``targets.mrk.json``, ``board.csv``, ``case.toml``) and their settings. The recordings may also
be PLUS sequence metafiles (``calibration.seq.mha`` ...; :mod:`EMRegModule.io.recording`).
"""

from __future__ import annotations

import math
import os
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import EMRegError

CT_FILE_NAMES = ("ct.nrrd", "ct.nii.gz", "ct.nii", "ct.mha", "ct.mhd")
CT_FOLDER_NAME = "ct"
DEFAULT_REFERENCE_SENSOR = 1
DEFAULT_PROBE_SENSOR = 2


@dataclass
class Case:
    """The files of one case folder (None where absent) and its ``case.toml`` settings."""

    folder: Path
    ct: Path | None
    calibration: Path | None
    navigation: Path | None
    targets: Path | None
    board: Path | None
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def reference_sensor(self) -> int:
        return int(self.settings.get("sensors", {}).get("reference", DEFAULT_REFERENCE_SENSOR))

    @property
    def probe_sensor(self) -> int:
        return int(self.settings.get("sensors", {}).get("probe", DEFAULT_PROBE_SENSOR))

    def section(self, name: str) -> dict[str, Any]:
        """One ``case.toml`` table (empty when absent)."""
        value = self.settings.get(name, {})
        if not isinstance(value, dict):
            raise EMRegError(f"{self.folder / 'case.toml'}: [{name}] must be a table")
        return value


def find_ct(case_dir: str | os.PathLike[str]) -> Path | None:
    """The CT of a case folder by the spec's names (a file, or a ``ct/`` DICOM folder), or None."""
    case_dir = Path(case_dir)
    for name in CT_FILE_NAMES:
        if (case_dir / name).is_file():
            return case_dir / name
    if (case_dir / CT_FOLDER_NAME).is_dir():
        return case_dir / CT_FOLDER_NAME
    return None


def open_case(folder: str | os.PathLike[str]) -> Case:
    """Discover a case folder's files by the spec's names and read ``case.toml``."""
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
        settings=read_case_settings(folder / "case.toml"),
    )


def read_case_settings(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read ``case.toml`` (empty dict when the file is absent); malformed TOML is an :class:`EMRegError`."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        with path.open("rb") as f:
            settings = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise EMRegError(f"{path}: malformed TOML ({exc})") from None
    sensors = settings.get("sensors", {})
    for role in ("reference", "probe"):
        if role in sensors and not (isinstance(sensors[role], int) and 1 <= sensors[role] <= 4):
            raise EMRegError(f"{path}: [sensors] {role} must be a port number (1..4), got {sensors[role]!r}")
    if "probe_axis" in sensors:
        from ..probe_axis import check_probe_axis

        check_probe_axis(sensors["probe_axis"], f"{path}: [sensors]")
    for key in ("reference_transform", "probe_transform"):
        if key in sensors and not (isinstance(sensors[key], str) and sensors[key].strip().isidentifier()):
            raise EMRegError(f"{path}: [sensors] {key} must be a transform name such as 'ProbeToTracker', "
                             f"got {sensors[key]!r}")
    return settings


def check_known_keys(table: Mapping[str, Any] | None, section: str, known: Iterable[str]) -> dict[str, Any]:
    """A copy of a ``case.toml`` table; an unknown key (a typo) is an :class:`EMRegError` listing the known ones."""
    table = dict(table or {})
    known = set(known)
    unknown = sorted(set(table) - known)
    if unknown:
        raise EMRegError(
            f"case.toml [{section}]: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    return table


def setting_number(section: str, name: str, value: Any) -> float:
    """A ``case.toml`` value that must be a finite number (not a string, not a boolean)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise EMRegError(f"case.toml [{section}]: {name} must be a number, got {value!r}")
    return float(value)
