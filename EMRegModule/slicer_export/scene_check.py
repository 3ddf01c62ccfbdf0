"""Whether a run's nodes show its results (3D Slicer's self-test, ``EMRegTest``, and the tests): positions read
back from MRML in world coordinates (RAS, mm, through the transform hierarchy) against the results (LPS, mm)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.detection.result import DetectionResult
from ..core.frames import LPS_TO_RAS, lps_to_ras_points
from ..core.registration import RegistrationResult
from ..names import CALIBRATION_NODE_NAME, MARKERS_NODE_NAME, PROBE_NODE_NAME, TRANSFORM_NODE_NAME


def scene_disagreements(scene: Any, detection: DetectionResult, registration: RegistrationResult,
                        probe_position_lps: np.ndarray | None = None) -> list[str]:
    """What the scene (a ``vtkMRMLScene``) shows differently from the results; empty when nothing.

    Checked: the markers at their origins (RAS, 1e-6 mm); the ``ReferenceToImage`` node equal to
    ``LPS_TO_RAS @ ReferenceToImage`` (1e-9); the calibration points under it, each paired one at its residual
    (1e-6 mm) from its marker's pinhole point (``origin + l * axis``); and with ``probe_position_lps`` (the last
    navigated probe position, image LPS mm) the probe pose under ``ReferenceToImage``, at that position."""
    import slicer.util

    found: list[str] = []
    markers = scene.GetFirstNodeByName(MARKERS_NODE_NAME)
    origins = np.array([m.origin for m in detection.markers], dtype=float).reshape(-1, 3)
    if markers is None or markers.GetNumberOfControlPoints() != len(detection.markers):
        return [f"{MARKERS_NODE_NAME}: not one control point per marker"]
    if not np.allclose(slicer.util.arrayFromMarkupsControlPoints(markers, world=True), lps_to_ras_points(origins),
                       atol=1e-6):
        found.append(f"{MARKERS_NODE_NAME}: not at the marker origins (RAS)")
    transform = scene.GetFirstNodeByName(TRANSFORM_NODE_NAME)
    if transform is None:
        return [*found, f"no {TRANSFORM_NODE_NAME} node"]
    matrix = slicer.util.arrayFromTransformMatrix(transform, toWorld=True)
    if not np.allclose(matrix, LPS_TO_RAS @ registration.reference_to_image, atol=1e-9):
        found.append(f"{TRANSFORM_NODE_NAME}: not LPS_TO_RAS @ ReferenceToImage")
    calibration = scene.GetFirstNodeByName(CALIBRATION_NODE_NAME)
    if calibration is None or calibration.GetTransformNodeID() != transform.GetID():
        return [*found, f"{CALIBRATION_NODE_NAME}: not under {TRANSFORM_NODE_NAME}"]
    points = slicer.util.arrayFromMarkupsControlPoints(calibration, world=True)
    labels = [calibration.GetNthControlPointLabel(i) for i in range(calibration.GetNumberOfControlPoints())]
    by_id = {m.id: m for m in detection.markers}
    for pair in registration.pairs:
        marker = by_id[pair["image_marker"]]
        pinhole = lps_to_ras_points(marker.origin + registration.sensor_offset_l_mm * marker.axis)[0]
        distance = float(np.linalg.norm(points[labels.index(pair["calibration_point"])] - pinhole))
        if abs(distance - float(pair["residual_mm"])) > 1e-6:
            found.append(f"calibration point {pair['calibration_point']}: {distance:.6f} mm from its pinhole point, "
                         f"not its residual {float(pair['residual_mm']):.6f} mm")
    if probe_position_lps is not None:
        probe = scene.GetFirstNodeByName(PROBE_NODE_NAME)
        if probe is None or probe.GetTransformNodeID() != transform.GetID():
            return [*found, f"{PROBE_NODE_NAME}: not under {TRANSFORM_NODE_NAME}"]
        probe_to_ras = slicer.util.arrayFromTransformMatrix(probe, toWorld=True)
        if not np.allclose(probe_to_ras[:3, 3], lps_to_ras_points(probe_position_lps)[0], atol=1e-6):
            found.append(f"{PROBE_NODE_NAME}: not at the last navigated position")
    return found
