"""The robot's part of a run's scene (issue 39): what it shows (:class:`RobotScene`, from the robot's outputs in a run
folder) and its nodes (:func:`build_robot_scene`), in the ``EMReg.mrb`` bundle and in the 3D Slicer module's robot
panel.

- ``SensorToFlange`` and ``TrackerToBase``: linear transform nodes whose "to parent" is the matrix as it is (mm),
  as the ``.h5`` files of ``emreg handeye`` load (tracker and robot side frames: no LPS/RAS flip);
- the needle guide on its plan: ``NeedleGuideToRAS`` = ``LPS_TO_RAS @ NeedleGuideToImage`` (the guide's frame
  unchanged, the image side RAS, as ``ReferenceToImage``), with the guide's model under it (its exit at the origin,
  its axis along +z to the planned depth), and the planned line Entry -> Target (RAS).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.frames import LPS_TO_RAS, lps_to_ras_points
from ..core.transforms import invert_rigid
from ..io.run_folder import RunFolder
from ..names import (
    GUIDE_MODEL_NODE_NAME,
    GUIDE_NODE_NAME,
    ROBOT_PLAN_NODE_NAME,
    SENSOR_TO_FLANGE_NODE_NAME,
    TRACKER_TO_BASE_NODE_NAME,
)
from .nodes import show_guide_model, show_line, show_transform


@dataclass
class RobotScene:
    """What the robot's nodes show (4x4 mm; points LPS mm): the calibration (None without one), and with a target
    the guide's pose in the image (``NeedleGuideToImage``, its exit on Entry or ``standoff`` before it), Entry,
    Target and the depth Entry -> Target plus standoff (mm)."""

    sensor_to_flange: np.ndarray | None = None
    tracker_to_base: np.ndarray | None = None
    needle_guide_to_image: np.ndarray | None = None
    entry_mm: np.ndarray | None = None
    target_mm: np.ndarray | None = None
    reach_mm: float = 0.0


def guide_to_image(target: dict[str, Any]) -> np.ndarray:
    """``NeedleGuideToImage`` (4x4, mm, LPS) of a ``robot_target.json``: ``ReferenceToImage @ inv(ReferenceToTracker)
    @ inv(TrackerToBase) @ NeedleGuideToBase``."""
    matrices = {key: np.asarray(target[key], dtype=float) for key in
                ("ReferenceToImage", "ReferenceToTracker", "TrackerToBase", "NeedleGuideToBase")}
    return (matrices["ReferenceToImage"] @ invert_rigid(matrices["ReferenceToTracker"])
            @ invert_rigid(matrices["TrackerToBase"]) @ matrices["NeedleGuideToBase"])


def robot_scene_of(folder: RunFolder) -> RobotScene | None:
    """The robot's nodes for a run folder's robot outputs (None without any). The calibration is
    ``robot_calibration.json``'s, else the one ``robot_target.json`` carries."""
    calibration, target = folder.robot_calibration, folder.robot_target
    if calibration is None and target is None:
        return None
    source = calibration if calibration is not None else target
    content = RobotScene(np.asarray(source["SensorToFlange"], dtype=float),
                         np.asarray(source["TrackerToBase"], dtype=float))
    if target is not None:
        content.needle_guide_to_image = guide_to_image(target)
        content.entry_mm = np.asarray(target["entry_image_mm"], dtype=float).reshape(3)
        content.target_mm = np.asarray(target["target_image_mm"], dtype=float).reshape(3)
        content.reach_mm = float(target.get("depth_mm", 0.0)) + float(target.get("standoff_mm", 0.0))
    return content


def build_robot_scene(scene: Any, content: RobotScene, nodes: dict[str, Any]) -> dict[str, Any]:
    """Add (or update, reusing ``nodes``) the robot's nodes on ``scene``; returns them by name."""
    built: dict[str, Any] = {}
    for name, matrix in ((SENSOR_TO_FLANGE_NODE_NAME, content.sensor_to_flange),
                         (TRACKER_TO_BASE_NODE_NAME, content.tracker_to_base)):
        if matrix is not None:
            built[name] = show_transform(scene, name, matrix, node=nodes.get(name))
    if content.needle_guide_to_image is not None:
        guide = built[GUIDE_NODE_NAME] = show_transform(scene, GUIDE_NODE_NAME,
                                                        LPS_TO_RAS @ content.needle_guide_to_image,
                                                        node=nodes.get(GUIDE_NODE_NAME))
        built[GUIDE_MODEL_NODE_NAME] = show_guide_model(scene, GUIDE_MODEL_NODE_NAME, guide, content.reach_mm,
                                                        node=nodes.get(GUIDE_MODEL_NODE_NAME))
        built[ROBOT_PLAN_NODE_NAME] = show_line(scene, ROBOT_PLAN_NODE_NAME, ["Entry", "Target"],
                                                lps_to_ras_points(np.vstack([content.entry_mm, content.target_mm])),
                                                (0.9, 0.1, 0.1), node=nodes.get(ROBOT_PLAN_NODE_NAME))
    nodes.update(built)
    return built
