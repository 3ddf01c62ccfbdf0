"""Detection results, and their JSON form (``markers.json``, written by :mod:`EMRegModule.io.markers_json`).

All positions and directions are in image space (CT physical LPS, mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...errors import EMRegError
from ...names import MARKERS_JSON
from ..transforms import make_transform, rotation_from_y_axis


def marker_to_image_from_axis(origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``MarkerToImage`` (4x4) of an axisymmetric marker: +Y along ``axis``, origin at ``origin``.

    The spin about +Y is not observable; it is fixed by ``transforms.rotation_from_y_axis``.
    """
    return make_transform(rotation_from_y_axis(axis), origin)


@dataclass
class DetectedMarker:
    """One marker found in the CT: bottom-face centre ``origin`` and unit +Y ``axis`` (LPS, mm)."""

    id: str
    origin: np.ndarray
    axis: np.ndarray
    volume_mm3: float
    fit_rms_mm: float
    marker_to_image: np.ndarray = field(default=None)  # type: ignore[assignment]
    marker_hu: float = float("nan")  # the median intensity of its core (HU), as measured in the CT

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        axis = np.asarray(self.axis, dtype=float).reshape(3)
        self.axis = axis / np.linalg.norm(axis)
        if self.marker_to_image is None:
            self.marker_to_image = marker_to_image_from_axis(self.origin, self.axis)
        self.marker_to_image = np.asarray(self.marker_to_image, dtype=float).reshape(4, 4)

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "origin": [float(v) for v in self.origin], "axis": [float(v) for v in self.axis],
                "volume_mm3": round(float(self.volume_mm3), 2), "fit_rms_mm": round(float(self.fit_rms_mm), 4)}


@dataclass
class RejectedCandidate:
    """A blob of marker-like density that is not a marker, and why (``code``: a short keyword)."""

    centroid: np.ndarray
    volume_mm3: float
    reason: str
    code: str = "other"
    marker_hu: float = float("nan")  # the median intensity of its core (HU)

    def __post_init__(self) -> None:
        self.centroid = np.asarray(self.centroid, dtype=float).reshape(3)

    def to_json(self) -> dict[str, Any]:
        return {"centroid": [float(v) for v in self.centroid], "volume_mm3": round(float(self.volume_mm3), 1),
                "reason": self.reason, "code": self.code}


@dataclass
class DetectionResult:
    """Markers found in a CT (``markers``, ids I01, I02, ...) and candidates turned down (``rejected``).

    ``image`` is the geometry block of ``markers.json`` (size, spacing, origin, direction).
    """

    markers: list[DetectedMarker]
    rejected: list[RejectedCandidate] = field(default_factory=list)
    image: dict[str, Any] = field(default_factory=dict)
    ct_series: dict[str, Any] | None = None  # a DICOM CT: the series used and the others (``io.dicom_series``)
    band: dict[str, Any] | None = None  # the intensity band used (low_hu, high_hu, source, marker_hu)
    provenance: dict[str, Any] | None = None  # what it was made from (``EMRegModule.io.provenance``)

    def __len__(self) -> int:
        return len(self.markers)

    @property
    def origins(self) -> np.ndarray:
        """(N, 3) marker origins, LPS mm."""
        return np.array([m.origin for m in self.markers], dtype=float).reshape(-1, 3)

    @property
    def axes(self) -> np.ndarray:
        """(N, 3) unit marker axes (+Y), LPS."""
        return np.array([m.axis for m in self.markers], dtype=float).reshape(-1, 3)

    def marker(self, marker_id: str) -> DetectedMarker:
        for m in self.markers:
            if m.id == marker_id:
                return m
        raise KeyError(marker_id)

    def to_json(self) -> dict[str, Any]:
        """The ``markers.json`` document (spec)."""
        document = {"coordinate_system": "LPS", "image": self.image,
                    "markers": [m.to_json() for m in self.markers],
                    "rejected": [r.to_json() for r in self.rejected]}
        if self.band is not None:
            document["band"] = self.band
        if self.ct_series is not None:
            document["ct_series"] = self.ct_series
        if self.provenance is not None:
            document["provenance"] = self.provenance
        return document

    @classmethod
    def from_json(cls, document: dict[str, Any], source: str = MARKERS_JSON) -> DetectionResult:
        """Parse a ``markers.json`` document; a malformed one raises :class:`EMRegError` naming ``source``."""
        try:
            system = document.get("coordinate_system", "LPS")
            if system != "LPS":
                raise EMRegError(f"{source}: coordinate_system must be LPS, got {system!r}")
            markers = []
            for i, m in enumerate(document["markers"]):
                origin = np.asarray(m["origin"], dtype=float)
                axis = np.asarray(m["axis"], dtype=float)
                if origin.shape != (3,) or axis.shape != (3,) or not np.all(np.isfinite(np.r_[origin, axis])) \
                        or np.linalg.norm(axis) < 1e-9:
                    raise EMRegError(f"{source}: marker {i + 1} needs a finite origin and a non-zero axis")
                markers.append(DetectedMarker(
                    id=str(m.get("id") or f"I{i + 1:02d}"), origin=origin, axis=axis,
                    volume_mm3=float(m.get("volume_mm3", np.nan)), fit_rms_mm=float(m.get("fit_rms_mm", np.nan))))
            rejected = [RejectedCandidate(np.asarray(r["centroid"], dtype=float), float(r.get("volume_mm3", np.nan)),
                                          str(r.get("reason", "")), str(r.get("code", "other")))
                        for r in document.get("rejected", [])]
        except EMRegError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise EMRegError(f"{source}: not a valid markers.json ({exc!s:.100})") from None
        ids = [m.id for m in markers]
        if len(set(ids)) != len(ids):
            raise EMRegError(f"{source}: marker ids must be unique")
        series, band = document.get("ct_series"), document.get("band")
        provenance = document.get("provenance")
        return cls(markers, rejected, dict(document.get("image", {})), series if isinstance(series, dict) else None,
                   band if isinstance(band, dict) else None, provenance if isinstance(provenance, dict) else None)


