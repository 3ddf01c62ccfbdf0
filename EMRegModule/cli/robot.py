"""The robot commands (issue 39): ``emreg handeye`` and ``emreg robot-target``.

``emreg handeye --robot-poses ROBOT --tracker TRACKER [--sensor NAME|PORT] [--settings case.toml] --out OUT``
writes ``OUT/robot_calibration.json`` (``SensorToFlange``, ``TrackerToBase``: 4x4 mm, with
``FlangeToBase @ SensorToFlange = TrackerToBase @ SensorToTracker``; ``time_offset_s`` with
``t_tracker = t_robot + time_offset_s``; residuals, frames used and rejected, predicted uncertainty) and the two
transforms for 3D Slicer, ``OUT/SensorToFlange.h5`` and ``OUT/TrackerToBase.h5``.

``emreg robot-target --registration R --robot-calibration C --reference REF --plan PLAN --tool GUIDE --out OUT``
writes ``OUT/robot_target.json``: the ``FlangeToBase`` (4x4 mm) that puts the needle guide's exit on Entry with
its +z along Entry -> Target, and the predicted error at the target.

Exit 2 for bad input, 3 when the data do not allow a safe answer; nothing is written then.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .args import AddCommand, out_folder, settings_of, warn

if TYPE_CHECKING:
    from ..core.handeye import HandEyeResult

ROBOT_CALIBRATION_JSON = "robot_calibration.json"
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
    from ..io.atomic import atomic_path, to_jsonable
    from ..io.itk_transform import write_slicer_frame_transform

    document = calibration_document(result, inputs, warnings, robot_positioning)
    with atomic_path(out / "SensorToFlange.h5") as x_tmp, atomic_path(out / "TrackerToBase.h5") as y_tmp, \
            atomic_path(out / ROBOT_CALIBRATION_JSON) as json_tmp:
        write_slicer_frame_transform(x_tmp, result.sensor_to_flange)
        write_slicer_frame_transform(y_tmp, result.tracker_to_base)
        json_tmp.write_text(json.dumps(to_jsonable(document), indent=2) + "\n", encoding="utf-8")
    return document


def cmd_handeye(args: argparse.Namespace) -> int:
    from .. import __version__
    from ..core.handeye import calibrate_hand_eye
    from ..io.handeye_inputs import read_robot_poses, read_sensor_poses
    from ..io.provenance import file_sha256

    settings = settings_of(args)
    out = Path(out_folder(args.out) or args.out)
    handeye = settings.handeye
    sensor = args.sensor if args.sensor is not None else handeye.sensor
    robot = read_robot_poses(args.robot_poses, handeye.flange_transform)
    tracker = read_sensor_poses(args.tracker, sensor)
    result = calibrate_hand_eye(robot.time_s, robot.poses, tracker.time_s, tracker.poses, handeye)
    inputs = {"robot_poses": {"path": str(args.robot_poses), "sha256": file_sha256(args.robot_poses),
                              "transform": robot.name, "samples": len(robot.time_s)},
              "tracker": {"path": str(args.tracker), "sha256": file_sha256(args.tracker), "sensor": tracker.name,
                          "samples": len(tracker.time_s)},
              "settings": settings.source or None, "emreg_version": __version__}
    warnings = robot.warnings + tracker.warnings
    document = write_calibration(out, result, inputs, warnings)
    warn("handeye", warnings)
    print(f"SensorToFlange and TrackerToBase from {len(result.used)} frames ({len(result.rejected)} left out); "
          f"time offset {result.time_offset_s:.4f} s; residual RMS {document['residuals']['rotation_deg']['rms']:.3f}"
          f" deg, {document['residuals']['translation_mm']['rms']:.3f} mm; predicted tool-point error "
          f"{result.tool_tip_rms_mm:.3f} mm RMS -> {Path(out) / ROBOT_CALIBRATION_JSON}")
    return 0


def _plan_points(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Entry and Target (LPS mm) of a plan: points labelled Entry and Target, else a Line's two points."""
    from ..errors import EMRegError
    from ..io.markups import read_markups

    labels, positions = read_markups(path)
    named = {label.strip().lower(): k for k, label in enumerate(labels)}
    if "entry" in named and "target" in named:
        return positions[named["entry"]], positions[named["target"]]
    if len(positions) == 2:
        return positions[0], positions[1]
    raise EMRegError(f"{path}: a plan is a markups Line (Entry, Target) or points labelled Entry and Target; "
                     f"this file holds {len(positions)} point(s) ({', '.join(labels) or 'none'})")


def _needle_guide(path: str) -> tuple[np.ndarray, float]:
    """``NeedleGuideToSensor`` (4x4, mm) and its calibration's RMS error (mm, 0 when the file gives none)."""
    from ..core.tool import check_tip_to_probe, read_tool
    from ..io.handeye_inputs import read_device_set_transform

    if Path(path).suffix.lower() == ".xml":
        matrix = read_device_set_transform(path, "NeedleGuide", "Sensor")
        return check_tip_to_probe(matrix, f'{path} (From="NeedleGuide" To="Sensor")'), 0.0
    tool = read_tool(path)
    return tool.tip_to_probe, float(tool.rms_mm or 0.0)


def _robot_calibration(path: str) -> dict[str, Any]:
    """``robot_calibration.json``: X, Y (checked rigid), the parameter covariance, the flange's mean rotation."""
    from ..core.transforms import check_rigid
    from ..errors import EMRegError
    from ..io.atomic import read_json

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
    import threading
    import time

    from ..devices.sources import open_source
    from ..errors import EMRegError

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


def _reference_now(args: argparse.Namespace, settings) -> np.ndarray:
    """``ReferenceToTracker`` now: the robust mean of a recording's reference samples, or of a live source's
    (a device URL: ``trakstar:``, ``aurora:``, ``igtl:``, ``replay:``)."""
    from ..devices.device_url import SCHEMES
    from ..errors import EMRegError
    from ..io.handeye_inputs import robust_mean_pose
    from ..io.recording import read_recording

    port = args.reference_sensor or settings.sensors.reference
    if str(args.reference).split(":", 1)[0] in SCHEMES and ":" in str(args.reference):
        return robust_mean_pose(_reference_live(str(args.reference), port))
    recording = read_recording(args.reference, settings, reference_port=port)
    rows = (recording.sensor == port) & np.all(np.isfinite(recording.rotation), axis=(1, 2))
    if not np.any(rows):
        raise EMRegError(f"{args.reference}: no full pose of the reference sensor (port {port}); ports present: "
                         f"{recording.sensors} (--reference-sensor)")
    return robust_mean_pose(recording.transforms()[rows])


def cmd_robot_target(args: argparse.Namespace) -> int:
    from ..core.registration import read_registration
    from ..core.robot_target import robot_target
    from ..io.atomic import atomic_write_json

    settings = settings_of(args)
    out = out_folder(args.out)
    registration = read_registration(args.registration, settings.registration.max_fre_mm)
    calibration = _robot_calibration(args.robot_calibration)
    reference_to_tracker = _reference_now(args, settings)
    entry, target = _plan_points(args.plan)
    guide_to_sensor, tool_rms = _needle_guide(args.tool)
    registration_ms = (float(np.trace(registration.error.covariance.at(target[None])[0]))
                       if registration.error is not None else registration.fre_mm ** 2)
    robot = settings.robot
    answer = robot_target(entry, target, registration.reference_to_image, reference_to_tracker,
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
                "ReferenceToImage": registration.reference_to_image.tolist(),
                "entry_image_mm": np.asarray(entry, dtype=float).tolist(),
                "target_image_mm": np.asarray(target, dtype=float).tolist(),
                "inputs": {"registration": str(args.registration), "robot_calibration": str(args.robot_calibration),
                           "reference": str(args.reference), "plan": str(args.plan), "tool": str(args.tool)},
                "note": "FlangeToBase puts the guide's exit on Entry (standoff_mm before it) with its +z along "
                        "Entry -> Target; predicted_error_mm is the RMS error at the target"}
    atomic_write_json(Path(out) / "robot_target.json", document)
    print(f"FlangeToBase for the plan: guide exit on Entry, {answer.depth_mm:.1f} mm to the target; predicted error "
          f"at the target {answer.predicted_error_mm['total']:.2f} mm RMS -> {Path(out) / 'robot_target.json'}")
    return 0


def add_parsers(add: AddCommand) -> None:
    """The subcommands of this module (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    p = add("handeye", cmd_handeye, "hand-eye (SensorToFlange) and robot-world (TrackerToBase) calibration with the "
            "EM tracker, from a robot's log and a tracker recording on two clocks")
    p.add_argument("--robot-poses", required=True, metavar="ROBOT",
                   help="the flange's poses in the robot base frame (FlangeToBase): a TUM trajectory file "
                        "(timestamp tx ty tz qx qy qz qw; s, m) or a PLUS sequence file ([handeye] flange_transform)")
    p.add_argument("--tracker", required=True, metavar="TRACKER",
                   help="the flange sensor's recording: a PLUS sequence file or EMReg tracking CSV")
    p.add_argument("--sensor", default=None, metavar="NAME|PORT",
                   help="the flange's sensor when TRACKER holds several: a transform name or a port")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_calibration.json, .h5)")
    t = add("robot-target", cmd_robot_target, "the flange pose (FlangeToBase) that puts the needle guide on a "
            "trajectory planned in the CT")
    t.add_argument("--registration", required=True, metavar="R", help="registration.json (ReferenceToImage)")
    t.add_argument("--robot-calibration", required=True, metavar="C", help="robot_calibration.json (emreg handeye)")
    t.add_argument("--reference", required=True, metavar="REF",
                   help="the reference sensor now: a recording or a live source URL (trakstar:, aurora:, igtl:, "
                        "replay:), its samples averaged robustly")
    t.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                   help="the reference sensor's port (default [sensors] reference)")
    t.add_argument("--plan", required=True, metavar="PLAN",
                   help="Slicer markups: a Line Entry -> Target, or points labelled Entry and Target")
    t.add_argument("--tool", required=True, metavar="GUIDE",
                   help="the needle guide on the flange sensor: a PLUS device set (From=NeedleGuide To=Sensor), an "
                        "ITK/Slicer transform or tool_calibration.json")
    t.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_target.json)")
