"""``OUT/navigation.csv`` (``time_s,x_mm,y_mm,z_mm,label,status``, then the guidance columns with a plan; positions
in image space, LPS mm): written by :func:`write_navigation_csv` from a
:class:`~EMRegModule.core.navigation.NavigationResult`; read by the report and the 3D Slicer bundle.
The numbers are parsed by ``numpy.loadtxt`` (a full recording: ~20 ms instead of ~0.1 s row by row); a file
it cannot take (quoted labels, ragged rows) is read row by row with :mod:`csv`, with the same result.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from ..core.navigation import NavigationResult
from ..errors import EMRegError
from .atomic import atomic_path

POSITION_COLUMNS = ("x_mm", "y_mm", "z_mm")
#: ``status`` (added): the pose's status, ``OK`` or ``INVALID`` (PLUS's TransformStatus names; see
#: :mod:`EMRegModule.core.checkpoints`); the spec's five columns come first, unchanged.
NAVIGATION_HEADER = "time_s,x_mm,y_mm,z_mm,label,status"


def read_navigation_csv(path: Path) -> tuple[np.ndarray, list[str]]:
    """Probe positions (N, 3, image LPS mm) and labels of an ``OUT/navigation.csv``."""
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    header_line, _, body = text.partition("\n")
    header = [name.strip() for name in next(csv.reader([header_line]), [])]
    missing = set(POSITION_COLUMNS) - set(header)
    if missing:
        raise EMRegError(f"{path}: navigation CSV lacks column(s) {', '.join(sorted(missing))}")
    columns = [header.index(name) for name in POSITION_COLUMNS]
    label = header.index("label") if "label" in header else None
    if '"' not in body:  # no quoted field: every line splits at its commas
        lines = [line for line in body.splitlines() if line]
        try:
            positions = np.loadtxt(lines, delimiter=",", usecols=columns, dtype=float, ndmin=2).reshape(-1, 3)
        except ValueError:
            pass  # something loadtxt does not take: the row-by-row reading below says what
        else:
            labels = [""] * len(lines) if label is None else [_field(line, label) for line in lines]
            return positions, labels
    rows = [row for row in csv.reader(io.StringIO(body)) if row]
    try:
        positions = np.array([[row[i] for i in columns] for row in rows], dtype=float).reshape(-1, 3)
    except (ValueError, IndexError):
        raise EMRegError(f"{path}: navigation CSV holds a non-numeric position") from None
    labels = [row[label].strip() if label is not None and label < len(row) else "" for row in rows]
    return positions, labels


def _field(line: str, index: int) -> str:
    fields = line.split(",")
    return fields[index].strip() if index < len(fields) else ""


#: The guidance columns appended to ``navigation.csv``, in this order, when a plan is given
#: (:mod:`EMRegModule.core.guidance`).
GUIDANCE_COLUMNS = ("target_distance_mm", "lateral_mm", "angle_deg", "to_go_mm")
#: The columns :func:`read_guidance_columns` returns (the time, and the guidance columns of a navigation with a plan).
GUIDANCE_SERIES = ("time_s", *GUIDANCE_COLUMNS)


def read_guidance_columns(path: Path) -> dict[str, np.ndarray] | None:
    """The time (s) and the guidance columns (mm, degrees; NaN where empty) of an ``OUT/navigation.csv`` written with
    a plan, and ``ok`` (the rows whose status is OK); None when it has no guidance columns."""
    with open(path, newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        if not set(GUIDANCE_SERIES) <= set(reader.fieldnames or ()):
            return None
        rows = list(reader)
    try:
        series = {name: np.array([float(r[name]) if r[name] else np.nan for r in rows]) for name in GUIDANCE_SERIES}
    except (TypeError, ValueError):
        raise EMRegError(f"{path}: navigation CSV holds a non-numeric guidance value") from None
    series["ok"] = np.array([(r.get("status") or "OK") == "OK" for r in rows])
    return series


def format_navigation_csv(result: NavigationResult) -> str:
    """``time_s,x_mm,y_mm,z_mm,label,status`` text, one row per probe sample (positions in LPS mm), followed by
    :data:`GUIDANCE_COLUMNS` (mm, degrees; empty where undefined) when the result has guidance numbers."""
    position = result.position_mm
    status = ["OK"] * len(result) if result.status is None else result.status.tolist()
    rows = zip(result.time_s.tolist(), position[:, 0].tolist(), position[:, 1].tolist(), position[:, 2].tolist(),
               result.label.tolist(), status, strict=True)
    lines = [NAVIGATION_HEADER if result.guidance is None else ",".join((NAVIGATION_HEADER, *GUIDANCE_COLUMNS))]
    lines.extend(f"{t:.4f},{x:.4f},{y:.4f},{z:.4f},{_csv_label(label)},{s}" for t, x, y, z, label, s in rows)
    if result.guidance is not None:
        numbers = result.guidance
        extra = zip(*(getattr(numbers, name).tolist() for name in GUIDANCE_COLUMNS), strict=True)
        lines[1:] = [f"{line},{guidance_fields(values)}" for line, values in zip(lines[1:], extra, strict=True)]
    return "\n".join(lines) + "\n"


def guidance_fields(values: tuple[float, ...] | list[float]) -> str:
    """The guidance columns of one row: each number with 4 decimals, empty where it is undefined (NaN)."""
    return ",".join("" if v != v else f"{v:.4f}" for v in values)


def _csv_label(label: object) -> str:
    text = "" if label is None else str(label)
    if any(c in text for c in ',"\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def write_navigation_csv(result: NavigationResult, path: str | os.PathLike[str]) -> None:
    """Write ``navigation.csv`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(format_navigation_csv(result), encoding="utf-8")
