"""Whether a run's nodes show its results, and the robot's nodes its outputs (3D Slicer's self-test, ``EMRegTest``,
and the tests): positions read back from MRML in world coordinates (RAS, mm, through the transform hierarchy) against
the results (LPS, mm)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.detection.result import DetectionResult
from ..core.frames import LPS_TO_RAS, lps_to_ras_points
from ..core.registration import RegistrationResult
from ..names import (
    CALIBRATION_NODE_NAME,
    GUIDE_MODEL_NODE_NAME,
    GUIDE_NODE_NAME,
    MARKERS_NODE_NAME,
    PROBE_NODE_NAME,
    ROBOT_PLAN_NODE_NAME,
    SENSOR_TO_FLANGE_NODE_NAME,
    TRACKER_TO_BASE_NODE_NAME,
    TRANSFORM_NODE_NAME,
)
from .robot_scene import RobotScene


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


def robot_disagreements(scene: Any, content: RobotScene) -> list[str]:
    """What the scene shows differently from the robot's outputs (:class:`RobotScene`); empty when nothing.

    Checked: ``SensorToFlange`` and ``TrackerToBase`` as they are (1e-9); with a target, ``NeedleGuideToRAS`` equal to
    ``LPS_TO_RAS @ NeedleGuideToImage`` (1e-9), the guide's model under it, its axis (+z, world) along the planned
    line Entry -> Target (RAS, 1e-5 degrees) and the needle at the planned depth on Target (1e-6 mm), and the plan's
    line at Entry and Target (RAS, 1e-6 mm)."""
    import slicer.util

    found: list[str] = []
    for name, matrix in ((SENSOR_TO_FLANGE_NODE_NAME, content.sensor_to_flange),
                         (TRACKER_TO_BASE_NODE_NAME, content.tracker_to_base)):
        node = scene.GetFirstNodeByName(name)
        if matrix is None:
            continue
        if node is None:
            found.append(f"no {name} node")
        elif not np.allclose(slicer.util.arrayFromTransformMatrix(node, toWorld=True), matrix, atol=1e-9):
            found.append(f"{name}: not the matrix of the calibration as it is")
    if content.needle_guide_to_image is None:
        return found
    guide = scene.GetFirstNodeByName(GUIDE_NODE_NAME)
    if guide is None:
        return [*found, f"no {GUIDE_NODE_NAME} node"]
    guide_to_ras = slicer.util.arrayFromTransformMatrix(guide, toWorld=True)
    if not np.allclose(guide_to_ras, LPS_TO_RAS @ content.needle_guide_to_image, atol=1e-9):
        found.append(f"{GUIDE_NODE_NAME}: not LPS_TO_RAS @ NeedleGuideToImage")
    model = scene.GetFirstNodeByName(GUIDE_MODEL_NODE_NAME)
    if model is None or model.GetTransformNodeID() != guide.GetID():
        found.append(f"{GUIDE_MODEL_NODE_NAME}: not under {GUIDE_NODE_NAME}")
    entry, target = lps_to_ras_points(np.vstack([content.entry_mm, content.target_mm]))
    direction = (target - entry) / np.linalg.norm(target - entry)
    axis = guide_to_ras[:3, 2]
    angle = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(axis, direction)), axis @ direction)))
    if angle > 1e-5:
        found.append(f"{GUIDE_NODE_NAME}: its axis is {angle:.6f} degrees off the planned line")
    tip = guide_to_ras[:3, 3] + content.reach_mm * guide_to_ras[:3, 2]
    if np.linalg.norm(tip - target) > 1e-6:
        found.append(f"{GUIDE_NODE_NAME}: a needle at the planned depth ends {np.linalg.norm(tip - target):.6f} mm "
                     "from Target")
    line = scene.GetFirstNodeByName(ROBOT_PLAN_NODE_NAME)
    if line is None or not np.allclose(slicer.util.arrayFromMarkupsControlPoints(line, world=True),
                                       np.vstack([entry, target]), atol=1e-6):
        found.append(f"{ROBOT_PLAN_NODE_NAME}: not the line Entry -> Target (RAS)")
    return found
