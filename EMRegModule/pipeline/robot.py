"""The robot's workflow from files (issue 39), what ``emreg handeye`` and ``emreg robot-target`` and the 3D Slicer
module's robot panel call.

:func:`calibrate_from_recordings` writes ``OUT/robot_calibration.json`` (``SensorToFlange``, ``TrackerToBase``:
4x4 mm, with ``FlangeToBase @ SensorToFlange = TrackerToBase @ SensorToTracker``; ``time_offset_s`` with
``t_tracker = t_robot + time_offset_s``; residuals, frames used and rejected, predicted uncertainty) and the two
transforms for 3D Slicer, ``OUT/SensorToFlange.h5`` and ``OUT/TrackerToBase.h5``.

:func:`target_from_files` writes ``OUT/robot_target.json``: the ``FlangeToBase`` (4x4 mm) that puts the needle
guide's exit on Entry with its +z along Entry -> Target, and the predicted error at the target.

Bad input raises :class:`~EMRegModule.errors.EMRegError` (exit 2), data that do not allow a safe answer
:class:`~EMRegModule.errors.NoSafeAnswerError` (exit 3); nothing is written then.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..core.handeye import HandEyeResult, calibrate_hand_eye
from ..core.robot_target import RobotTarget, robot_target
from ..core.tool import check_tip_to_probe
from ..core.transforms import check_rigid
from ..devices.device_url import SCHEMES
from ..devices.sources import open_source
from ..errors import EMRegError
from ..io.atomic import atomic_path, atomic_write_json, read_json, to_jsonable
from ..io.handeye_inputs import read_device_set_transform, read_robot_poses, read_sensor_poses, robust_mean_pose
from ..io.itk_transform import write_slicer_frame_transform
from ..io.markups import read_markups
from ..io.provenance import file_sha256
from ..io.recording import read_recording
from ..io.registration_files import read_registration
from ..io.tool_files import read_tool
from ..names import ROBOT_CALIBRATION_JSON, ROBOT_TARGET_JSON, SENSOR_TO_FLANGE_H5, TRACKER_TO_BASE_H5
from ..settings import Settings

PARAMETERS = ("SensorToFlange rotation vector applied on the right (rad, 3), SensorToFlange translation (mm, 3), "
              "TrackerToBase rotation vector on the right (rad, 3), TrackerToBase translation (mm, 3), "
              "time_offset_s (s)")
EQUATION = "FlangeToBase @ SensorToFlange = TrackerToBase @ SensorToTracker; t_tracker = t_robot + time_offset_s"


def _stats(values: np.ndarray) -> dict[str, float]:
    return {"rms": float(np.sqrt(np.mean(values ** 2))), "median": float(np.median(values)),
            "p95": float(np.percentile(values, 95)), "max": float(np.max(values))}


def calibration_document(result: HandEyeResult, inputs: dict[str, Any], warnings: list[str],
                         robot_positioning: dict[str, Any] | None = None) -> dict[str, Any]:
    """``robot_calibration.json``'s content for a result (mm, degrees, seconds), with the robot's positioning
    error where the robot was driven (``robot-calibrate``)."""
    reasons: dict[str, int] = {}
    for frame in result.rejected:
        key = frame.reason.split(":")[-1].strip() if "times the expected noise" in frame.reason else frame.reason
        reasons[key] = reasons.get(key, 0) + 1
    return {
        "SensorToFlange": result.sensor_to_flange.tolist(),
        "TrackerToBase": result.tracker_to_base.tolist(),
        "time_offset_s": result.time_offset_s,
        "equation": EQUATION,
        "time_offset": {"cross_correlation_s": result.xcorr_offset_s, "correlation": result.correlation,
                        "std_s": result.time_offset_std_s},
        "residuals": {"rotation_deg": _stats(result.rotation_residual_deg),
                      "translation_mm": _stats(result.translation_residual_mm),
                      "noise_rotation_deg": result.noise_rotation_deg, "noise_position_mm": result.noise_position_mm},
        "frames": {"used": len(result.used), "rejected": len(result.rejected), "still": result.still,
                   "dwells": result.dwells, "rejected_by_reason": reasons,
                   "rejected_frames": [{"index": f.index, "time_s": f.time_s, "reason": f.reason}
                                       for f in result.rejected]},
        "motion": {"rotation_range_deg": result.rotation_range_deg, "second_axis_rms_deg": result.second_axis_deg,
                   "mean_flange_rotation": result.mean_flange_rotation.tolist()},
        "uncertainty": {
            "tool_tip_mm": result.tool_tip_mm.tolist(), "tool_tip_rms_mm": result.tool_tip_rms_mm,
            "tool_tip_covariance_mm2": result.tool_tip_covariance_mm2.tolist(),
            "tracker_point_mm": result.tracker_point_mm.tolist(), "tracker_point_rms_mm": result.tracker_point_rms_mm,
            "tracker_point_covariance_mm2": result.tracker_point_covariance_mm2.tolist(),
            "note": "predicted from the residuals (Gauss-Newton covariance): the tool point's place in the Flange "
                    "frame, the tracker point's in the Base frame",
            "parameter_covariance": result.covariance.tolist(),
            "parameters": PARAMETERS},
        "robot_positioning": robot_positioning,
        "inputs": inputs,
        "warnings": warnings,
    }


def write_calibration(out: Path, result: HandEyeResult, inputs: dict[str, Any], warnings: list[str],
                      robot_positioning: dict[str, Any] | None = None) -> dict:
    """Write ``OUT/robot_calibration.json``, ``SensorToFlange.h5`` and ``TrackerToBase.h5`` together or not at all
    (each to a temporary beside it, all renamed at the end); returns the document."""
    document = calibration_document(result, inputs, warnings, robot_positioning)
    with atomic_path(out / SENSOR_TO_FLANGE_H5) as x_tmp, atomic_path(out / TRACKER_TO_BASE_H5) as y_tmp, \
            atomic_path(out / ROBOT_CALIBRATION_JSON) as json_tmp:
        write_slicer_frame_transform(x_tmp, result.sensor_to_flange)
        write_slicer_frame_transform(y_tmp, result.tracker_to_base)
        json_tmp.write_text(json.dumps(to_jsonable(document), indent=2) + "\n", encoding="utf-8")
    return document


def calibrate_from_recordings(robot_poses: str | os.PathLike[str], tracker: str | os.PathLike[str], out: Path,
                              settings: Settings, sensor: str | int | None = None
                              ) -> tuple[HandEyeResult, dict[str, Any]]:
    """``emreg handeye``: ``SensorToFlange`` and ``TrackerToBase`` from a robot's log (``FlangeToBase``: TUM or a
    PLUS sequence) and the flange sensor's recording (PLUS sequence or EMReg CSV; ``sensor``: its transform name or
    port, default ``[handeye] sensor``), written into ``out`` (an existing folder, :func:`write_calibration`).
    Returns the result and the document written (its ``warnings``: what the readers noticed)."""
    handeye = settings.handeye
    robot = read_robot_poses(robot_poses, handeye.flange_transform)
    recording = read_sensor_poses(tracker, sensor if sensor is not None else handeye.sensor)
    result = calibrate_hand_eye(robot.time_s, robot.poses, recording.time_s, recording.poses, handeye)
    inputs = {"robot_poses": {"path": str(robot_poses), "sha256": file_sha256(robot_poses),
                              "transform": robot.name, "samples": len(robot.time_s)},
              "tracker": {"path": str(tracker), "sha256": file_sha256(tracker), "sensor": recording.name,
                          "samples": len(recording.time_s)},
              "settings": settings.source or None, "emreg_version": __version__}
    return result, write_calibration(out, result, inputs, robot.warnings + recording.warnings)


def describe_calibration(result: HandEyeResult, document: dict[str, Any], out: Path) -> str:
    """One line on a calibration written into ``out``: frames, clock offset, residuals, predicted error."""
    return (f"SensorToFlange and TrackerToBase from {len(result.used)} frames ({len(result.rejected)} left out); "
            f"time offset {result.time_offset_s:.4f} s; residual RMS {document['residuals']['rotation_deg']['rms']:.3f}"
            f" deg, {document['residuals']['translation_mm']['rms']:.3f} mm; predicted tool-point error "
            f"{result.tool_tip_rms_mm:.3f} mm RMS -> {out / ROBOT_CALIBRATION_JSON}")


def plan_points(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Entry and Target (LPS mm) of a plan: points labelled Entry and Target, else a Line's two points."""
    labels, positions = read_markups(path)
    named = {label.strip().lower(): k for k, label in enumerate(labels)}
    if "entry" in named and "target" in named:
        return positions[named["entry"]], positions[named["target"]]
    if len(positions) == 2:
        return positions[0], positions[1]
    raise EMRegError(f"{path}: a plan is a markups Line (Entry, Target) or points labelled Entry and Target; "
                     f"this file holds {len(positions)} point(s) ({', '.join(labels) or 'none'})")


def needle_guide(path: str | os.PathLike[str]) -> tuple[np.ndarray, float]:
    """``NeedleGuideToSensor`` (4x4, mm) and its calibration's RMS error (mm, 0 when the file gives none)."""
    if Path(path).suffix.lower() == ".xml":
        matrix = read_device_set_transform(path, "NeedleGuide", "Sensor")
        return check_tip_to_probe(matrix, f'{path} (From="NeedleGuide" To="Sensor")'), 0.0
    tool = read_tool(str(path))
    return tool.tip_to_probe, float(tool.rms_mm or 0.0)


def read_robot_calibration(path: str | os.PathLike[str]) -> dict[str, Any]:
    """``robot_calibration.json``: X, Y (checked rigid), the parameter covariance, the flange's mean rotation."""
    document = read_json(path, "robot calibration JSON")
    try:
        out = {key: np.asarray(document[key], dtype=float) for key in ("SensorToFlange", "TrackerToBase")}
        for key, matrix in out.items():
            check_rigid(matrix, f"{path}: {key}")
        covariance = document.get("uncertainty", {}).get("parameter_covariance")
        out["covariance"] = np.asarray(covariance, dtype=float) if covariance is not None else np.zeros((13, 13))
        positioning = document.get("robot_positioning") or {}
        out["positioning"] = np.asarray(positioning["errors_flange"], dtype=float).reshape(-1, 6) \
            if positioning else None
        rotation = document.get("motion", {}).get("mean_flange_rotation")
        out["preferred"] = np.asarray(rotation, dtype=float) if rotation is not None else None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise EMRegError(f"{path}: not a robot calibration (robot_calibration.json; {exc!s:.80})") from None
    return out


#: A live reference is the robust mean of this many samples, taken within ``LIVE_TIMEOUT_S``.
LIVE_SAMPLES = 40
LIVE_TIMEOUT_S = 10.0


def _reference_live(url: str, port: int) -> np.ndarray:
    """``LIVE_SAMPLES`` valid poses (N, 4, 4, mm) of the reference sensor from a live source (a device URL)."""
    poses: list[np.ndarray] = []
    enough = threading.Event()

    def take(sample) -> None:
        if sample.sensor == port and sample.valid:
            poses.append(sample.transform())
            if len(poses) >= LIVE_SAMPLES:
                enough.set()

    with open_source(url, reference_sensor=port, fast=True) as source:
        source.start(take)
        end = time.monotonic() + LIVE_TIMEOUT_S
        while not enough.wait(0.05) and not source.finished.is_set() and time.monotonic() < end:
            pass
    if len(poses) < 5:
        raise EMRegError(f"{url}: {len(poses)} valid samples of the reference sensor (port {port}) within "
                         f"{LIVE_TIMEOUT_S:g} s; is it connected and in the field (--reference-sensor)?")
    return np.asarray(poses[:LIVE_SAMPLES])


def reference_now(reference: str | os.PathLike[str], port: int, settings: Settings) -> np.ndarray:
    """``ReferenceToTracker`` now (4x4, mm) of the reference sensor on ``port``: the robust mean of a recording's
    samples, or of a live source's (a device URL: ``trakstar:``, ``aurora:``, ``igtl:``, ``replay:``)."""
    if str(reference).split(":", 1)[0] in SCHEMES and ":" in str(reference):
        return robust_mean_pose(_reference_live(str(reference), port))
    recording = read_recording(reference, settings, reference_port=port)
    rows = (recording.sensor == port) & np.all(np.isfinite(recording.rotation), axis=(1, 2))
    if not np.any(rows):
        raise EMRegError(f"{reference}: no full pose of the reference sensor (port {port}); ports present: "
                         f"{recording.sensors} (--reference-sensor)")
    return robust_mean_pose(recording.transforms()[rows])


def target_from_files(registration: str | os.PathLike[str], robot_calibration: str | os.PathLike[str],
                      reference: str | os.PathLike[str], plan: str | os.PathLike[str], tool: str | os.PathLike[str],
                      out: Path, settings: Settings, reference_sensor: int | None = None
                      ) -> tuple[RobotTarget, dict[str, Any]]:
    """``emreg robot-target``: the flange pose that puts the needle guide (``tool``) on the plan (``plan``: Entry ->
    Target in the CT) through the registration (``registration.json``), the hand-eye calibration
    (``robot_calibration.json``) and the reference sensor now (``reference``: a recording or a live URL; its port
    ``reference_sensor``, default ``[sensors] reference``), written as ``out/robot_target.json`` (``out``: an
    existing folder). Returns the answer and the document written."""
    recorded = read_registration(registration, settings.registration.max_fre_mm)
    calibration = read_robot_calibration(robot_calibration)
    reference_to_tracker = reference_now(reference, reference_sensor or settings.sensors.reference, settings)
    entry, target = plan_points(plan)
    guide_to_sensor, tool_rms = needle_guide(tool)
    registration_ms = (float(np.trace(recorded.error.covariance.at(target[None])[0]))
                       if recorded.error is not None else recorded.fre_mm ** 2)
    robot = settings.robot
    answer = robot_target(entry, target, recorded.reference_to_image, reference_to_tracker,
                          calibration["TrackerToBase"], calibration["SensorToFlange"], guide_to_sensor,
                          calibration["covariance"], registration_ms, tool_rms, robot.standoff_mm,
                          calibration["preferred"], robot.max_tracker_distance_mm, robot.reach_mm,
                          robot.model, (robot.end_effector_mm, robot.end_effector_rpy_deg), calibration["positioning"],
                          (robot.positioning_mm, robot.positioning_deg))
    document = {"FlangeToBase": answer.flange_to_base.tolist(),
                "NeedleGuideToBase": answer.needle_guide_to_base.tolist(),
                "entry_base_mm": answer.entry_base_mm.tolist(), "target_base_mm": answer.target_base_mm.tolist(),
                "depth_mm": answer.depth_mm, "standoff_mm": robot.standoff_mm, "roll_deg": answer.roll_deg,
                "predicted_error_mm": answer.predicted_error_mm,
                "robot_model": robot.model,
                "joints_rad": None if answer.joints_rad is None else answer.joints_rad.tolist(),
                "joint_limit_margin": answer.joint_limit_margin,
                "ReferenceToTracker": reference_to_tracker.tolist(),
                # what emreg robot-go needs to verify the guide with the tracker and follow the reference
                "SensorToFlange": calibration["SensorToFlange"].tolist(),
                "TrackerToBase": calibration["TrackerToBase"].tolist(),
                "NeedleGuideToSensor": guide_to_sensor.tolist(),
                "ReferenceToImage": recorded.reference_to_image.tolist(),
                "entry_image_mm": np.asarray(entry, dtype=float).tolist(),
                "target_image_mm": np.asarray(target, dtype=float).tolist(),
                "inputs": {"registration": str(registration), "robot_calibration": str(robot_calibration),
                           "reference": str(reference), "plan": str(plan), "tool": str(tool)},
                "note": "FlangeToBase puts the guide's exit on Entry (standoff_mm before it) with its +z along "
                        "Entry -> Target; predicted_error_mm is the RMS error at the target"}
    atomic_write_json(out / ROBOT_TARGET_JSON, document)
    return answer, document
