"""The robot steps that move a robot (issue 39, section 3): calibration poses it plans and moves through itself, and
the needle guide brought onto the plan in closed loop with the EM tracker.

:func:`robot_calibrate` plans calibration poses around where the flange stands
(:func:`EMRegModule.core.robot_motion.plan_calibration_poses`: turns about axes spread over a hemisphere, kept where
the sensor stays in the tracker's volume), moves through them dwelling at each while it records the robot's flange
pose and the tracker's flange sensor, returns to the start, and solves them with ``emreg handeye``'s solver:
``OUT/robot_calibration.json`` and the two ``.h5``, plus the recordings (``OUT/robot_poses.tum``,
``OUT/flange_sensor.tum``: the flange's and the sensor's poses, s and m).

:func:`robot_go` moves the needle guide to the plan: first to a point ``approach_mm`` back along the planned axis,
then along it; then it measures where the guide is with the flange sensor and the live reference, and corrects the
residual until it is within ``[robot] tolerance_mm`` / ``tolerance_deg`` or gives up (exit 3) after
``max_corrections``. The guide's pose streams over OpenIGTLink as ``NeedleGuideToRAS`` while it runs; ``OUT`` gets
``robot_go.json`` (every measurement, the final error).

Without ``execute`` nothing moves: both only say the planned motion. Every move is limited in velocity and
acceleration (``[robot]``) and stops when the tracker's flange or reference sensor is INVALID or stale, the
reference jumps, or the sensor leaves the tracker's volume (:mod:`EMRegModule.devices.robot.guard`): exit 3 with
the reason. What is planned and measured is said, a line each, on ``say``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
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
)
from ..core.transforms import apply_transform, invert_rigid, rotation_angle_deg
from ..devices.igtl_server import IGTLServer
from ..devices.robot.driver import MotionLimits
from ..devices.robot.guard import FlangeRecording, TrackerWatch, guarded_move, wait_for_tracker
from ..devices.robot.url import open_robot
from ..devices.sources import open_source
from ..errors import NoSafeAnswerError
from ..io.atomic import atomic_write_json
from ..io.tum import write_tum
from ..settings import RobotSettings, Settings
from .robot import RobotCalibration, read_target, write_calibration

Say = Callable[[str], None]


def _limits(robot_settings: RobotSettings) -> MotionLimits:
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


def _dwell(watch: TrackerWatch, seconds: float) -> None:
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


def plan_calibration(start: np.ndarray, sensor_tracker_mm: np.ndarray, settings: Settings) -> np.ndarray:
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


@dataclass(frozen=True)
class CalibrationRun:
    """A robot calibration moved through and solved: the written calibration and the number of poses planned."""

    calibration: RobotCalibration
    poses: int


def robot_calibrate(robot_url: str, tracker_url: str, flange_port: int, settings: Settings, out: Path,
                    execute: bool, say: Say) -> CalibrationRun | None:
    """Plan the calibration poses and say them; with ``execute``, move through them recording, come back, solve and
    write into ``out``. None for a dry run (nothing moved)."""
    robot_settings = settings.robot
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
        try:
            _dwell(watch, robot_settings.dwell_s)
            for pose in [*poses, start]:
                guarded_move(robot, pose, limits, watch)
                _dwell(watch, robot_settings.dwell_s)
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
    return CalibrationRun(write_calibration(out, result, inputs, []), len(poses))


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

    def __init__(self, port: int, watch: TrackerWatch, target: dict[str, Any], period_s: float = 0.05) -> None:
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
            self.server.send_transform("NeedleGuideToRAS", LPS_TO_RAS @ guide_to_image, time.time(), status)
            self.sent += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.server.close()


def _converge(robot, watch: TrackerWatch, target: dict[str, Any], settings: Settings, limits: MotionLimits,
              flange_port: int, reference_port: int, say: Say) -> list[dict[str, Any]]:
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


@dataclass(frozen=True)
class GoResult:
    """The guide on the plan: the measurements after the move and after each correction, the last one final."""

    history: list[dict[str, Any]]

    @property
    def final(self) -> dict[str, Any]:
        return self.history[-1]

    @property
    def corrections(self) -> int:
        return len(self.history) - 1


def robot_go(robot_url: str, tracker_url: str, target_path: str, flange_port: int, reference_port: int,
             settings: Settings, out: Path | None, execute: bool, igtl_port: int | None, say: Say) -> GoResult | None:
    """Say the planned motion to ``robot_target.json``'s plan; with ``execute``, move there, measure and correct
    until on the plan, streaming ``NeedleGuideToRAS`` on ``igtl_port`` (None: not streamed), and write
    ``out/robot_go.json`` (``out`` None: not written). None for a dry run (nothing moved)."""
    robot_settings = settings.robot
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
    went = GoResult(history)
    if out is not None:
        atomic_write_json(out / "robot_go.json", {
            "on_plan": True, "corrections": went.corrections, "final": went.final, "measurements": history,
            "tolerance_mm": robot_settings.tolerance_mm, "tolerance_deg": robot_settings.tolerance_deg,
            "predicted_error_mm": target["predicted_error_mm"], "target": str(target_path),
            "note": "errors measured with the flange sensor through the guide against the plan, which follows the "
                    "live reference (exit: the guide's exit from Entry; tip: the needle tip at the planned depth "
                    "from Target; angle: the guide's +z against Entry -> Target)"})
    return went
