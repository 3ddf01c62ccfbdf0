"""The robot's part of a report (issue 39): the hand-eye calibration's fit to the recordings it was made from.

``robot_calibration.json`` names its recordings (``inputs``: the robot's log and the flange sensor's recording;
``emreg robot-calibrate`` writes them into its output folder); when they are still there, and are the same bytes
when the calibration recorded a sha256, :func:`load_robot_fit` recomputes the residual of every tracker sample and the
clock-offset profile (:mod:`EMRegModule.core.handeye_profile`). Otherwise it says why in one line, never a crash.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EMRegError
from ..io.handeye_inputs import PoseStream, read_robot_poses, read_sensor_poses
from ..io.provenance import file_sha256
from ..io.tum import read_tum
from .inputs import ReportInputs

if TYPE_CHECKING:
    from ..core.handeye_profile import CalibrationFit


def _recording(out_dir: Path, block: Any, what: str) -> tuple[Path | None, str | None]:
    """The file a calibration's ``inputs`` block names (a path relative to OUT, or as given), or why not."""
    if not isinstance(block, Mapping) or not block.get("path"):
        return None, f"robot_calibration.json names no {what}"
    named = Path(str(block["path"]))
    path = next((p for p in (out_dir / named, named) if p.is_file()), None)
    if path is None:
        return None, f"the {what} {named} is not there any more"
    if block.get("sha256") and file_sha256(path) != block["sha256"]:
        return None, f"{path} is not the {what} the calibration used (its sha256 differs)"
    return path, None


def _sensor_poses(path: Path, block: Mapping[str, Any]) -> PoseStream:
    """The flange sensor's poses: a TUM file as ``emreg robot-calibrate`` writes it, else the recording's sensor."""
    if path.suffix.lower() == ".tum":
        time_s, poses = read_tum(path)
        return PoseStream(time_s, poses, "flange sensor (TUM)")
    sensor = str(block.get("sensor") or "") or None
    if sensor is not None and sensor.startswith("port "):
        sensor = sensor[len("port "):]
    return read_sensor_poses(path, sensor)


def load_robot_fit(inputs: ReportInputs) -> tuple[CalibrationFit | None, str | None]:
    """The calibration's fit to its recordings, or None and why (None, None: no ``robot_calibration.json``)."""
    document = inputs.folder.robot_calibration
    if document is None:
        return None, None
    given = document.get("inputs") or {}
    tracker_block = given.get("tracker_recording") or given.get("tracker")
    robot_path, why = _recording(inputs.out_dir, given.get("robot_poses"), "robot's log")
    tracker_path, why_tracker = _recording(inputs.out_dir, tracker_block, "tracker recording")
    if robot_path is None or tracker_path is None:
        return None, why or why_tracker
    from ..core.handeye_profile import calibration_fit  # scipy.stats and scipy.signal: only with a robot calibration

    try:
        robot = read_robot_poses(robot_path, str(given["robot_poses"].get("transform") or "FlangeToBase"))
        tracker = _sensor_poses(tracker_path, tracker_block)
        rejected = [int(frame["index"]) for frame in (document.get("frames") or {}).get("rejected_frames", [])]
        fit = calibration_fit(robot.time_s, robot.poses, tracker.time_s, tracker.poses,
                              np.asarray(document["SensorToFlange"], dtype=float),
                              np.asarray(document["TrackerToBase"], dtype=float), float(document["time_offset_s"]),
                              np.asarray(rejected, dtype=int))
    except EMRegError as exc:
        return None, str(exc)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        return None, f"robot_calibration.json does not match its recordings ({exc!s:.80})"
    return fit, None
