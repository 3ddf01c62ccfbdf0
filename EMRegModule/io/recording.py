"""Tracking recordings in any of the formats EMReg accepts: the spec's CSV or a PLUS / 3D Slicer
sequence metafile (``.seq.mha``, ``.mha``, ``.seq.nrrd``, ``.igs.nrrd``), chosen by the file name, or a
folder of sequence files with one transform each (3D Slicer's way: :mod:`.sequence_folder`).

``[sensors]`` settings used for sequence metafiles: ``reference`` / ``probe`` (the ports the two
transforms become) and ``reference_transform`` / ``probe_transform`` (the transform names,
default ``ReferenceToTracker`` / ``ProbeToTracker``).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..core.tracking import TrackingRecording
from ..errors import EMRegError
from ..names import RECORDING_SUFFIXES  # in order of preference (the spec's CSV first)
from ..settings import Settings
from .sequence_folder import is_sequence_folder, read_sequence_folder
from .sequence_metafile import (
    DEFAULT_PROBE_TRANSFORM,
    DEFAULT_REFERENCE_TRANSFORM,
    is_sequence_file,
    read_sequence_metafile,
    write_sequence_metafile,
)
from .tracking_csv import read_tracking_csv, write_tracking_csv


def _names(settings: Settings | Mapping[str, Any] | None, reference_port: int | None = None,
           probe_port: int | None = None) -> dict[str, Any]:
    """Transform names and ports from the typed settings (or a parsed ``case.toml`` mapping)."""
    if isinstance(settings, Settings):
        sensors: dict[str, Any] = {k: v for k, v in vars(settings.sensors).items() if v is not None}
    else:
        sensors = dict((settings or {}).get("sensors", {}) or {})
    return {
        "reference_transform": str(sensors.get("reference_transform") or DEFAULT_REFERENCE_TRANSFORM),
        "probe_transform": str(sensors.get("probe_transform") or DEFAULT_PROBE_TRANSFORM),
        "reference_port": int(reference_port if reference_port is not None else sensors.get("reference", 1)),
        "probe_port": int(probe_port if probe_port is not None else sensors.get("probe", 2)),
    }


def _probe_transform_given(settings: Settings | Mapping[str, Any] | None) -> bool:
    """Whether the settings name the probe's transform (``[sensors] probe_transform``)."""
    if isinstance(settings, Settings):
        return settings.sensors.probe_transform is not None
    return bool(((settings or {}).get("sensors", {}) or {}).get("probe_transform"))


def read_recording(path: str | os.PathLike[str], settings: Settings | Mapping[str, Any] | None = None,
                   reference_port: int | None = None, probe_port: int | None = None) -> TrackingRecording:
    """Read a tracking recording (CSV or sequence metafile, by its name). ``settings``: the parsed
    ``case.toml`` (its ``[sensors]`` table; typed or a mapping); the ports override ``[sensors]
    reference`` / ``probe``. A FIFO, device or socket is refused (:class:`EMRegError`) before it is
    opened: reading one would wait for a writer, or never end."""
    _refuse_special_file(path)
    if is_sequence_file(path):
        names = _names(settings, reference_port, probe_port)
        if not _probe_transform_given(settings):
            names["probe_transform"] = None  # ProbeToTracker, or the tool of a file with two transforms
        return read_sequence_metafile(path, **names)
    if Path(path).is_dir():  # 3D Slicer's recording: one sequence file per transform
        return read_sequence_folder(path, **_names(settings, reference_port, probe_port))
    return read_tracking_csv(path)


def _refuse_special_file(path: str | os.PathLike[str]) -> None:
    """Refuse (one line, exit 2) a path that is neither a regular file nor a folder; a missing one is left to
    the readers, which say so."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise EMRegError(f"{path}: not a regular file (a FIFO, device or socket); give the recording's file")


def write_recording(recording: TrackingRecording, path: str | os.PathLike[str], settings: Settings | None = None,
                    reference_port: int | None = None, probe_port: int | None = None,
                    orientation: str | None = None) -> None:
    """Write a recording atomically as CSV or, for a sequence-metafile name, as a PLUS sequence metafile.

    ``settings``: the typed ``case.toml`` (:class:`~EMRegModule.settings.Settings`), whose ``[sensors]``
    names the transforms of a sequence file; the ports override ``[sensors] reference`` / ``probe``."""
    if is_sequence_file(path):
        write_sequence_metafile(recording, path, **_names(settings, reference_port, probe_port))
    else:
        write_tracking_csv(recording, path, orientation=orientation)


def find_recording(folder: str | os.PathLike[str], stem: str) -> Path | None:
    """A case folder's recording ``stem`` (``calibration``, ``navigation``, ``board``) under any accepted
    name (``stem.csv`` first, then ``stem.seq.mha``, ``stem.mha``, ``stem.seq.nrrd``, ``stem.igs.nrrd``),
    else a folder ``stem/`` of sequence files, one transform each, as 3D Slicer saves a recording
    (:mod:`EMRegModule.io.sequence_folder`)."""
    folder = Path(folder)
    for suffix in RECORDING_SUFFIXES:
        candidate = folder / f"{stem}{suffix}"
        if candidate.is_file():
            return candidate
    return folder / stem if is_sequence_folder(folder / stem) else None
