"""A plan file: a 3D Slicer markups JSON holding the target (and the entry) of a trajectory, read into a
:class:`~EMRegModule.core.guidance.Plan` (image space, LPS mm).

:func:`read_plan` reads the file's defined control points (coordinates as the file declares them,
``coordinateSystem`` LPS or RAS, ``coordinateUnits``, converted to LPS mm as for fiducials:
:func:`~EMRegModule.io.markups.read_markups_with_frame`) and the points of its ``Line`` markup, if any; the rules
that make a plan of them (a Line, points labelled Entry and Target, or a single point) and the one-line refusals
are :func:`~EMRegModule.core.plan.plan_from_points`'s.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..core.guidance import Plan
from ..core.plan import plan_from_points
from ..errors import EMRegError
from .atomic import read_json
from .markups import read_markups_with_frame


def read_plan(path: str | os.PathLike[str]) -> Plan:
    """The plan of a Slicer markups JSON file (module docstring), in image space (LPS mm)."""
    labels, positions, declared = read_markups_with_frame(path)
    document = read_json(path, "markups JSON")
    lines = _line_points(document, labels, positions, path)
    return plan_from_points(labels, positions, lines, str(path), declared["coordinate_system"])


def _line_points(document: Any, labels: list[str], positions: np.ndarray,
                 path: str | os.PathLike[str]) -> list[tuple[str, np.ndarray]] | None:
    """The (label, LPS position) of the defined points of the file's Line markup, in order; None without one.

    ``labels`` / ``positions``: every defined point of the file, markup after markup (as
    :func:`~EMRegModule.io.markups.read_markups_with_frame` returns them), which this splits by markup."""
    found = None
    start = 0
    try:
        for markup in document["markups"]:
            count = sum(1 for point in markup.get("controlPoints", [])
                        if point.get("positionStatus", "defined") == "defined")
            if str(markup.get("type", "")).lower() == "line":
                if found is not None:
                    raise EMRegError(f"{path}: plan: several Line markups; give one planned line")
                found = [(labels[k], positions[k]) for k in range(start, start + count)]
            start += count
    except (KeyError, TypeError, AttributeError):
        return None
    return found
