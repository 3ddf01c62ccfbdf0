"""Marker detection and pose estimation in CT (paper section 2.4): ``emreg detect``.

``detect_markers(image, model, settings, progress)`` finds the PVC markers in a CT and returns
each one's origin (bottom-face centre) and +Y axis in image space (LPS, mm). Its files, ``markers.json`` and
``markers.mrk.json``, are written and read by :mod:`EMRegModule.io.markers_json`.
"""

from typing import TYPE_CHECKING, Any

from .result import DetectedMarker, DetectionResult, RejectedCandidate
from .settings import DetectionSettings, settings_from_dict

if TYPE_CHECKING:
    from .detect import detect_markers


def __getattr__(name: str) -> Any:
    """``detect_markers`` is imported when first asked for: its imagery libraries (scipy.ndimage, VTK) cost
    about 0.5 s that readers of ``markers.json`` (the report, navigate) do not need."""
    if name == "detect_markers":
        from .detect import detect_markers

        return detect_markers
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DetectedMarker", "DetectionResult", "DetectionSettings", "RejectedCandidate", "detect_markers",
    "settings_from_dict",
]
