"""Where the robot must go: the flange pose that puts a needle guide on a trajectory planned in the CT.

Frames (mm): ``Image`` (CT, LPS), ``Reference`` (the reference sensor on the patient's fiducial frame),
``Tracker``, ``Base`` (the robot's base), ``Flange``, ``Sensor`` (the EM sensor on the flange's guide),
``NeedleGuide`` (origin at the guide's exit, +z the needle's direction). The chain:

- ``ImageToBase = TrackerToBase @ ReferenceToTracker @ inv(ReferenceToImage)`` puts the plan (Entry, Target)
  in the robot's base frame;
- the guide's pose ``NeedleGuideToBase``: its exit at Entry (or ``standoff_mm`` before it, back along the axis),
  its +z along Entry -> Target, the roll about the axis free;
- ``FlangeToBase = NeedleGuideToBase @ inv(SensorToFlange @ NeedleGuideToSensor)``.

The roll is chosen, with the robot's model known (:mod:`EMRegModule.core.robot_kinematics`), to keep the robot
furthest from its joint limits: the flange pose at every roll (``ROLL_STEP_DEG`` apart) solved for the joints
from a few seeds, the roll whose best solution has the largest margin to the limits wins; a plan no roll makes
reachable is refused. Without a model, the roll keeps the flange's orientation nearest a preferred one (the mean
orientation of the hand-eye recording, which the robot has reached). Pure: arrays in, a :class:`RobotTarget` out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import NoSafeAnswerError
from .robot_kinematics import RobotModel, seeds_around
from .robot_kinematics import robot_model as make_robot_model
from .robot_motion import positioning_ms_at
from .transforms import apply_transform, invert_rigid, rotation_matrices

#: Rolls about the guide's axis tried with a robot model (degrees apart).
ROLL_STEP_DEG = 5.0


@dataclass(frozen=True)
class RobotTarget:
    """The answer: ``flange_to_base`` and ``needle_guide_to_base`` (4x4, mm); Entry and Target in the base
    frame (mm); the depth Entry -> Target (mm); the roll chosen (degrees about the guide's +z from the guide
    frame whose x axis is nearest the base's); the predicted RMS error at the target (mm) per source and in
    total; with a robot model, the joint angles (rad) that reach ``flange_to_base`` and their margin to the
    joint limits (:meth:`~EMRegModule.core.robot_kinematics.RobotModel.limit_margin`; None without a model)."""

    flange_to_base: np.ndarray
    needle_guide_to_base: np.ndarray
    entry_base_mm: np.ndarray
    target_base_mm: np.ndarray
    depth_mm: float
    roll_deg: float
    predicted_error_mm: dict[str, float]
    joints_rad: np.ndarray | None = None
    joint_limit_margin: float | None = None


def _axis_frame(direction: np.ndarray) -> np.ndarray:
    """A rotation whose third column is ``direction`` (unit), its first column as near the base's x as may be."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - z * (helper @ z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _rotation_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def best_roll(guide_rotation: np.ndarray, guide_to_flange_rotation: np.ndarray,
              preferred_flange_rotation: np.ndarray) -> float:
    """The roll (rad) about the guide's +z that brings ``R_guide Rz(roll) R_guide_to_flange^T`` (the flange's
    rotation in the base frame) nearest ``preferred_flange_rotation`` (Frobenius; closed form)."""
    m = guide_to_flange_rotation.T @ preferred_flange_rotation.T @ guide_rotation
    return float(np.arctan2(m[0, 1] - m[1, 0], m[0, 0] + m[1, 1]))


def roll_for_joint_limits(guide_frame: np.ndarray, exit_base_mm: np.ndarray, guide_to_flange: np.ndarray,
                          model: RobotModel) -> tuple[float, np.ndarray, float]:
    """The roll (rad) about the guide's +z that keeps the robot furthest from its joint limits, with the joint
    angles (rad) that reach the flange pose there and their margin; :class:`NoSafeAnswerError` when no roll is
    reachable. ``guide_frame``: the guide's rotation at roll 0 (Base frame); ``exit_base_mm``: where its exit goes."""
    rolls = np.radians(np.arange(0.0, 360.0, ROLL_STEP_DEG))
    flange_to_guide = invert_rigid(guide_to_flange)
    targets = np.empty((len(rolls), 4, 4))
    for k, roll in enumerate(rolls):
        guide_to_base = np.eye(4)
        guide_to_base[:3, :3], guide_to_base[:3, 3] = guide_frame @ _rotation_z(roll), exit_base_mm
        targets[k] = guide_to_base @ flange_to_guide
    seeds = seeds_around(model)
    joints, reached = model.inverse(np.repeat(targets, len(seeds), axis=0), np.tile(seeds, (len(rolls), 1)))
    margin = np.where(reached, model.limit_margin(joints), -np.inf)
    best = int(np.argmax(margin))
    if not np.isfinite(margin[best]):
        raise NoSafeAnswerError(f"robot-target: the {model.name.upper()} cannot reach the plan at any roll about the "
                                "needle's axis (the flange pose is out of its reach or beyond its joint limits); "
                                "plan another entry, or move the robot's base")
    return float(rolls[best // len(seeds)]), joints[best], float(margin[best])


def plan_flange_pose(entry_image: np.ndarray, target_image: np.ndarray, reference_to_image: np.ndarray,
                     reference_to_tracker: np.ndarray, tracker_to_base: np.ndarray, sensor_to_flange: np.ndarray,
                     needle_guide_to_sensor: np.ndarray, standoff_mm: float = 0.0,
                     preferred_flange_rotation: np.ndarray | None = None, robot_model: RobotModel | None = None
                     ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None, float | None]:
    """``(FlangeToBase, NeedleGuideToBase, roll rad, joints rad, joint-limit margin)`` (4x4, mm) that put the
    guide's exit on Entry (or ``standoff_mm`` before it) with its +z along Entry -> Target (both LPS mm in the
    CT); the joints and margin None without ``robot_model``. See the module docstring for the frames and the
    roll."""
    image_to_base = tracker_to_base @ reference_to_tracker @ invert_rigid(reference_to_image)
    entry, target = apply_transform(image_to_base, np.vstack([entry_image, target_image]))
    if np.linalg.norm(target - entry) < 1e-6:
        raise NoSafeAnswerError("robot-target: Entry and Target are the same point; the plan has no direction")
    direction = (target - entry) / np.linalg.norm(target - entry)
    guide_to_flange = sensor_to_flange @ needle_guide_to_sensor
    frame = _axis_frame(direction)
    exit_point = entry - standoff_mm * direction
    joints, margin = None, None
    if robot_model is not None:
        roll, joints, margin = roll_for_joint_limits(frame, exit_point, guide_to_flange, robot_model)
    elif preferred_flange_rotation is not None:
        roll = best_roll(frame, guide_to_flange[:3, :3], preferred_flange_rotation)
    else:
        roll = 0.0
    guide_to_base = np.eye(4)
    guide_to_base[:3, :3] = frame @ _rotation_z(roll)
    guide_to_base[:3, 3] = exit_point
    return guide_to_base @ invert_rigid(guide_to_flange), guide_to_base, roll, joints, margin


def _params_to_pose(pose: np.ndarray, params: np.ndarray) -> np.ndarray:
    """A pose moved by 6 parameters: a rotation vector applied on the right (rad), a translation added (mm)."""
    moved = pose.copy()
    moved[:3, :3] = pose[:3, :3] @ rotation_matrices(params[:3])
    moved[:3, 3] = pose[:3, 3] + params[3:]
    return moved


def hand_eye_ms_at(guide_tracker: np.ndarray, tip_guide_mm: np.ndarray, sensor_to_flange: np.ndarray,
                   tracker_to_base: np.ndarray, needle_guide_to_sensor: np.ndarray,
                   parameter_covariance: np.ndarray) -> float:
    """Mean-square error (mm^2) of the needle tip (``tip_guide_mm``, NeedleGuide frame) from the hand-eye
    calibration's 12 pose parameters (X's and Y's rotation vectors on the right, rad, and translations, mm; their
    full covariance, cross terms included: near the calibration's poses X's and Y's errors largely cancel).

    The guide is wanted at ``guide_tracker`` (4x4, Tracker frame). The robot is sent to ``Y W inv(X G)`` with the
    calibration's X and Y; the guide then truly stands at ``Y_true W inv(X G) X_true G``: the tip's error is
    linearised in the calibration's errors by central differences."""
    covariance = np.asarray(parameter_covariance, dtype=float)[:12, :12]
    tip = np.append(np.asarray(tip_guide_mm, dtype=float), 1.0)
    commanded = tracker_to_base @ guide_tracker @ invert_rigid(sensor_to_flange @ needle_guide_to_sensor)

    def tip_base(params: np.ndarray) -> np.ndarray:
        # the truth as the calibration's answer moved by the parameters' error
        true_x, true_y = _params_to_pose(sensor_to_flange, params[:6]), _params_to_pose(tracker_to_base, params[6:])
        return (invert_rigid(true_y) @ commanded @ true_x @ needle_guide_to_sensor @ tip)[:3]

    step = np.array([1e-6] * 3 + [1e-3] * 3 + [1e-6] * 3 + [1e-3] * 3)
    jac = np.empty((3, 12))
    for k in range(12):
        delta = np.zeros(12)
        delta[k] = step[k]
        jac[:, k] = (tip_base(delta) - tip_base(-delta)) / (2 * step[k])
    return float(np.trace(jac @ covariance @ jac.T))


def robot_ms_at(tip_flange_mm: np.ndarray, errors: np.ndarray | None, rms: tuple[float, float] = (0.0, 0.0)
                ) -> float:
    """Mean-square error (mm^2) of a point on the flange (``tip_flange_mm``, Flange frame) from the robot's own
    positioning: over its measured misses ``errors`` (:func:`~EMRegModule.core.robot_motion.positioning_errors`),
    else from an RMS distance (mm) and angle (degrees, about any axis) ``rms``."""
    if errors is not None and len(errors):
        return positioning_ms_at(tip_flange_mm, errors)
    return rms[0] ** 2 + (2.0 / 3.0) * (np.radians(rms[1]) * float(np.linalg.norm(tip_flange_mm))) ** 2


def robot_target(entry_image: np.ndarray, target_image: np.ndarray, reference_to_image: np.ndarray,
                 reference_to_tracker: np.ndarray, tracker_to_base: np.ndarray, sensor_to_flange: np.ndarray,
                 needle_guide_to_sensor: np.ndarray, hand_eye_covariance: np.ndarray, registration_ms_mm2: float,
                 tool_rms_mm: float = 0.0, standoff_mm: float = 0.0,
                 preferred_flange_rotation: np.ndarray | None = None, max_tracker_distance_mm: float | None = None,
                 reach_mm: float | None = None, robot_model: RobotModel | str | None = None,
                 end_effector: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), positioning_errors: np.ndarray | None = None,
                 positioning_rms: tuple[float, float] = (0.0, 0.0)) -> RobotTarget:
    """The flange pose for a plan and its predicted error at the target (see :func:`plan_flange_pose`).

    ``hand_eye_covariance``: the calibration's parameter covariance (13x13 or 12x12); ``registration_ms_mm2``: the
    registration's mean-square error at the target (mm^2); ``tool_rms_mm``: the guide's calibration error (mm);
    ``robot_model``: the robot's kinematic model, or its name (``[robot] model``) with ``end_effector`` (the
    translation mm and roll-pitch-yaw degrees set on the robot, :func:`~EMRegModule.core.robot_kinematics.robot_model`);
    ``positioning_errors``: the robot's own misses (commanded against reached flange poses,
    :func:`~EMRegModule.core.robot_motion.positioning_errors`), else ``positioning_rms`` (mm, degrees). The
    predicted error is that of the needle
    tip at the target, per source (``registration``, ``hand_eye``, ``tool``, ``robot``) and in ``total``.
    Refused (:class:`NoSafeAnswerError`) when Entry or Target lies farther than ``max_tracker_distance_mm`` from
    the field generator, the flange would be farther than ``reach_mm`` from the robot's base, or (with
    ``robot_model``) no roll about the axis is reachable."""
    if isinstance(robot_model, str):
        robot_model = make_robot_model(robot_model, *end_effector)
    flange_to_base, guide_to_base, roll, joints, margin = plan_flange_pose(
        entry_image, target_image, reference_to_image, reference_to_tracker, tracker_to_base, sensor_to_flange,
        needle_guide_to_sensor, standoff_mm, preferred_flange_rotation, robot_model)
    image_to_tracker = reference_to_tracker @ invert_rigid(reference_to_image)
    entry_tracker, target_tracker = apply_transform(image_to_tracker, np.vstack([entry_image, target_image]))
    if max_tracker_distance_mm is not None:
        far = max(np.linalg.norm(entry_tracker), np.linalg.norm(target_tracker))
        if far > max_tracker_distance_mm:
            raise NoSafeAnswerError(f"robot-target: the plan lies {far:.0f} mm from the field generator, outside the "
                                    f"tracker's volume ({max_tracker_distance_mm:g} mm, [robot] "
                                    "max_tracker_distance_mm): the guide could not be verified there")
    if reach_mm is not None and np.linalg.norm(flange_to_base[:3, 3]) > reach_mm:
        raise NoSafeAnswerError(f"robot-target: the flange would be {np.linalg.norm(flange_to_base[:3, 3]):.0f} mm "
                                f"from the robot's base, beyond its reach ({reach_mm:g} mm, [robot] reach_mm)")
    image_to_base = tracker_to_base @ image_to_tracker
    entry_base, target_base = apply_transform(image_to_base, np.vstack([entry_image, target_image]))
    depth = float(np.linalg.norm(target_base - entry_base))
    tip_guide = np.array([0.0, 0.0, depth + standoff_mm])  # the needle tip at the target, NeedleGuide frame
    guide_tracker = invert_rigid(tracker_to_base) @ guide_to_base
    hand_eye_ms = hand_eye_ms_at(guide_tracker, tip_guide, sensor_to_flange, tracker_to_base, needle_guide_to_sensor,
                                 hand_eye_covariance)
    tip_flange = apply_transform(sensor_to_flange @ needle_guide_to_sensor, tip_guide[None])[0]
    robot_ms = robot_ms_at(tip_flange, positioning_errors, positioning_rms)
    terms = {"registration": float(np.sqrt(max(registration_ms_mm2, 0.0))), "hand_eye": float(np.sqrt(hand_eye_ms)),
             "tool": float(tool_rms_mm), "robot": float(np.sqrt(robot_ms))}
    terms["total"] = float(np.sqrt(sum(v ** 2 for v in terms.values())))
    return RobotTarget(flange_to_base, guide_to_base, entry_base, target_base, depth, float(np.degrees(roll)), terms,
                       joints, margin)
