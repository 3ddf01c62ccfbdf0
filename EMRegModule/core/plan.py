"""A plan: the target (and the entry) of a trajectory, a :class:`~EMRegModule.core.guidance.Plan` (image space,
LPS mm), made of labelled points (:func:`plan_from_points`: those of a plan file, read by
:mod:`EMRegModule.io.plan_markups`, or of a 3D Slicer markups node).

What makes the plan, in this order:

1. a markup of ``type`` ``Line`` with two defined control points: Entry -> Target (Slicer's line runs from its
   first point to its second; points labelled ``Entry`` / ``Target`` are taken by their labels whatever the order);
2. points labelled ``Entry`` and ``Target`` (case and surrounding spaces ignored), in any point list: one ``Target``
   is needed, an ``Entry`` is optional (without it, a target alone);
3. a single defined point (whatever its label): a target alone.

Refused with one line naming the source (:class:`~EMRegModule.errors.EMRegError`, exit 2): no usable points, two
points labelled ``Target`` (or ``Entry``), several unlabelled points, a line without two points, Entry and Target
closer than :data:`~EMRegModule.core.guidance.MIN_PLAN_LENGTH_MM`. :func:`check_plan_in_image` refuses a plan outside
the CT.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import EMRegError
from .guidance import MIN_PLAN_LENGTH_MM, Plan

ENTRY_LABEL = "entry"
TARGET_LABEL = "target"


def plan_from_points(labels: list[str], positions: np.ndarray, line: list[tuple[str, np.ndarray]] | None,
                     source: str, coordinate_system: str = "LPS") -> Plan:
    """The plan of labelled points (LPS mm, (N, 3)) by the rules of the module docstring; ``line``: the (label,
    position) points of a Line markup, when there is one (they then make the plan). ``source`` names them in the
    one-line refusals (a file, a 3D Slicer markups node)."""
    where = f"{source}: plan"
    if line is not None:
        if len(line) != 2:
            raise EMRegError(f"{where}: the Line markup has {len(line)} defined control point(s); a planned line "
                             "needs two (Entry, then Target)")
        named = {label.strip().lower(): p for label, p in line}
        if set(named) == {ENTRY_LABEL, TARGET_LABEL}:
            entry, target = named[ENTRY_LABEL], named[TARGET_LABEL]
        else:
            entry, target = line[0][1], line[1][1]
        return _checked(Plan(target, entry, source, coordinate_system), where)
    keys = [label.strip().lower() for label in labels]
    for name in (TARGET_LABEL, ENTRY_LABEL):
        if keys.count(name) > 1:
            raise EMRegError(f"{where}: {keys.count(name)} points are labelled {name.capitalize()!r}; label exactly "
                             "one point Target (and at most one Entry)")
    if TARGET_LABEL in keys:
        target = positions[keys.index(TARGET_LABEL)]
        entry = positions[keys.index(ENTRY_LABEL)] if ENTRY_LABEL in keys else None
        return _checked(Plan(target, entry, source, coordinate_system), where)
    if ENTRY_LABEL in keys:
        raise EMRegError(f"{where}: a point labelled Entry but none labelled Target; label the target point Target")
    if len(labels) == 1:
        return Plan(positions[0], None, source, coordinate_system)
    if not labels:
        raise EMRegError(f"{where}: no defined control point; give a Line (Entry, Target), points labelled Entry "
                         "and Target, or a single target point")
    raise EMRegError(f"{where}: {len(labels)} points and none labelled Target; label the points Entry and Target, "
                     "or give a Line markup")


def _checked(plan: Plan, where: str) -> Plan:
    length = plan.length_mm
    if length is not None and length < MIN_PLAN_LENGTH_MM:
        raise EMRegError(f"{where}: Entry and Target are {length:.2f} mm apart (a zero-length line has no "
                         f"direction); place them at least {MIN_PLAN_LENGTH_MM:g} mm apart")
    return plan


def check_plan_in_image(plan: Plan, geometry: Mapping[str, Any], ct_name: str = "the CT") -> None:
    """Refuse (one line) a plan whose target or entry lies outside the CT's extent (half a voxel beyond the first and
    last voxel centres). ``geometry``: the CT's ``size``, ``spacing``, ``origin``, ``direction`` (9 numbers,
    row-major), as in ``markers.json``'s ``image``."""
    size = np.asarray(geometry["size"], dtype=float).reshape(3)
    spacing = np.asarray(geometry["spacing"], dtype=float).reshape(3)
    origin = np.asarray(geometry["origin"], dtype=float).reshape(3)
    direction = np.asarray(geometry["direction"], dtype=float).reshape(3, 3)
    for name, point in (("Target", plan.target_mm), ("Entry", plan.entry_mm)):
        if point is None:
            continue
        index = np.linalg.solve(direction * spacing, np.asarray(point, dtype=float) - origin)
        if np.any(index < -0.5) or np.any(index > size - 0.5):
            where = ", ".join(f"{v:.1f}" for v in point)
            raise EMRegError(f"{plan.source}: plan: the {name} [{where}] mm (LPS) lies outside {ct_name}'s extent; "
                             "plan in the CT the registration was made on (mind LPS / RAS: the file says "
                             f"{plan.coordinate_system})")
