"""The detection's files: ``OUT/markers.json`` (the spec's, every marker and rejected candidate) and
``OUT/markers.mrk.json`` (the marker origins as 3D Slicer markups), image space (CT physical LPS, mm).

The values are :class:`~EMRegModule.core.detection.result.DetectionResult` (its JSON form ``to_json`` /
``from_json``); this module only puts them in files and takes them out.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..core.detection.result import DetectionResult
from ..errors import EMRegError
from ..names import MARKERS_JSON, MARKERS_MRK_JSON
from .atomic import atomic_write_json, read_json
from .markups import write_markups
from .provenance import check_belongs


def write_detection(result: DetectionResult, out_dir: str | os.PathLike[str]) -> None:
    """Write ``OUT/markers.json`` and ``OUT/markers.mrk.json`` (marker origins, LPS) atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / MARKERS_JSON, result.to_json())
    write_markups(out / MARKERS_MRK_JSON, [m.id for m in result.markers], result.origins, name="I")


def read_detection(path: str | os.PathLike[str]) -> DetectionResult:
    """Read ``markers.json`` (a file, or a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / MARKERS_JSON
    document = read_json(path, MARKERS_JSON)
    if not isinstance(document, dict):
        raise EMRegError(f"{path}: not a valid markers.json (not a JSON object)")
    return DetectionResult.from_json(document, str(path))


def markers_beside(registration_path: str | os.PathLike[str]) -> tuple[DetectionResult | None, str | None]:
    """The detected markers (``markers.json``) beside a ``registration.json`` (a file or its folder), checked to
    belong with it, and None; or None and why they cannot be used (None too when there is no ``markers.json``)."""
    path = Path(registration_path)
    markers = (path if path.is_dir() else path.parent) / MARKERS_JSON
    if not markers.is_file():
        return None, None
    try:
        detection = read_detection(markers)
        check_belongs(markers)
    except EMRegError as exc:
        return None, f"{exc}: no checkpoints at the pinholes"
    return detection, None
