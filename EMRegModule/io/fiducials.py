"""Fiducials from anywhere: the image-side points of a registration read from a file.

:func:`read_fiducials` reads, by content and name:

- a 3D Slicer markups JSON (``.mrk.json``, any ``coordinateSystem`` and ``coordinateUnits``:
  :func:`EMRegModule.io.markups.read_markups_with_frame`), converted to LPS mm;
- a 3D Slicer markups CSV (``.fcsv``): ``# CoordinateSystem = RAS | LPS`` or the older numeric form
  (``0`` = RAS, ``1`` = LPS; ``2`` = IJK is refused), RAS when the header is absent, as
  ``vtkMRMLMarkupsFiducialStorageNode`` reads it; columns named by ``# columns = ...`` (Slicer 4.x/5.x:
  ``id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``) or, without a version line, the
  Slicer 3 layout ``label,x,y,z,sel,vis``; millimetres; converted to LPS;
- a PLUS device-set XML's ``<PhantomDefinition><Geometry><Landmarks><Landmark Name=".." Position="x y z"/>``
  (as PLUS's ``vtkPlusPhantomLandmarkRegistrationAlgo`` reads it; names kept), in the phantom's own frame
  (PLUS ``Phantom``, mm): the registration then maps the Reference frame into that frame.

``markers.json`` from ``emreg detect`` is recognised (:func:`is_markers_file`) and goes the CT markers'
way (the pinhole axis and the sensor offset l), as ``--markers`` does.

Every fiducial set is checked (:func:`~EMRegModule.core.fiducials.check_fiducials`: at least three points, finite,
unique labels, not all on one line). A bad file raises :class:`EMRegError` (exit 2) with one line naming it.
"""

from __future__ import annotations

import csv
import os
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Any

import numpy as np

from ..core.fiducials import Fiducials, check_fiducials
from ..core.frames import lps_to_ras_points
from ..errors import EMRegError
from ..names import MARKERS_JSON
from .atomic import read_json
from .markups import read_markups_with_frame

FORMAT_MARKUPS = "Slicer markups JSON"
FORMAT_FCSV = "Slicer markups CSV (fcsv)"
FORMAT_PLUS = "PLUS phantom definition"

#: The case-folder file a fiducial case holds instead of a CT.

#: The columns of an .fcsv written by Slicer 4.6 and later, when no ``# columns`` line names them.
FCSV_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc", "associatedNodeID")
#: Slicer 3's unversioned .fcsv.
FCSV_SLICER3_COLUMNS = ("label", "x", "y", "z", "sel", "vis")
#: ``# CoordinateSystem = ...`` values: the named form and Slicer's older numeric one.
FCSV_SYSTEMS = {"RAS": "RAS", "0": "RAS", "LPS": "LPS", "1": "LPS"}


def is_markers_file(path: str | os.PathLike[str]) -> bool:
    """True for a ``markers.json`` of ``emreg detect`` (a JSON object with a ``markers`` list and no ``markups``)."""
    path = Path(path)
    if path.is_dir():
        return (path / MARKERS_JSON).is_file()
    if path.suffix.lower() != ".json" or path.name.lower().endswith(".mrk.json"):
        return False
    try:
        document = read_json(path, "fiducials file")
    except EMRegError:
        return False
    return isinstance(document, dict) and "markers" in document and "markups" not in document


def read_fiducials(path: str | os.PathLike[str]) -> Fiducials:
    """The fiducials of a Slicer markups file (``.mrk.json``, ``.json``, ``.fcsv``) or a PLUS device-set XML
    (``.xml``), checked (see the module docstring); positions in LPS mm (markups) or the phantom's frame (PLUS)."""
    path = Path(path)
    if not path.is_file():
        raise EMRegError(f"{path}: fiducials file not found" if not path.exists() else
                         f"{path}: not a fiducials file (a folder)")
    suffix = path.suffix.lower()
    if suffix == ".fcsv":
        fiducials = _read_fcsv(path)
    elif suffix == ".xml":
        fiducials = _read_plus_landmarks(path)
    elif suffix == ".json":
        labels, positions, declared = read_markups_with_frame(path)
        fiducials = Fiducials(labels, positions, str(path), FORMAT_MARKUPS, "LPS", declared)
    else:
        raise EMRegError(f"{path}: unknown fiducials file type {suffix or '(none)'!r}; give a Slicer markups file "
                         "(.mrk.json, .fcsv), a PLUS device-set XML with <PhantomDefinition> landmarks (.xml), or "
                         "markers.json")
    check_fiducials(fiducials)
    return fiducials


# --- .fcsv ------------------------------------------------------------------------------------


def _read_fcsv(path: Path) -> Fiducials:
    """Labels and LPS positions of a Slicer ``.fcsv`` (see the module docstring)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise EMRegError(f"{path}: not a Slicer markups CSV ({exc})") from None
    version: str | None = None
    system_value: str | None = None
    columns: list[str] | None = None
    rows: list[tuple[int, list[str]]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("#"):
            key, _, value = line[1:].partition("=")
            key = key.strip().lower()
            if key == "markups fiducial file version":
                version = value.strip()
            elif key == "coordinatesystem":
                system_value = value.strip()
            elif key == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        if line.strip():
            rows.append((number, next(csv.reader([line], skipinitialspace=False))))
    system = "RAS" if system_value is None else FCSV_SYSTEMS.get(system_value.upper())
    if system is None:
        raise EMRegError(f"{path}: # CoordinateSystem = {system_value!r:.20} is not one EMReg reads (RAS or LPS, "
                         "or Slicer's older 0 = RAS, 1 = LPS)")
    if columns is None:
        columns = list(FCSV_COLUMNS if version is not None else FCSV_SLICER3_COLUMNS)
    index = {name: k for k, name in enumerate(columns)}
    missing = [name for name in ("x", "y", "z") if name not in index]
    if missing:
        raise EMRegError(f"{path}: the # columns line names no {', '.join(missing)} column")
    labels: list[str] = []
    positions: list[list[float]] = []
    for k, (number, fields) in enumerate(rows):
        try:
            position = [float(fields[index[name]]) for name in ("x", "y", "z")]
        except (IndexError, ValueError):
            raise EMRegError(f"{path}: line {number} has no numeric x, y, z (columns {','.join(columns)})") from None
        label = _field(fields, index.get("label")) or _field(fields, index.get("id")) or f"F-{k + 1}"
        labels.append(label)
        positions.append(position)
    lps = np.asarray(positions, dtype=float).reshape(-1, 3)
    if system == "RAS":
        lps = lps_to_ras_points(lps)  # the flip is its own inverse: RAS -> LPS
    return Fiducials(labels, lps, str(path), FORMAT_FCSV, "LPS",
                     {"coordinate_system": system, "units": "mm", "version": version or "Slicer 3 (unversioned)"})


def _field(fields: list[str], k: int | None) -> str:
    return fields[k].strip() if k is not None and k < len(fields) else ""


# --- PLUS phantom definition --------------------------------------------------------------------


def _read_plus_landmarks(path: Path) -> Fiducials:
    """The ``<Landmarks>`` of a PLUS device-set XML's ``<PhantomDefinition><Geometry>`` (names kept, mm, the
    phantom's frame: ``vtkPlusPhantomLandmarkRegistrationAlgo``'s ``PhantomCoordinateFrame``, default Phantom)."""
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as exc:
        raise EMRegError(f"{path}: not a valid XML file ({exc})") from None
    phantom = root if _tag(root) == "phantomdefinition" else _child(root, "phantomdefinition")
    geometry = _child(phantom, "geometry") if phantom is not None else None
    landmarks = _child(geometry, "landmarks") if geometry is not None else None
    points = [e for e in landmarks if _tag(e) == "landmark"] if landmarks is not None else []
    if not points:
        where = ("no <PhantomDefinition>" if phantom is None else "no <Geometry> in its <PhantomDefinition>"
                 if geometry is None else "no <Landmark> in its <Landmarks>" if landmarks is not None
                 else "no <Landmarks> in its <PhantomDefinition><Geometry>")
        raise EMRegError(f"{path}: a PLUS device-set file without landmarks ({where}); give the phantom definition "
                         "that holds <Landmarks><Landmark Name=... Position=\"x y z\"/>")
    labels: list[str] = []
    positions: list[list[float]] = []
    for k, element in enumerate(points):
        name = element.get("Name")
        text = element.get("Position", "")
        try:
            position = [float(v) for v in text.split()]
        except ValueError:
            position = []
        if not name or len(position) != 3:
            raise EMRegError(f"{path}: landmark {k + 1} needs a Name and a Position of 3 numbers, got "
                             f"Name={name!r:.30} Position={text!r:.40}")
        labels.append(name)
        positions.append(position)
    algorithm = next((e for e in root.iter() if _tag(e) == "vtkplusphantomlandmarkregistrationalgo"), None)
    frame = (algorithm.get("PhantomCoordinateFrame") if algorithm is not None else None) or "Phantom"
    return Fiducials(labels, np.asarray(positions, dtype=float), str(path), FORMAT_PLUS, frame,
                     {"coordinate_system": f"{frame} (PLUS phantom frame)", "units": "mm"})


def _tag(element: Any) -> str:
    return str(element.tag).lower()


def _child(element: Any, name: str) -> Any:
    """The first direct child named ``name`` (case-insensitive, as PLUS's ``FindNestedElementWithName``)."""
    return next((e for e in element if _tag(e) == name), None)
