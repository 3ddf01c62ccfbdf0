"""3D Slicer markups JSON (point lists) read/write.

Written files are in LPS (``coordinateSystem: "LPS"``), which Slicer 5 reads directly;
files in RAS are converted to LPS on reading, and ``coordinateUnits`` other than ``mm`` ("m", "cm",
"um") are scaled to millimetres; an unknown unit is an error.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

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
    document = read_json(path, "markups JSON")
    labels: list[str] = []
    positions: list[list[float]] = []
    try:
        for markup in document["markups"]:
            system = str(markup.get("coordinateSystem", "LPS")).upper()
            if system not in ("LPS", "RAS"):
                raise EMRegError(f"{path}: unknown coordinateSystem {system!r}")
            flip = np.array([-1.0, -1.0, 1.0]) if system == "RAS" else np.ones(3)
            units = str(markup.get("coordinateUnits", "mm"))
            if units not in UNIT_TO_MM:
                raise EMRegError(f"{path}: unknown coordinateUnits {units!r} (EMReg reads {', '.join(UNIT_TO_MM)})")
            flip = flip * UNIT_TO_MM[units]
            for i, point in enumerate(markup.get("controlPoints", [])):
                if point.get("positionStatus", "defined") != "defined":
                    continue
                position = np.asarray(point["position"], dtype=float)
                if position.shape != (3,) or not np.all(np.isfinite(position)):
                    raise EMRegError(f"{path}: control point {i + 1} has no valid 3D position")
                labels.append(str(point.get("label") or f"P{i + 1}"))
                positions.append(list(position * flip))
    except (KeyError, TypeError, ValueError) as exc:
        raise EMRegError(f"{path}: not a Slicer markups file ({exc!s:.100})") from None
    return labels, np.asarray(positions, dtype=float).reshape(-1, 3)
