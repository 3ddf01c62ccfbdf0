"""Moving a robot (issue 39, section 3), what ``emreg robot-calibrate`` and ``emreg robot-go`` and the 3D Slicer
module's robot panel call: :func:`robot_calibrate` and :func:`robot_go`.

``emreg robot-calibrate --robot URL --tracker URL --out OUT [--sensor PORT] [--execute]`` plans its own
calibration poses around where the flange stands (:func:`EMRegModule.core.robot_motion.plan_calibration_poses`: turns
about axes spread over a hemisphere, kept where the sensor stays in the tracker's volume), moves through them
dwelling at each while it records the robot's flange pose and the tracker's flange sensor, returns to the start,
and solves them with ``emreg handeye``'s solver: ``OUT/robot_calibration.json`` and the two ``.h5``, plus the
recordings (``OUT/robot_poses.tum``, ``OUT/flange_sensor.tum``: the flange's and the sensor's poses, s and m).

``emreg robot-go --robot URL --tracker URL --target OUT/robot_target.json [--execute]`` moves the needle guide to
the plan: first to a point ``approach_mm`` back along the planned axis, then along it; then it measures where the
guide is with the flange sensor and the live reference, and corrects the residual until it is within
``[robot] tolerance_mm`` / ``tolerance_deg`` or gives up (exit 3) after ``max_corrections``. The guide's pose
streams over OpenIGTLink as ``NeedleGuideToRAS`` (``--igtl-port``) while it runs. ``--out`` writes
``robot_go.json`` (every measurement, the final error: :func:`robot_go`).

Without ``--execute`` (``execute=False``) nothing moves: both say the planned motion. Every move is limited in
velocity and acceleration (``[robot]``) and stops when the tracker's flange or reference sensor is INVALID or stale, the
reference jumps, or the sensor leaves the tracker's volume (:mod:`EMRegModule.devices.robot.guard`): exit 3 with
the reason.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..core.frames import LPS_TO_RAS
from ..core.handeye import calibrate_hand_eye, motion_spread
from ..core.robot_motion import (
    approach_pose,
    check_step,
    correct_flange,
    guide_error,
    keep_in_volume,
    plan_calibration_poses,
    positioning_errors,
)
from ..core.transforms import apply_transform, check_rigid, invert_rigid, rotation_angle_deg
from ..devices.igtl_server import IGTLServer
from ..devices.robot.driver import MotionLimits
from ..devices.robot.guard import FlangeRecording, TrackerWatch, guarded_move, wait_for_tracker
from ..devices.robot.url import open_robot
from ..devices.sources import open_source
from ..errors import EMRegError, NoSafeAnswerError
from ..io.atomic import atomic_write_json, read_json
from ..io.tum import write_tum
from ..names import DEFAULT_IGTL_PORT, GUIDE_NODE_NAME, ROBOT_CALIBRATION_JSON, ROBOT_GO_JSON
from ..settings import Settings
from .robot import write_calibration

#: Where the planned motion and the measurements are said (the command line prints them).
Say = Callable[[str], None]


def _limits(robot_settings) -> MotionLimits:
    return MotionLimits(robot_settings.max_velocity_mm_s, robot_settings.max_acceleration_mm_s2,
                        robot_settings.max_rotation_deg_s, robot_settings.max_rotation_acceleration_deg_s2)


def _describe_move(name: str, start: np.ndarray, pose: np.ndarray) -> str:
    angle = float(rotation_angle_deg(start[:3, :3], pose[:3, :3]))
    position = ", ".join(f"{v:.1f}" for v in pose[:3, 3])
    return (f"  {name}: flange at ({position}) mm in the base frame, {np.linalg.norm(pose[:3, 3] - start[:3, 3]):.1f}"
            f" mm and {angle:.1f} deg from where it stands")


class _RobotLog:
    """Polls the robot's flange pose (``FlangeToBase``, mm) at ``rate_hz`` on its own thread (monotonic s)."""

    def __init__(self, robot, rate_hz: float = 100.0) -> None:
        self.robot = robot
        self.period_s = 1.0 / rate_hz
        self.time_s: list[float] = []
        self.poses: list[np.ndarray] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="robot-log", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            pose = self.robot.flange_to_base()
            self.time_s.append(time.monotonic())
            self.poses.append(pose)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


def _dwell(watch, seconds: float) -> None:
    """Stay still for ``seconds`` while the tracker vouches for what it sees (exit 3 the moment it does not)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        problem = watch.check()
        if problem:
            raise NoSafeAnswerError(f"robot: stopped while still: {problem}")
        time.sleep(0.01)


def _open(robot_url: str, tracker_url: str, flange_port: int, reference_port: int | None, settings: Settings):
    """The robot, the tracker's source and its watch, started; the caller closes them (:func:`_close`)."""
    robot = open_robot(robot_url)
    source = None
    try:
        source = open_source(tracker_url, reference_sensor=reference_port or settings.sensors.reference,
                             probe_sensor=flange_port)
        watch = TrackerWatch(flange_port, reference_port, settings.robot.max_tracker_distance_mm,
                             settings.robot.stale_s, settings.navigation)
        source.start(watch.on_sample)
        wait_for_tracker(watch)
    except BaseException:
        if source is not None:
            source.stop()
        robot.close()
        raise
    return robot, source, watch


def _close(robot, source) -> None:
    robot.close()
    source.stop()


def plan_calibration(start: np.ndarray, sensor_tracker_mm: np.ndarray, settings) -> np.ndarray:
    """The calibration poses for a flange at ``start`` whose sensor is at ``sensor_tracker_mm`` (Tracker, mm);
    :class:`NoSafeAnswerError` when too few keep the sensor in the tracker's volume or they would not determine
    the calibration (the rotations' spread below ``[handeye]``'s minima)."""
    robot = settings.robot
    poses = plan_calibration_poses(start, robot.calibration_poses, robot.calibration_angle_deg,
                                   robot.calibration_translation_mm)
    keep = keep_in_volume(start, poses, sensor_tracker_mm, robot.max_tracker_distance_mm,
                          sensor_radius_mm=robot.sensor_radius_mm)
    poses = poses[keep]
    spread, second = motion_spread(np.concatenate([start[None], poses])) if len(poses) else (0.0, 0.0)
    if len(poses) < 4 or spread < settings.handeye.min_rotation_deg or second < settings.handeye.min_second_axis_deg:
        raise NoSafeAnswerError(
            f"robot-calibrate: {len(poses)} of {robot.calibration_poses} planned poses keep the sensor (now "
            f"{np.linalg.norm(sensor_tracker_mm):.0f} mm from the field generator) within the tracker's volume "
            f"({robot.max_tracker_distance_mm:g} mm), rotating {spread:.1f} deg ({second:.1f} deg about a second "
            "axis): too few to calibrate; move the flange nearer the field generator")
    return poses


def robot_calibrate(robot_url: str, tracker_url: str, out: Path, settings: Settings, sensor: int | None = None,
                    execute: bool = False, say: Say = print) -> dict[str, Any] | None:
    """``emreg robot-calibrate``: plan calibration poses around where the flange stands, say them and, with
    ``execute`` only, move through them recording, then solve and write ``out/robot_calibration.json`` (with the
    ``.h5`` and the recordings; ``out``: an existing folder). ``sensor``: the flange sensor's port (default
    ``[robot] flange_sensor``). Returns the document written, None for a dry run (nothing moved)."""
    robot_settings = settings.robot
    flange_port = sensor or robot_settings.flange_sensor
    limits = _limits(robot_settings)
    robot, source, watch = _open(robot_url, tracker_url, flange_port, None, settings)
    try:
        start = robot.flange_to_base()
        sensor_now = watch.mean_poses(0.3)[flange_port]
        poses = plan_calibration(start, sensor_now[:3, 3], settings)
        say(f"robot-calibrate: {len(poses)} poses around the flange's pose, dwelling {robot_settings.dwell_s:g} s at "
              f"each (limits {limits.velocity_mm_s:g} mm/s, {limits.rotation_deg_s:g} deg/s), then back:")
        for k, pose in enumerate(poses):
            say(_describe_move(f"pose {k + 1}", start, pose))
        if not execute:
            say("robot-calibrate: dry run, nothing moved; add --execute to move the robot through these poses")
            return None
        watch.recording = FlangeRecording()
        log = _RobotLog(robot)
        reached = []  # where the robot put the flange at each pose, measured as robot-go measures (after measure_s)
        try:
            _dwell(watch, robot_settings.dwell_s)
            for pose in [*poses, start]:
                guarded_move(robot, pose, limits, watch)
                _dwell(watch, robot_settings.dwell_s + robot_settings.measure_s)
                reached.append(robot.flange_to_base())
        finally:
            log.stop()
        recording, watch.recording = watch.recording, None
    finally:
        _close(robot, source)
    robot_time, robot_poses = np.asarray(log.time_s), np.asarray(log.poses)
    tracker_time, tracker_poses = np.asarray(recording.time_s), np.asarray(recording.poses)
    handeye = replace(settings.handeye, timing_jitter_s=max(settings.handeye.timing_jitter_s,
                                                             robot_settings.motion_jitter_s))
    result = calibrate_hand_eye(robot_time, robot_poses, tracker_time, tracker_poses, handeye)
    write_tum(out / "robot_poses.tum", robot_time, robot_poses, "FlangeToBase, emreg robot-calibrate")
    write_tum(out / "flange_sensor.tum", tracker_time, tracker_poses,
              f"SensorToTracker of port {flange_port}, emreg robot-calibrate")
    inputs = {"robot": str(robot_url), "tracker": str(tracker_url), "sensor": flange_port,
              "robot_poses": {"path": "robot_poses.tum", "samples": len(robot_time)},
              "tracker_recording": {"path": "flange_sensor.tum", "samples": len(tracker_time)},
              "planned_poses": len(poses), "settings": settings.source or None, "emreg_version": __version__}
    misses = positioning_errors(np.concatenate([poses, start[None]]), np.asarray(reached))
    document = write_calibration(out, result, inputs, [], {
        "errors_flange": misses.tolist(), "position_rms_mm": float(np.sqrt(np.mean(np.sum(misses[:, 3:] ** 2, 1)))),
        "rotation_rms_deg": float(np.degrees(np.sqrt(np.mean(np.sum(misses[:, :3] ** 2, 1))))),
        "note": "per pose, the flange pose the robot reported after the dwell in the commanded pose's frame: "
                "rotation vector (rad), translation (mm)"})
    say(f"robot-calibrate: SensorToFlange and TrackerToBase from {len(result.used)} frames over {len(poses)} poses; "
          f"residual RMS {document['residuals']['rotation_deg']['rms']:.3f} deg, "
          f"{document['residuals']['translation_mm']['rms']:.3f} mm; predicted tool-point error "
          f"{result.tool_tip_rms_mm:.3f} mm RMS -> {out / ROBOT_CALIBRATION_JSON}")
    return document


def read_target(path: str | Path) -> dict[str, np.ndarray]:
    """What ``emreg robot-go`` needs of ``robot_target.json`` (4x4 mm transforms, points mm); exit 2 when absent."""
    document = read_json(path, "robot target JSON")
    keys = ("FlangeToBase", "NeedleGuideToBase", "SensorToFlange", "TrackerToBase", "NeedleGuideToSensor",
            "ReferenceToTracker", "ReferenceToImage")
    try:
        out = {key: np.asarray(document[key], dtype=float) for key in keys}
        for key in keys:
            check_rigid(out[key], f"{path}: {key}")
        out["entry"] = np.asarray(document["entry_image_mm"], dtype=float).reshape(3)
        out["target"] = np.asarray(document["target_image_mm"], dtype=float).reshape(3)
        out["standoff_mm"] = float(document.get("standoff_mm", 0.0))
        out["predicted_error_mm"] = document.get("predicted_error_mm", {})
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise EMRegError(f"{path}: not a robot target for robot-go (robot_target.json of this version of emreg "
                         f"robot-target; {exc!s:.80})") from None
    return out


class _Plan:
    """The plan where the patient is now: the guide wanted in the Tracker frame, its flange pose, Entry and Target
    in the Tracker frame; the plan follows the reference from where it stood at targeting (``ReferenceToTracker``
    of ``robot_target.json``) to where it stands now."""

    def __init__(self, target: dict[str, Any], reference_now: np.ndarray) -> None:
        self.guide_to_flange = target["SensorToFlange"] @ target["NeedleGuideToSensor"]
        base_to_tracker = invert_rigid(target["TrackerToBase"])
        follow = reference_now @ invert_rigid(target["ReferenceToTracker"])
        self.guide_tracker = follow @ base_to_tracker @ target["NeedleGuideToBase"]
        self.flange = target["TrackerToBase"] @ self.guide_tracker @ invert_rigid(self.guide_to_flange)
        image_to_tracker = reference_now @ invert_rigid(target["ReferenceToImage"])
        self.entry_tracker, self.target_tracker = apply_transform(image_to_tracker,
                                                                  np.vstack([target["entry"], target["target"]]))


class _GuideStream:
    """Sends the guide's pose as ``NeedleGuideToRAS`` over OpenIGTLink every ``period_s`` from the watch's latest
    samples (the flange sensor through the guide, the live reference, the registration)."""

    def __init__(self, port: int, watch, target: dict[str, Any], period_s: float = 0.05) -> None:
        self.server = IGTLServer(port=port)
        self.watch = watch
        self.target = target
        self.period_s = period_s
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="guide-stream", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            flange, reference = self.watch.latest()
            if flange is None or reference is None:
                continue
            guide_to_image = (self.target["ReferenceToImage"] @ invert_rigid(reference.transform())
                              @ flange.transform() @ self.target["NeedleGuideToSensor"])
            status = "OK" if flange.valid and reference.valid else (
                flange.transform_status if not flange.valid else reference.transform_status)
            self.server.send_transform(GUIDE_NODE_NAME, LPS_TO_RAS @ guide_to_image, time.time(), status)
            self.sent += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.server.close()


def _converge(robot, watch, target: dict[str, Any], settings: Settings, limits: MotionLimits, flange_port: int,
              reference_port: int, say: Say) -> list[dict[str, Any]]:
    """Measure the guide and correct it until it is on the plan; the measurements (exit 3 when it gives up)."""

    robot_settings = settings.robot
    history = []
    for step in range(robot_settings.max_corrections + 1):
        _dwell(watch, robot_settings.dwell_s)
        means = watch.mean_poses(robot_settings.measure_s)
        plan = _Plan(target, means[reference_port])
        guide_seen = means[flange_port] @ target["NeedleGuideToSensor"]
        error = guide_error(guide_seen, plan.entry_tracker, plan.target_tracker, target["standoff_mm"])
        flange_now = robot.flange_to_base()
        history.append({"step": step, "exit_mm": error.exit_mm, "lateral_mm": error.lateral_mm,
                        "angle_deg": error.angle_deg, "tip_mm": error.tip_mm, "FlangeToBase": flange_now.tolist(),
                        "NeedleGuideToTracker": guide_seen.tolist()})
        say(f"robot-go: measured {'after the move' if step == 0 else f'after correction {step}'}: "
            f"{error.describe()}")
        if error.within(robot_settings.tolerance_mm, robot_settings.tolerance_deg):
            return history
        if step == robot_settings.max_corrections:
            break
        tracker_to_base = target["TrackerToBase"]
        wanted = correct_flange(flange_now, tracker_to_base @ guide_seen, tracker_to_base @ plan.guide_tracker)
        check_step(flange_now, wanted, robot_settings.max_correction_mm, robot_settings.max_correction_deg)
        guarded_move(robot, wanted, limits, watch)
    raise NoSafeAnswerError(f"robot-go: gave up after {robot_settings.max_corrections} corrections: the guide's "
                            f"{error.describe()} (tolerance {robot_settings.tolerance_mm:g} mm, "
                            f"{robot_settings.tolerance_deg:g} deg, [robot] tolerance_mm / _deg); it is not on the "
                            "plan")


def robot_go(robot_url: str, tracker_url: str, target_path: str | Path, settings: Settings,
             sensor: int | None = None, reference_sensor: int | None = None, igtl_port: int | None = DEFAULT_IGTL_PORT,
             out: Path | None = None, execute: bool = False, say: Say = print) -> dict[str, Any] | None:
    """``emreg robot-go``: say the motion that puts the needle guide on the plan of ``robot_target.json``
    (``target_path``) where the reference stands now and, with ``execute`` only, move there, measure the guide with
    the flange sensor (port ``sensor``, default ``[robot] flange_sensor``) and the live reference
    (``reference_sensor``, default ``[sensors] reference``) and correct it until it is within tolerance
    (:class:`NoSafeAnswerError` when it gives up), streaming ``NeedleGuideToRAS`` on ``igtl_port`` (None: not).
    Returns the closed-loop result, also written as ``out/robot_go.json`` with ``out`` (an existing folder); None
    for a dry run (nothing moved)."""
    robot_settings = settings.robot
    flange_port = sensor or robot_settings.flange_sensor
    reference_port = reference_sensor or settings.sensors.reference
    target = read_target(target_path)
    limits = _limits(robot_settings)
    robot, source, watch = _open(robot_url, tracker_url, flange_port, reference_port, settings)
    stream = None
    try:
        means = watch.mean_poses(robot_settings.measure_s)
        plan = _Plan(target, means[reference_port])
        start = robot.flange_to_base()
        approach = approach_pose(plan.flange, plan.guide_to_flange, robot_settings.approach_mm)
        say(f"robot-go: the guide to the plan (limits {limits.velocity_mm_s:g} mm/s, {limits.rotation_deg_s:g} "
            "deg/s), following the reference:")
        say(_describe_move(f"approach, {robot_settings.approach_mm:g} mm back along the axis", start, approach))
        say(_describe_move("on the plan", start, plan.flange))
        if not execute:
            say("robot-go: dry run, nothing moved; add --execute to move the robot")
            return None
        if igtl_port is not None:
            stream = _GuideStream(igtl_port, watch, target)
        guarded_move(robot, approach, limits, watch)
        guarded_move(robot, plan.flange, limits, watch)
        history = _converge(robot, watch, target, settings, limits, flange_port, reference_port, say)
    finally:
        if stream is not None:
            stream.close()
        _close(robot, source)
    final = history[-1]
    result = {"on_plan": True, "corrections": len(history) - 1, "final": final, "measurements": history,
              "tolerance_mm": robot_settings.tolerance_mm, "tolerance_deg": robot_settings.tolerance_deg,
              "predicted_error_mm": target["predicted_error_mm"], "target": str(target_path),
              "note": "errors measured with the flange sensor through the guide against the plan, which follows the "
                      "live reference (exit: the guide's exit from Entry; tip: the needle tip at the planned depth "
                      "from Target; angle: the guide's +z against Entry -> Target)"}
    if out is not None:
        atomic_write_json(out / ROBOT_GO_JSON, result)
    say(f"robot-go: on the plan after {len(history) - 1} correction(s): exit {final['exit_mm']:.2f} mm, tip "
        f"{final['tip_mm']:.2f} mm, axis {final['angle_deg']:.2f} deg")
    return result
