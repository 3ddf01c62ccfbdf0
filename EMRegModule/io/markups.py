"""3D Slicer markups JSON (point lists) read/write.

Written files are in LPS (``coordinateSystem: "LPS"``), which Slicer 5 reads directly;
files in RAS are converted to LPS on reading, and ``coordinateUnits`` other than ``mm`` ("m", "cm",
"um") are scaled to millimetres; an unknown unit is an error.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..core.frames import LPS_TO_RAS_3X3
from ..errors import EMRegError
from .atomic import atomic_write_json, read_json

MARKUPS_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/"
    "markups-schema-v1.0.3.json#"
)


#: Slicer markups ``coordinateUnits`` EMReg reads, and the factor to millimetres (Slicer writes "mm";
#: the schema allows any unit string, "m" is what some exporters write).
UNIT_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0, "um": 0.001}


def markups_document(labels: Sequence[str], positions_lps: np.ndarray, name: str = "F") -> dict:
    """A Slicer markups point-list document with the given labels and LPS positions (mm)."""
    positions_lps = np.asarray(positions_lps, dtype=float).reshape(-1, 3)
    control_points = [
        {
            "id": str(i + 1), "label": str(label), "description": "", "associatedNodeID": "",
            "position": [float(v) for v in position],
            "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True, "locked": True, "visibility": True, "positionStatus": "defined",
        }
        for i, (label, position) in enumerate(zip(labels, positions_lps, strict=True))
    ]
    return {
        "@schema": MARKUPS_SCHEMA,
        "markups": [{
            "type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm", "locked": True,
            "labelFormat": f"{name}-%N", "controlPoints": control_points,
        }],
    }


def write_markups(
    path: str | os.PathLike[str], labels: Sequence[str], positions_lps: np.ndarray, name: str = "F"
) -> None:
    """Write a Slicer point list (LPS, mm) atomically."""
    atomic_write_json(path, markups_document(labels, positions_lps, name))


def read_markups(path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray]:
    """Labels and LPS positions (N, 3) of every defined control point in a markups JSON file."""
    labels, positions, _ = read_markups_with_frame(path)
    return labels, positions


def read_markups_with_frame(path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray, dict[str, str]]:
    """:func:`read_markups` plus what the file declared: ``{"coordinate_system": "RAS"|"LPS"|"RAS, LPS",
    "units": "mm"|...}`` (the positions returned are LPS mm whatever it declared).

    As 3D Slicer reads them (``vtkMRMLMarkupsJsonStorageNode``): ``coordinateSystem`` ``LPS`` (the default) or
    ``RAS``; ``coordinateUnits`` a unit string or a coded entry ``[code, "UCUM", meaning]`` (default ``mm``;
    ``um``, ``cm`` and ``m`` are scaled to mm, any other unit refused); control points whose ``positionStatus``
    is ``undefined`` or ``preview`` are left out, an unknown status refused.
    """
    document = read_json(path, "markups JSON")
    labels: list[str] = []
    positions: list[list[float]] = []
    systems: list[str] = []
    units_seen: list[str] = []
    try:
        for markup in document["markups"]:
            system = str(markup.get("coordinateSystem") or "LPS").upper()
            if system not in ("LPS", "RAS"):
                raise EMRegError(f"{path}: unknown coordinateSystem {system!r} (Slicer writes LPS or RAS)")
            flip = np.diag(LPS_TO_RAS_3X3) if system == "RAS" else np.ones(3)
            units = _markups_units(markup.get("coordinateUnits", "mm"), path)
            flip = flip * UNIT_TO_MM[units]
            systems.append(system)
            units_seen.append(units)
            for i, point in enumerate(markup.get("controlPoints", [])):
                status = point.get("positionStatus", "defined")
                if status not in POSITION_STATUSES:
                    raise EMRegError(f"{path}: control point {i + 1} has an unknown positionStatus {status!r:.30} "
                                     f"(Slicer writes {', '.join(POSITION_STATUSES)})")
                if status != "defined":
                    continue
                position = np.asarray(point["position"], dtype=float)
                if position.shape != (3,) or not np.all(np.isfinite(position)):
                    raise EMRegError(f"{path}: control point {i + 1} has no valid 3D position")
                labels.append(str(point.get("label") or f"P{i + 1}"))
                positions.append(list(position * flip))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise EMRegError(f"{path}: not a Slicer markups file ({exc!s:.100})") from None
    declared = {"coordinate_system": ", ".join(dict.fromkeys(systems)) or "LPS",
                "units": ", ".join(dict.fromkeys(units_seen)) or "mm"}
    return labels, np.asarray(positions, dtype=float).reshape(-1, 3), declared


#: The ``positionStatus`` values of a Slicer control point (only ``defined`` points are read).
POSITION_STATUSES = ("defined", "undefined", "preview")


def _markups_units(value: object, path: str | os.PathLike[str]) -> str:
    """The unit of a markup's ``coordinateUnits``: a string, or a coded entry ``[code, "UCUM", meaning]`` (the
    only coding scheme Slicer reads); refused (:class:`EMRegError`) unless EMReg can scale it to mm."""
    if isinstance(value, list):
        if len(value) != 3 or str(value[1]).upper() != "UCUM":
            raise EMRegError(f"{path}: coordinateUnits {value!r:.60} is not a UCUM coded entry [code, \"UCUM\", "
                             "meaning]")
        value = value[0]
    units = str(value)
    if units not in UNIT_TO_MM:
        raise EMRegError(f"{path}: unknown coordinateUnits {units!r} (EMReg reads {', '.join(UNIT_TO_MM)})")
    return units
