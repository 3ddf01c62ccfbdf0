"""A tracked tool's files: the tool file EMReg reads, ``emreg pivot``'s outputs, and the pivot recording's poses.

The tool itself (``TipToProbe``, 4x4 mm: the tip frame into the probe sensor's frame) and its pivot calibration are
:mod:`EMRegModule.core.tool`'s.

Tool files (:func:`read_tool`), by name:

- ``*.json``: EMReg's ``tool_calibration.json`` (``{"TipToProbe": 4x4, ...}``, :func:`write_tool_calibration`);
- ``*.h5``, ``*.tfm``, ``*.txt``: an ITK transform file as 3D Slicer saves a linear transform node named
  ``TipToProbe``. ITK stores the *resampling* transform (it maps points of the parent frame, Probe, into the
  child frame, Tip: the inverse of the node's "to parent" matrix) in LPS, and 3D Slicer converts it to RAS on
  reading: a file holding ``T`` is the node ``TipToProbe = F @ inv(T) @ F`` with ``F = diag(-1, -1, 1)``.
  Both frames are tracker-side frames, which Slicer (as PLUS and SlicerIGT) uses unchanged, so the node's
  matrix is ``TipToProbe`` itself; :func:`write_tip_to_probe_itk` writes ``T = F @ ProbeToTip @ F``;
- ``*.xml``: a PLUS device-set file: ``<CoordinateDefinitions><Transform From="<Name>Tip" To="<Name>"
  Matrix="..."/>``, ``<Name>`` the tool's transform name (``Stylus``: the recording's ``StylusToTracker``).

:func:`pivot_poses` reads a pivot recording (a tracking CSV or a PLUS sequence file) into the tool sensor's poses
for :func:`~EMRegModule.core.tool.pivot_calibration`.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Any

import numpy as np

from ..core.frames import LPS_TO_RAS
from ..core.tool import ToolCalibration, check_tip_to_probe
from ..core.tracking import probe_in_reference
from ..core.transforms import invert_rigid
from ..errors import EMRegError
from ..names import TIP_TO_PROBE_H5, TOOL_CALIBRATION_JSON
from .atomic import atomic_write_json, read_json
from .itk_transform import read_itk_linear_matrix, write_itk_linear_matrix
from .recording import read_recording
from .sequence_metafile import (
    DEFAULT_PROBE_TRANSFORM,
    DEFAULT_REFERENCE_TRANSFORM,
    is_sequence_file,
    read_sequence_frames,
    recording_from_frames,
)


def read_tool(path: str | os.PathLike[str], name: str | None = None) -> ToolCalibration:
    """A tool from a file (module docstring), by its name: ``.json``, ``.h5`` / ``.tfm`` / ``.txt``, ``.xml``.

    ``name``: the tool's transform name (``[tool] name``), which picks the ``<Name>Tip`` transform of a PLUS
    device set and names the tool read, whatever its file calls it. Raises :class:`EMRegError` (one line) for a
    missing or unreadable file, a non-rigid matrix, and a PLUS file without the tip transform."""
    path = Path(path)
    if not path.is_file():
        raise EMRegError(f"{path}: tool file not found")
    suffix = path.suffix.lower()
    if suffix == ".json":
        tool = _read_tool_json(path)
    elif suffix in (".h5", ".hdf5", ".tfm", ".txt", ".mat"):
        tool = ToolCalibration(read_tip_to_probe_itk(path), str(path), None, "itk transform file")
    elif suffix == ".xml":
        tool = _read_plus_device_set(path, name)
    else:
        raise EMRegError(f"{path}: not a tool file EMReg reads (tool_calibration.json, an ITK transform "
                         ".h5/.tfm/.txt, or a PLUS device-set .xml)")
    if name:
        tool.name = name
    return tool


def _read_tool_json(path: Path) -> ToolCalibration:
    document = read_json(path, "tool calibration JSON")
    if not isinstance(document, dict) or "TipToProbe" not in document:
        raise EMRegError(f"{path}: not a tool calibration (no TipToProbe key)")
    matrix = check_tip_to_probe(document["TipToProbe"], str(path))
    name = document.get("tool")
    return ToolCalibration(matrix, str(path), str(name) if name else None, str(document.get("method", "file")),
                           rms_mm=_optional_float(document.get("rms_mm")))


def _optional_float(value: Any) -> float | None:
    try:
        return None if value is None else float(value)
    except (TypeError, ValueError):
        return None


def read_tip_to_probe_itk(path: str | os.PathLike[str]) -> np.ndarray:
    """``TipToProbe`` (4x4, mm) from an ITK transform file as 3D Slicer writes a ``TipToProbe`` node
    (``F @ inv(T) @ F`` of the stored ``T``; module docstring)."""
    stored = read_itk_linear_matrix(path)
    return check_tip_to_probe(LPS_TO_RAS @ np.linalg.inv(stored) @ LPS_TO_RAS, str(path))


def write_tip_to_probe_itk(path: str | os.PathLike[str], tip_to_probe: np.ndarray) -> None:
    """Write ``TipToProbe`` as an ITK transform file that 3D Slicer loads as the node ``TipToProbe``
    (``T = F @ ProbeToTip @ F``; module docstring), atomically."""
    write_itk_linear_matrix(path, LPS_TO_RAS @ invert_rigid(tip_to_probe) @ LPS_TO_RAS)


def _read_plus_device_set(path: Path, name: str | None) -> ToolCalibration:
    """The ``<Name>Tip`` -> ``<Name>`` transform of a PLUS device set's ``CoordinateDefinitions``."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError, UnicodeDecodeError) as exc:
        raise EMRegError(f"{path}: not a readable XML file ({exc!s:.80})") from None
    tips = {}
    for element in root.iter("Transform"):
        source, target = element.get("From", ""), element.get("To", "")
        if source.endswith("Tip") and source[:-3] == target and target:
            tips[target] = element
    if name is not None:
        wanted = name[:-len("ToTracker")] if name.endswith("ToTracker") else name
        if wanted not in tips:
            found = ", ".join(f'From="{t}Tip" To="{t}"' for t in tips) or "none"
            raise EMRegError(f'{path}: no tip transform <Transform From="{wanted}Tip" To="{wanted}"> in '
                             f"CoordinateDefinitions (tip transforms found: {found})")
        chosen = wanted
    elif len(tips) == 1:
        chosen = next(iter(tips))
    elif not tips:
        raise EMRegError(f'{path}: no tool tip transform in CoordinateDefinitions (a <Transform From="<Name>Tip" '
                         'To="<Name>" Matrix="..."/>, e.g. From="StylusTip" To="Stylus")')
    else:
        raise EMRegError(f"{path}: several tool tip transforms ({', '.join(tips)}); name the tool with "
                         "[tool] name in case.toml")
    text = tips[chosen].get("Matrix", "")
    try:
        numbers = [float(v) for v in text.split()]
    except ValueError:
        raise EMRegError(f'{path}: the Matrix of From="{chosen}Tip" To="{chosen}" holds a non-number') from None
    if len(numbers) != 16:
        raise EMRegError(f'{path}: the Matrix of From="{chosen}Tip" To="{chosen}" has {len(numbers)} numbers, 16 '
                         "expected (4x4, row-major)")
    matrix = check_tip_to_probe(np.reshape(numbers, (4, 4)), f'{path} (From="{chosen}Tip" To="{chosen}")')
    error = _optional_float(tips[chosen].get("Error"))
    return ToolCalibration(matrix, str(path), chosen, "PLUS device set", rms_mm=error)


def write_tool_calibration(tool: ToolCalibration, out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``OUT/tool_calibration.json`` and ``OUT/TipToProbe.h5`` (for 3D Slicer), each atomically."""
    out = Path(out)
    json_path, itk_path = out / TOOL_CALIBRATION_JSON, out / TIP_TO_PROBE_H5
    atomic_write_json(json_path, tool.to_json())
    write_tip_to_probe_itk(itk_path, tool.tip_to_probe)
    return json_path, itk_path


def pivot_poses(path: str | os.PathLike[str], settings: Any, reference_port: int, probe_port: int
                ) -> tuple[np.ndarray, str, str | None, list[str]]:
    """The tool sensor's poses of a pivot recording: ``ProbeToReference`` (N, 4, 4), or ``ProbeToTracker`` when
    the recording has no reference sensor; the frame's name, the tool's name (a sequence file's transform without
    ``ToTracker``, e.g. ``Stylus``; None for a CSV), and the recording's warnings. ``settings``: the typed
    ``case.toml`` (its ``[sensors]`` transform names). In a sequence file without the probe's transform, the one
    transform there is, or the one besides the reference, is the tool (with a warning)."""
    path = Path(path)
    name = None
    warnings: list[str] = []
    if is_sequence_file(path):
        frames = read_sequence_frames(path)
        reference = settings.sensors.reference_transform or DEFAULT_REFERENCE_TRANSFORM
        tool = settings.sensors.probe_transform or DEFAULT_PROBE_TRANSFORM
        others = [n for n in frames.names if n != reference]
        if tool not in frames.matrices and len(others) == 1 and settings.sensors.probe_transform is None:
            besides = f"transform besides {reference}" if reference in frames.matrices else "transform"
            warnings.append(f"{path}: no {tool}Transform; {others[0]}Transform is the only {besides}: taken as the "
                            "tool")
            tool = others[0]
        if tool not in frames.matrices:
            raise EMRegError(f"{path}: no {tool}Transform (the tool) in the file; it holds "
                             f"{', '.join(n + 'Transform' for n in frames.names) or 'no transforms'}; name the tool "
                             "with [sensors] probe_transform in case.toml")
        name = tool[:-len("ToTracker")] if tool.endswith("ToTracker") else tool
        ports = {tool: probe_port}
        if reference in frames.matrices:
            ports = {reference: reference_port, tool: probe_port}
        recording = recording_from_frames(frames, ports)
    else:
        recording = read_recording(path, settings, reference_port, probe_port)
    warnings += recording.warnings
    if reference_port not in recording.sensors:
        return recording.for_sensor(probe_port, "probe").transforms(), "Tracker", name, warnings
    samples = probe_in_reference(recording, reference_port, probe_port, check_ports=False)
    return samples.probe_to_reference, "Reference", name, warnings
