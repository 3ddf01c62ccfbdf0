"""Fiducials: the named image-side points of a registration onto points (:mod:`.fiducial_registration`), and the
check every fiducial set passes: at least :data:`MIN_FIDUCIALS` points, finite, unique labels, not all on one line
(within :data:`COLLINEAR_TOLERANCE_MM`). Read from files by :mod:`EMRegModule.io.fiducials`; handed over from
3D Slicer's markups by the Slicer module."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import EMRegError

#: A rigid fit needs three points not on one line.
MIN_FIDUCIALS = 3


#: Fiducials all within this distance (mm) of one line are collinear: the rotation about it is unknown.
COLLINEAR_TOLERANCE_MM = 1.0


@dataclass
class Fiducials:
    """Named fiducial points (N, 3, mm) in the fiducials' frame: image space (LPS) for Slicer markups, the
    phantom's frame for a PLUS phantom definition. ``declared``: what the file said of its frame and units."""

    labels: list[str]
    positions: np.ndarray
    source: str
    format: str
    frame: str = "LPS"
    declared: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.labels)

    def to_json(self) -> dict[str, Any]:
        """The ``fiducials`` block of ``registration.json``: where the points came from and the points (mm)."""
        return {"file": self.source, "format": self.format, "frame": self.frame, "declared": dict(self.declared),
                "points": [{"label": label, "position": [float(v) for v in position]}
                           for label, position in zip(self.labels, self.positions, strict=True)]}


def check_fiducials(fiducials: Fiducials) -> None:
    """Refuse (:class:`EMRegError`, one line naming the file) fewer than :data:`MIN_FIDUCIALS` points, repeated
    labels, non-finite positions, or points all on one line."""
    where = fiducials.source
    n = len(fiducials.labels)
    if n < MIN_FIDUCIALS:
        raise EMRegError(f"{where}: {n} fiducial(s); a registration needs at least {MIN_FIDUCIALS} (not on one line)")
    repeated = sorted({label for label in fiducials.labels if fiducials.labels.count(label) > 1})
    if repeated:
        raise EMRegError(f"{where}: fiducial label(s) {', '.join(map(repr, repeated))} used more than once; each "
                         "fiducial needs its own name (registration.json pairs by name)")
    positions = np.asarray(fiducials.positions, dtype=float)
    if positions.shape != (n, 3) or not np.all(np.isfinite(positions)):
        raise EMRegError(f"{where}: every fiducial needs a finite 3D position")
    off_line = _line_distances_mm(positions)
    if float(np.max(off_line)) <= COLLINEAR_TOLERANCE_MM:
        raise EMRegError(f"{where}: the {n} fiducials lie on one line (all within {float(np.max(off_line)):.2f} mm "
                         f"of it; {COLLINEAR_TOLERANCE_MM:g} mm allowed): the rotation about that line is unknown; "
                         "add a fiducial off the line")


def _line_distances_mm(points: np.ndarray) -> np.ndarray:
    """Distance (mm) of each point (N, 3) from the least-squares line through them."""
    centred = np.asarray(points, dtype=float) - np.mean(points, axis=0)
    direction = np.linalg.svd(centred, full_matrices=False)[2][0]
    return np.linalg.norm(centred - np.outer(centred @ direction, direction), axis=1)
