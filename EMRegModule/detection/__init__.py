"""Marker detection and pose estimation in CT (paper section 2.4): ``emreg detect``.

``detect_markers(image, model, settings, progress)`` finds the PVC markers in a CT and returns
each one's origin (bottom-face centre) and +Y axis in image space (LPS, mm);
``write_detection`` writes ``markers.json`` and ``markers.mrk.json``; ``read_detection`` reads
``markers.json`` back.
"""

from .detect import detect_markers
from .result import DetectedMarker, DetectionResult, RejectedCandidate, read_detection, write_detection
from .settings import DetectionSettings, settings_from_dict

__all__ = [
    "DetectedMarker", "DetectionResult", "DetectionSettings", "RejectedCandidate", "detect_markers",
    "read_detection", "settings_from_dict", "write_detection",
]
