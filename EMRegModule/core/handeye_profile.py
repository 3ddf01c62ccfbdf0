"""How well a hand-eye calibration explains its recordings, for a reader to see (the report's robot section): the
residual of every tracker sample at the chosen clock offset, and the residual the frames would have were the clocks
offset otherwise. Pure: arrays in, a :class:`CalibrationFit` out.

Frames and units as in :mod:`.handeye`: ``FlangeToBase @ SensorToFlange = TrackerToBase @ SensorToTracker``, 4x4 mm;
``t_tracker = t_robot + time_offset_s`` (s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .handeye import SCAN_HALF_WIDTH_S, pose_residuals, residual_distances
from .handeye_sync import interpolate_poses, prepared_log

#: A tracker sample farther than this from the robot's log on either side (s) has no robot pose to compare with.
MAX_ROBOT_GAP_S = 0.25

#: The offset profile is evaluated on at most this many frames, spread over the recording.
PROFILE_FRAMES = 400


@dataclass(frozen=True)
class CalibrationFit:
    """The calibration against its recordings.

    Per tracker sample (tracker clock, s): ``rotation_deg`` and ``translation_mm``, the sensor's pose by the robot
    against by the tracker (NaN where the robot's log has no pose then); ``rejected``, the samples the calibration
    left out. The clock-offset profile: ``offsets_s`` (``t_tracker - t_robot``) and ``offset_residual_mm``, the
    median residual of the frames used (the sensor origin's distance and the rotation's at the solver's lever,
    mm) with X and Y kept, at each offset; ``time_offset_s`` the offset chosen."""

    time_s: np.ndarray
    rotation_deg: np.ndarray
    translation_mm: np.ndarray
    rejected: np.ndarray
    offsets_s: np.ndarray
    offset_residual_mm: np.ndarray
    time_offset_s: float


def calibration_fit(robot_time_s: np.ndarray, flange_to_base: np.ndarray, tracker_time_s: np.ndarray,
                    sensor_to_tracker: np.ndarray, sensor_to_flange: np.ndarray, tracker_to_base: np.ndarray,
                    time_offset_s: float, rejected_rows: np.ndarray, half_width_s: float = SCAN_HALF_WIDTH_S,
                    steps: int = 81) -> CalibrationFit:
    """The residuals of a calibration (``sensor_to_flange``, ``tracker_to_base``, ``time_offset_s``) on the robot's
    log (``FlangeToBase`` at ``robot_time_s``, robot clock) and the tracker's samples (``SensorToTracker`` at
    ``tracker_time_s``), with ``rejected_rows`` (indices of the tracker samples it left out); the offset profile
    over ``time_offset_s`` +/- ``half_width_s`` in ``steps`` steps."""
    robot_time_s, flange_to_base = prepared_log(robot_time_s, flange_to_base)  # as the solver saw it
    rejected = np.zeros(len(tracker_time_s), dtype=bool)
    rejected[np.asarray(rejected_rows, dtype=int)] = True
    flange, paired = interpolate_poses(robot_time_s, flange_to_base, tracker_time_s - time_offset_s, MAX_ROBOT_GAP_S)
    turn, shift = pose_residuals(flange, sensor_to_tracker, sensor_to_flange, tracker_to_base)
    rotation_deg = np.where(paired, np.degrees(np.linalg.norm(turn, axis=1)), np.nan)
    translation_mm = np.where(paired, np.linalg.norm(shift, axis=1), np.nan)
    used = np.nonzero(~rejected)[0]
    used = used[np.unique(np.linspace(0, len(used) - 1, min(len(used), PROFILE_FRAMES)).round().astype(int))] \
        if len(used) else used
    offsets = time_offset_s + np.linspace(-half_width_s, half_width_s, steps)
    profile = np.full(len(offsets), np.nan)
    for k, offset in enumerate(offsets):
        flange_k, valid = interpolate_poses(robot_time_s, flange_to_base, tracker_time_s[used] - offset,
                                            MAX_ROBOT_GAP_S)
        if np.count_nonzero(valid) >= 3:
            profile[k] = float(np.median(residual_distances(flange_k[valid], sensor_to_tracker[used][valid],
                                                            sensor_to_flange, tracker_to_base)))
    return CalibrationFit(np.asarray(tracker_time_s, dtype=float), rotation_deg, translation_mm, rejected, offsets,
                          profile, float(time_offset_s))
