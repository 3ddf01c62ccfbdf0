"""A robot near a patient moves only while the tracker vouches for what it sees: :class:`TrackerWatch` follows the
flange sensor and the reference sensor of a live source, and :func:`guarded_move` stops the robot the moment

- the flange sensor's or the reference's pose is INVALID (the tracker does not vouch for it: not attached, out of
  range, missing) or stale (no sample for ``stale_s``);
- the flange sensor leaves the tracker's volume (farther than ``max_tracker_distance_mm`` from the field
  generator, or the tracker says it is out of range);
- the reference sensor jumps: the slip detector's jump test (:func:`EMRegModule.core.checkpoints.reference_jumps`) on
  its recent samples, or the reference standing farther than the jump limits from where it stood when the move
  began (``[navigation] reference_jump_mm`` / ``reference_jump_deg``).

Poses are ``SensorToTracker`` (mm); times ``time.monotonic()`` seconds when a sample arrived.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ...core.checkpoints import reference_jumps
from ...core.transforms import rotation_angle_deg
from ...errors import NoSafeAnswerError
from ...io.handeye_inputs import robust_mean_pose
from ...settings import NavigationSettings
from ..samples import STATUS_OUT_OF_RANGE, SensorSample
from .driver import MotionLimits, RobotDriver

#: Reference samples kept for the jump test (at 80 Hz, about a second and a half).
REFERENCE_WINDOW = 120


@dataclass
class FlangeRecording:
    """The flange sensor's valid samples while recording: arrival times (s, monotonic) and poses (4x4, mm)."""

    time_s: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)


class TrackerWatch:
    """Follows the flange and reference sensors of a live source (``on_sample`` is the source's callback) and says
    why the robot must not move (:meth:`check`), if it must not."""

    def __init__(self, flange_port: int, reference_port: int | None, max_tracker_distance_mm: float,
                 stale_s: float = 0.25, navigation: NavigationSettings | None = None) -> None:
        self.flange_port = flange_port
        self.reference_port = reference_port
        self.max_tracker_distance_mm = max_tracker_distance_mm
        self.stale_s = stale_s
        self.navigation = navigation or NavigationSettings()
        self._lock = threading.Lock()
        self._last: dict[int, tuple[float, SensorSample]] = {}
        self._reference: deque[tuple[float, np.ndarray]] = deque(maxlen=REFERENCE_WINDOW)
        self._held: np.ndarray | None = None
        self.recording: FlangeRecording | None = None
        self._collect: dict[int, list[np.ndarray]] | None = None

    def on_sample(self, sample: SensorSample) -> None:
        if sample.sensor not in (self.flange_port, self.reference_port):
            return
        now = time.monotonic()
        with self._lock:
            self._last[sample.sensor] = (now, sample)
            if not sample.valid:
                return
            pose = sample.transform()
            if sample.sensor == self.reference_port:
                self._reference.append((now, pose))
            if sample.sensor == self.flange_port and self.recording is not None:
                self.recording.time_s.append(now)
                self.recording.poses.append(pose)
            if self._collect is not None:
                self._collect.setdefault(sample.sensor, []).append(pose)

    # -- what the tracker says now --------------------------------------------------------------
    def _sensor_problem(self, port: int, name: str, now: float) -> str | None:
        last = self._last.get(port)
        if last is None or now - last[0] > self.stale_s:
            age = "none yet" if last is None else f"none for {now - last[0]:.2f} s"
            return f"the {name} sensor (port {port}) is stale: {age} (limit {self.stale_s:g} s)"
        sample = last[1]
        if sample.status == STATUS_OUT_OF_RANGE:
            return f"the {name} sensor (port {port}) left the tracker's volume ({sample.transform_status})"
        if not sample.valid:
            return f"the {name} sensor (port {port}) is INVALID ({sample.transform_status})"
        distance = float(np.linalg.norm(sample.position_mm))
        if port == self.flange_port and distance > self.max_tracker_distance_mm:
            return (f"the flange sensor left the tracker's volume: {distance:.0f} mm from the field generator "
                    f"(limit {self.max_tracker_distance_mm:g} mm, [robot] max_tracker_distance_mm)")
        return None

    def _reference_problem(self) -> str | None:
        if len(self._reference) < 2:
            return None
        times = np.array([t for t, _ in self._reference])
        poses = np.array([p for _, p in self._reference])
        jumps = reference_jumps(times, poses[:, :3, 3], poses[:, :3, :3], self.navigation)
        if jumps:
            return f"the reference sensor jumped (the slip detector: {jumps[-1].describe()})"
        if self._held is not None and len(poses) >= 3:
            now_pose = robust_mean_pose(poses[-5:])
            moved = float(np.linalg.norm(now_pose[:3, 3] - self._held[:3, 3]))
            angle = float(rotation_angle_deg(self._held[:3, :3], now_pose[:3, :3]))
            if moved > self.navigation.reference_jump_mm or angle > self.navigation.reference_jump_deg:
                return (f"the reference sensor moved {moved:.2f} mm / {angle:.2f} deg since the motion began (limits "
                        f"{self.navigation.reference_jump_mm:g} mm / {self.navigation.reference_jump_deg:g} deg, "
                        "[navigation] reference_jump_mm / _deg)")
        return None

    def check(self) -> str | None:
        """Why the robot must stop now (one line), or None."""
        now = time.monotonic()
        with self._lock:
            problem = self._sensor_problem(self.flange_port, "flange", now)
            if problem is None and self.reference_port is not None:
                problem = self._sensor_problem(self.reference_port, "reference", now) or self._reference_problem()
        return problem

    def latest(self) -> tuple[SensorSample | None, SensorSample | None]:
        """The latest samples of the flange sensor and of the reference (None: none yet)."""
        with self._lock:
            flange = self._last.get(self.flange_port)
            reference = self._last.get(self.reference_port) if self.reference_port is not None else None
        return (flange[1] if flange else None), (reference[1] if reference else None)

    def hold_reference(self) -> None:
        """Remember where the reference stands now: a move stops when it leaves this pose."""
        with self._lock:
            if self._reference:
                self._held = robust_mean_pose(np.array([p for _, p in list(self._reference)[-9:]]))

    def release_reference(self) -> None:
        with self._lock:
            self._held = None

    def mean_poses(self, seconds: float, minimum: int = 5) -> dict[int, np.ndarray]:
        """The robust mean pose (4x4, mm) of the flange sensor and of the reference over the next ``seconds``,
        while each stays valid; :class:`NoSafeAnswerError` when the tracker gives too few samples or a stop
        condition arises meanwhile."""
        with self._lock:
            self._collect = {}
        end = time.monotonic() + seconds
        try:
            while time.monotonic() < end:
                problem = self.check()
                if problem:
                    raise NoSafeAnswerError(f"robot: cannot measure the guide: {problem}")
                time.sleep(0.01)
        finally:
            with self._lock:
                collected, self._collect = self._collect or {}, None
        out = {}
        for port in (self.flange_port, self.reference_port):
            if port is None:
                continue
            poses = collected.get(port, [])
            if len(poses) < minimum:
                raise NoSafeAnswerError(f"robot: {len(poses)} valid samples of port {port} in {seconds:g} s; the "
                                        "tracker does not see the sensor well enough to measure")
            out[port] = robust_mean_pose(np.array(poses))
        return out


def wait_for_tracker(watch: TrackerWatch, timeout_s: float = 3.0) -> None:
    """Wait until the watch has nothing against moving; :class:`NoSafeAnswerError` with the reason otherwise."""
    end = time.monotonic() + timeout_s
    while True:
        problem = watch.check()
        if problem is None:
            return
        if time.monotonic() > end:
            raise NoSafeAnswerError(f"robot: not moving: {problem}")
        time.sleep(0.02)


def guarded_move(robot: RobotDriver, flange_to_base: np.ndarray, limits: MotionLimits, watch: TrackerWatch,
                 poll_s: float = 0.005, timeout_s: float = 60.0) -> None:
    """Move the flange to ``flange_to_base`` (4x4, mm) within ``limits`` while the watch has nothing against it;
    stop the robot and raise :class:`NoSafeAnswerError` (exit 3) with the reason the moment it has (and on any
    interruption, Ctrl-C included)."""
    problem = watch.check()
    if problem:
        raise NoSafeAnswerError(f"robot: not moving: {problem}")
    watch.hold_reference()
    robot.start_move(flange_to_base, limits)
    end = time.monotonic() + timeout_s
    try:
        while robot.moving():
            problem = watch.check()
            if problem is None and time.monotonic() > end:
                problem = f"the move took longer than {timeout_s:g} s"
            if problem:
                robot.stop()
                raise NoSafeAnswerError(f"robot: stopped: {problem}")
            time.sleep(poll_s)
    except BaseException:
        robot.stop()
        raise
    finally:
        watch.release_reference()
