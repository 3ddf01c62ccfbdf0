"""The simulated world both simulated trackers measure: which sensors there are and where they are, in the
Tracker frame (position mm, angles degrees: azimuth, elevation, roll), as a function of time.

:class:`BuiltinScene` is a deterministic scene (the fiducial frame's reference sensor at rest on sensor 1, a
probe dwelling at waypoints on sensor 2, two tools moving on sensors 3 and 4); :class:`ReplayScene` is a
tracking recording played back (the recording's quality numbers ride along with each pose). The trakSTAR
simulator encodes these poses as records, the Aurora simulator as BX/TX transforms (:func:`pose_at`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ...core.transforms import rotation_to_angles
from ...errors import EMRegError
from ..trakstar import protocol as tp
from ..trakstar.protocol import Pose

if TYPE_CHECKING:
    from ...core.tracking import TrackingRecording


class BuiltinScene:
    """A deterministic scene in the Tracker frame (mm, degrees), a function of time.

    Port 1: the reference sensor of the fiducial frame, at rest. Port 2: the probe, dwelling at
    six waypoints around the frame and moving between them. Ports 3 and 4: tools moving slowly on
    circles. Everything stays inside the 36-inch position range.
    """

    sensors = (1, 2, 3, 4)
    period_s: float | None = None

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.reference_position = np.array([300.0, 40.0, 120.0])
        self.reference_angles = np.array([20.0, -10.0, 5.0])
        self.waypoints = self.reference_position + rng.uniform(-60.0, 60.0, size=(6, 3))
        self.dwell_s = 0.6
        self.move_s = 0.4

    def pose(self, sensor: int, t_s: float) -> Pose:
        """Truth pose of ``sensor`` at ``t_s`` seconds after start."""
        if sensor == 1:
            return Pose(self.reference_position.copy(), self.reference_angles.copy())
        if sensor == 2:
            cycle = self.dwell_s + self.move_s
            k = int(t_s // cycle)
            phase = t_s - k * cycle
            a = self.waypoints[k % len(self.waypoints)]
            b = self.waypoints[(k + 1) % len(self.waypoints)]
            s = 0.0 if phase < self.dwell_s else (phase - self.dwell_s) / self.move_s
            s = s * s * (3.0 - 2.0 * s)
            position = a + s * (b - a)
            angles = np.array([40.0 * np.sin(0.7 * t_s), 30.0 * np.sin(0.5 * t_s + 1.0), 60.0 * np.sin(0.3 * t_s)])
            return Pose(position, angles)
        w = 0.8 if sensor == 3 else -0.5
        centre = np.array([200.0, -150.0, 50.0]) if sensor == 3 else np.array([-250.0, 100.0, -80.0])
        position = centre + 80.0 * np.array([np.cos(w * t_s), np.sin(w * t_s), 0.3 * np.sin(2 * w * t_s)])
        azimuth = ((100.0 * w * t_s + 180.0) % 360.0) - 180.0
        angles = np.array([azimuth, 45.0 * np.sin(w * t_s), -170.0 + (20.0 * t_s) % 340.0])
        return Pose(position, angles)


class ReplayScene:
    """Poses from a tracking recording (``SensorToTracker`` rows), frame by frame.

    Rows of one moment (same ``time_s`` within 1 ms) form one frame. ``next_point(sensor)`` returns
    the sensor's samples one after another (cycling), ``frame(k)`` the k-th frame (cycling).
    """

    def __init__(self, recording: TrackingRecording) -> None:
        order = np.argsort(recording.time_s, kind="stable")
        times = recording.time_s[order]
        sensors = recording.sensor[order]
        positions = recording.position_mm[order]
        angles = rotation_to_angles(recording.rotation[order])
        quality = np.nan_to_num(recording.quality[order], nan=0.0)
        self.sensors = tuple(sorted(int(s) for s in np.unique(sensors)))
        if any(not 1 <= s <= tp.MAX_SENSORS for s in self.sensors):
            raise EMRegError(f"{recording.source}: the simulator has sensor ports 1..4, "
                             f"the recording uses {self.sensors}")
        self.frames: list[tuple[float, dict[int, Pose]]] = []
        for i in range(len(times)):
            if not self.frames or times[i] - self.frames[-1][0] > 1e-3:
                self.frames.append((float(times[i]), {}))
            self.frames[-1][1][int(sensors[i])] = Pose(positions[i].copy(), angles[i].copy(), float(quality[i]))
        self.per_sensor = {s: [p[s] for _, p in self.frames if s in p] for s in self.sensors}
        self._cursor = dict.fromkeys(self.sensors, 0)
        frame_times = np.array([t for t, _ in self.frames])
        steps = np.diff(frame_times)
        self.period_s = float(np.median(steps)) if len(steps) else 1.0 / tp.POWER_ON_RATE_HZ
        self.duration_s = float(frame_times[-1] - frame_times[0]) + self.period_s

    def next_point(self, sensor: int) -> Pose | None:
        samples = self.per_sensor.get(sensor)
        if not samples:
            return None
        i = self._cursor[sensor]
        self._cursor[sensor] = (i + 1) % len(samples)
        return samples[i]

    def frame_offset_s(self, k: int) -> float:
        """Time of frame ``k`` (cycling) from the first frame, in seconds."""
        n = len(self.frames)
        loops, i = divmod(k, n)
        return loops * self.duration_s + self.frames[i][0] - self.frames[0][0]

    def frame(self, k: int) -> dict[int, Pose]:
        return self.frames[k % len(self.frames)][1]


#: Either scene.
Scene = BuiltinScene | ReplayScene


def pose_at(scene: Scene, sensor: int, t_s: float, frame: int) -> Pose | None:
    """The truth pose of ``sensor``: a built-in scene's at ``t_s`` seconds after the start, a replay's in its
    ``frame`` (cycling); None for a sensor the scene does not have."""
    if isinstance(scene, ReplayScene):
        return scene.frame(frame).get(sensor)
    return scene.pose(sensor, t_s) if sensor in scene.sensors else None
