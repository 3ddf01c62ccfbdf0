"""How the robot moves for EMReg: the calibration poses it plans for itself, and the closed-loop step that brings
the needle guide onto the plan as the EM tracker measures it. Pure: arrays in, arrays out (mm, degrees).

Frames as in :mod:`EMRegModule.core.robot_target`: ``Base``, ``Flange``, ``Tracker``, ``Sensor`` (the EM sensor on the
flange's guide), ``NeedleGuide`` (origin at the guide's exit, +z the needle's direction), ``Reference``.

**Calibration poses.** Hand-eye calibration needs rotations about at least two non-parallel axes, and is best
conditioned when the rotation axes are spread over all directions and the angles are large. The poses turn the
flange from where it stands by ``angle_deg`` about axes spread evenly over a hemisphere of the flange's own frame
(a Fibonacci lattice, the sign alternating), about a pivot fixed on the flange (where the sensor sits, roughly),
with small translations spread over a cube so that the translations are determined too. Before the sensor's
place on the flange is known, a pose is kept only when the sensor, wherever it is within ``sensor_radius_mm``
of the pivot, stays inside the tracker's volume.

**Closed loop.** Where the guide is, as the tracker sees it (``NeedleGuideToTracker`` from the flange sensor), is
compared with where the plan wants it (the plan follows the live reference); the difference, carried into the
base frame through ``TrackerToBase``, is applied to the flange: ``FlangeToBase_next = Delta @ FlangeToBase_now``
with ``Delta = NeedleGuideToBase_wanted @ inv(NeedleGuideToBase_seen)``. Errors in ``SensorToFlange`` and in the
robot's own positioning cancel; an error in ``TrackerToBase``'s rotation only turns the correction slightly, so the
steps still converge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import NoSafeAnswerError
from .transforms import axis_angle_to_rotation, invert_rigid, rotation_angle_deg, rotation_matrices, rotation_vectors


def spread_axes(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the upper hemisphere (z >= 0; a Fibonacci lattice), (count, 3)."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count  # 1 .. 0: the upper hemisphere
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * k
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), z])


def plan_calibration_poses(flange_to_base: np.ndarray, count: int = 12, angle_deg: float = 25.0,
                           translation_mm: float = 20.0, pivot_flange_mm: np.ndarray | None = None) -> np.ndarray:
    """Calibration poses (count, 4, 4, mm) around ``flange_to_base``: the flange turned by +-``angle_deg`` about
    axes spread over a hemisphere of its own frame, about ``pivot_flange_mm`` (a point on the flange, Flange frame,
    mm; default its origin), each moved by up to ``translation_mm`` along the base's axes (a cube's corners)."""
    start = np.asarray(flange_to_base, dtype=float)
    pivot = np.zeros(3) if pivot_flange_mm is None else np.asarray(pivot_flange_mm, dtype=float)
    axes = spread_axes(count)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    poses = np.empty((count, 4, 4))
    for k, axis in enumerate(axes):
        turn = np.eye(4)
        turn[:3, :3] = axis_angle_to_rotation(axis, np.radians(angle_deg) * (1 if k % 2 == 0 else -1))
        turn[:3, 3] = pivot - turn[:3, :3] @ pivot  # about the pivot, in the flange's frame
        pose = start @ turn
        pose[:3, 3] += translation_mm * corners[(3 * k) % len(corners)] / np.sqrt(3.0)
        poses[k] = pose
    return poses


def sensor_reach_mm(start_flange_to_base: np.ndarray, pose: np.ndarray, pivot_flange_mm: np.ndarray,
                    sensor_radius_mm: float) -> float:
    """How far (mm) a sensor within ``sensor_radius_mm`` of the pivot (Flange frame) can move from the start pose
    to ``pose``: the pivot's displacement plus the turn's chord at that radius."""
    pivot = np.append(np.asarray(pivot_flange_mm, dtype=float), 1.0)
    moved = float(np.linalg.norm((pose @ pivot - start_flange_to_base @ pivot)[:3]))
    angle = float(np.radians(rotation_angle_deg(start_flange_to_base[:3, :3], pose[:3, :3])))
    return moved + 2.0 * np.sin(angle / 2.0) * sensor_radius_mm


def keep_in_volume(start_flange_to_base: np.ndarray, poses: np.ndarray, sensor_tracker_mm: np.ndarray,
                   max_tracker_distance_mm: float, pivot_flange_mm: np.ndarray | None = None,
                   sensor_radius_mm: float = 150.0) -> np.ndarray:
    """The poses (a boolean mask) that keep the sensor, now at ``sensor_tracker_mm`` (Tracker frame, mm), inside the
    tracker's volume (``max_tracker_distance_mm`` from the field generator) wherever within ``sensor_radius_mm`` of
    the pivot it sits."""
    pivot = np.zeros(3) if pivot_flange_mm is None else pivot_flange_mm
    now = float(np.linalg.norm(sensor_tracker_mm))
    return np.array([now + sensor_reach_mm(start_flange_to_base, pose, pivot, sensor_radius_mm)
                     <= max_tracker_distance_mm for pose in poses], dtype=bool)


def positioning_errors(commanded: np.ndarray, reached: np.ndarray) -> np.ndarray:
    """How the robot missed the flange poses it was told (N, 4, 4 each, mm, Base frame), from moves that ended:
    per move, the reached pose in the commanded one's frame as a rotation vector (rad) and a translation (mm),
    (N, 6) in the Flange frame: a point ``r`` on the flange lands ``R r + t - r`` from where it was sent."""
    commanded, reached = np.asarray(commanded, dtype=float), np.asarray(reached, dtype=float)
    miss = np.array([invert_rigid(pose) for pose in commanded]) @ reached
    return np.concatenate([rotation_vectors(miss[:, :3, :3]), miss[:, :3, 3]], axis=1)


def positioning_ms_at(point_flange_mm: np.ndarray, errors: np.ndarray) -> float:
    """Mean-square distance (mm^2) by which a point on the flange (Flange frame, mm) misses, over the robot's
    positioning errors (:func:`positioning_errors`)."""
    errors = np.asarray(errors, dtype=float).reshape(-1, 6)
    if not len(errors):
        return 0.0
    point = np.asarray(point_flange_mm, dtype=float)
    moved = (rotation_matrices(errors[:, :3]) @ point) + errors[:, 3:]
    return float(np.mean(np.sum((moved - point) ** 2, axis=1)))


@dataclass(frozen=True)
class GuideError:
    """How far the guide is from the plan: its exit from Entry (mm), the exit's distance from the planned line
    (mm), the angle between its +z and Entry -> Target (deg), and the needle tip at the planned depth from Target
    (mm)."""

    exit_mm: float
    lateral_mm: float
    angle_deg: float
    tip_mm: float

    def within(self, tolerance_mm: float, tolerance_deg: float) -> bool:
        return self.exit_mm <= tolerance_mm and self.tip_mm <= tolerance_mm and self.angle_deg <= tolerance_deg

    def describe(self) -> str:
        return (f"exit {self.exit_mm:.2f} mm from Entry, tip {self.tip_mm:.2f} mm from Target, "
                f"axis {self.angle_deg:.2f} deg off")


def guide_error(needle_guide_to_frame: np.ndarray, entry_mm: np.ndarray, target_mm: np.ndarray,
                standoff_mm: float = 0.0) -> GuideError:
    """The guide's error against a plan, all in one frame (mm): the guide's pose, Entry and Target. With a standoff
    the exit is compared with the point ``standoff_mm`` before Entry."""
    entry, target = np.asarray(entry_mm, dtype=float), np.asarray(target_mm, dtype=float)
    depth = float(np.linalg.norm(target - entry))
    u = (target - entry) / depth
    wanted_exit = entry - standoff_mm * u
    exit_point = needle_guide_to_frame[:3, 3]
    axis = needle_guide_to_frame[:3, 2]
    offset = exit_point - wanted_exit
    lateral = offset - (offset @ u) * u
    tip = exit_point + (depth + standoff_mm) * axis
    angle = float(np.degrees(np.arccos(np.clip(axis @ u, -1.0, 1.0))))
    return GuideError(float(np.linalg.norm(offset)), float(np.linalg.norm(lateral)), angle,
                      float(np.linalg.norm(tip - target)))


def correct_flange(flange_to_base_now: np.ndarray, guide_seen_to_base: np.ndarray,
                   guide_wanted_to_base: np.ndarray) -> np.ndarray:
    """The next flange pose (4x4, mm) of the closed loop (module docstring)."""
    delta = np.asarray(guide_wanted_to_base, dtype=float) @ invert_rigid(guide_seen_to_base)
    pose = delta @ np.asarray(flange_to_base_now, dtype=float)
    u, _, vt = np.linalg.svd(pose[:3, :3])
    pose[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return pose


def approach_pose(flange_to_base: np.ndarray, guide_to_flange: np.ndarray, back_mm: float) -> np.ndarray:
    """The flange pose ``back_mm`` back along the guide's axis from ``flange_to_base`` (the guide's -z)."""
    guide_to_base = flange_to_base @ guide_to_flange
    shifted = flange_to_base.copy()
    shifted[:3, 3] -= back_mm * guide_to_base[:3, 2]
    return shifted


def check_step(flange_to_base_now: np.ndarray, flange_to_base_next: np.ndarray, max_step_mm: float,
               max_step_deg: float) -> None:
    """Refuse (:class:`NoSafeAnswerError`) a correction larger than a correction can be: something is wrong (the
    reference moved, the wrong calibration) and moving further would not be safe."""
    moved = float(np.linalg.norm(flange_to_base_next[:3, 3] - flange_to_base_now[:3, 3]))
    angle = float(rotation_angle_deg(flange_to_base_now[:3, :3], flange_to_base_next[:3, :3]))
    if moved > max_step_mm or angle > max_step_deg:
        raise NoSafeAnswerError(f"robot-go: the correction would move the flange {moved:.1f} mm and turn it "
                                f"{angle:.1f} deg (more than [robot] max_correction_mm {max_step_mm:g} / "
                                f"max_correction_deg {max_step_deg:g}); check the calibration and the reference")
