"""Hand-eye recordings with known truth, from KinHEC (a generator we did not write): published Panda, UR and
iiwa kinematics move the flange; KinHEC's eye-to-hand scene is ours (its "marker on the flange" is the EM
sensor, its static "camera" the field generator): ``X = T_ee_marker = SensorToFlange``,
``Y = T_base_cam = TrackerToBase``, ``B = T_cam_marker = SensorToTracker``.

KinHEC gives the robot's log (its own flange-pose noise) and the tracker's true poses at its sample instants on
an offset clock; EMReg's tests add what an EM tracker does on top: heavy-tailed noise (Student-t), a different
epoch, and wrong poses (single glitches, short distorted bursts). Used by ``test_handeye.py`` and
``scripts/bench_handeye.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from EMRegModule.core.transforms import make_transform, rotation_matrices

#: The robot's clock: ROS time (s since 1970) at the start of the recording.
ROBOT_EPOCH_S = 1_765_000_000.0

#: The tracker's clock: seconds since the tracker was switched on, at the start of the recording.
TRACKER_EPOCH_S = 1234.5

ROBOTS = {"panda": "panda", "ur": "ur5e", "iiwa": "iiwa7"}


@dataclass
class HandEyeCase:
    """One recording: the robot's log (``FlangeToBase``, mm, robot clock s), the tracker's (``SensorToTracker``,
    mm, tracker clock s), which tracker samples are wrong, and the truth."""

    name: str
    robot_time_s: np.ndarray
    flange_to_base: np.ndarray
    tracker_time_s: np.ndarray
    sensor_to_tracker: np.ndarray
    outlier: np.ndarray
    sensor_to_flange: np.ndarray
    tracker_to_base: np.ndarray
    time_offset_s: float
    true_flange_to_base: np.ndarray  # at the tracker's instants, noise free

    def write_tum(self, path: Path) -> None:
        """The robot's log as a TUM trajectory (s, m, ``qx qy qz qw``)."""
        quaternion = Rotation.from_matrix(self.flange_to_base[:, :3, :3]).as_quat()
        rows = np.column_stack([self.robot_time_s, self.flange_to_base[:, :3, 3] / 1000.0, quaternion])
        np.savetxt(path, rows, fmt="%.6f", header="timestamp tx ty tz qx qy qz qw (KinHEC, EMReg test)",
                   comments="# ")

    def write_csv(self, path: Path, port: int = 3, with_reference: bool = False) -> None:
        """The tracker's recording as EMReg's CSV (quaternions), the flange sensor on ``port`` (and a still
        reference sensor on port 1 with ``with_reference``)."""
        quaternion = Rotation.from_matrix(self.sensor_to_tracker[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        lines = ["time_s,sensor,x_mm,y_mm,z_mm,qw,qx,qy,qz,quality,label"]
        for t, p, q in zip(self.tracker_time_s, self.sensor_to_tracker[:, :3, 3], quaternion, strict=True):
            if with_reference:
                lines.append(f"{t:.6f},1,100.0,50.0,-200.0,1,0,0,0,,")
            lines.append(f"{t:.6f},{port},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{q[0]:.7f},{q[1]:.7f},{q[2]:.7f},"
                         f"{q[3]:.7f},,")
        path.write_text("\n".join(lines) + "\n")

    def write_recordings(self, folder: Path) -> tuple[Path, Path]:
        """The robot's log ``folder/robot.tum`` and the tracker's ``folder/tracker.csv`` (the flange sensor on port 3
        beside a still reference on port 1), as a robot session leaves them; their paths."""
        robot, tracker = Path(folder) / "robot.tum", Path(folder) / "tracker.csv"
        self.write_tum(robot)
        self.write_csv(tracker, port=3, with_reference=True)
        return robot, tracker

    def write_sequence(self, path: Path, name: str = "SensorToTracker", robot: bool = False) -> None:
        """The tracker's recording (or, with ``robot``, the robot's log) as a PLUS sequence metafile with one
        transform ``name``."""
        times, poses = (self.robot_time_s, self.flange_to_base) if robot else (self.tracker_time_s,
                                                                                 self.sensor_to_tracker)
        lines = ["ObjectType = Image", "NDims = 3", "BinaryData = True", "BinaryDataByteOrderMSB = False",
                 "CompressedData = False", f"DimSize = 0 0 {len(times)}", "ElementType = MET_UCHAR",
                 "Kinds = domain domain list"]
        for k, (t, pose) in enumerate(zip(times, poses, strict=True)):
            lines.append(f"Seq_Frame{k:04d}_{name}Transform = " + " ".join(f"{v:.9g}" for v in pose.ravel()))
            lines.append(f"Seq_Frame{k:04d}_{name}TransformStatus = OK")
            lines.append(f"Seq_Frame{k:04d}_Timestamp = {t:.6f}")
        lines.append("ElementDataFile = LOCAL")
        path.write_text("\n".join(lines) + "\n")


def _config(name: str, robot: str, family: str, seed: int, time_offset_s: float, tracker_rate_hz: float,
            robot_rate_hz: float, duration_s: float, family_params: dict | None):
    from kinhec import SequenceConfig

    params = {} if family == "joint_sinusoid" else {"n_waypoints": 10, "speed_frac": 0.35, "dwell_range": (0.8, 1.6)}
    params.update(family_params or {})
    return SequenceConfig(
        sequence_id=name, track="emreg", level="test", seed=seed, robot=ROBOTS.get(robot, robot),
        configuration="eye_to_hand", family=family, family_params=params,
        sampling={"mode": "continuous", "duration_s": duration_s, "camera_rate_hz": tracker_rate_hz,
                  "robot_rate_hz": robot_rate_hz, "sync": "asynchronous", "n_stations": None},
        timing={"time_offset_s": time_offset_s, "jitter_std_s": 0.0005, "drop_fraction": 0.0},
        camera_noise={"model": "none", "rot_std_rad": [0.0] * 3, "trans_std_m": [0.0] * 3, "pixel_std": 0.5,
                      "student_t_dof": None})


def _mm(poses: np.ndarray) -> np.ndarray:
    out = np.array(poses, dtype=float)
    out[..., :3, 3] *= 1000.0
    return out


def _outliers(rng: np.random.Generator, poses: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Wrong poses on ``fraction`` of the samples: half single glitches (any orientation, tens of mm off), half
    short distorted bursts (3 to 6 samples, 3-10 mm and 2-6 degrees off)."""
    n = len(poses)
    wrong = np.zeros(n, dtype=bool)
    out = poses.copy()
    target = int(round(fraction * n))
    while np.count_nonzero(wrong) < target // 2:
        i = int(rng.integers(n))
        wrong[i] = True
        out[i, :3, :3] = Rotation.random(random_state=rng).as_matrix()
        out[i, :3, 3] += rng.normal(size=3) * rng.uniform(20.0, 150.0)
    while np.count_nonzero(wrong) < target:
        start, length = int(rng.integers(n - 6)), int(rng.integers(3, 7))
        shift = rng.normal(size=3)
        shift *= rng.uniform(3.0, 10.0) / np.linalg.norm(shift)
        turn = Rotation.from_rotvec(rng.normal(size=3) * np.radians(rng.uniform(2.0, 6.0)) / np.sqrt(3))
        for i in range(start, start + length):
            out[i, :3, :3] = turn.as_matrix() @ poses[i, :3, :3]
            out[i, :3, 3] = poses[i, :3, 3] + shift
            wrong[i] = True
    return out, wrong


def _em_noise(rng: np.random.Generator, poses: np.ndarray, position_mm: float, rotation_deg: float,
              dof: float | None) -> np.ndarray:
    """EM-like noise: position in the Tracker frame, rotation in the Sensor frame, Student-t with ``dof`` degrees
    of freedom (heavy tails; None: Gaussian), scales ``position_mm`` and ``rotation_deg`` per axis."""
    n = len(poses)
    tail = np.sqrt(dof / rng.chisquare(dof, size=n))[:, None] if dof else np.ones((n, 1))
    out = poses.copy()
    out[:, :3, 3] += rng.normal(size=(n, 3)) * position_mm * tail
    turn = Rotation.from_rotvec(np.radians(rotation_deg) * rng.normal(size=(n, 3)) * tail).as_matrix()
    out[:, :3, :3] = poses[:, :3, :3] @ turn
    return out


def kinhec_case(robot: str = "panda", family: str = "joint_sinusoid", seed: int = 1, time_offset_s: float = 0.037,
                outlier_fraction: float = 0.0, noise: bool = True, em_position_mm: float = 0.2,
                em_rotation_deg: float = 0.1, tail_dof: float | None = 3.0, tracker_rate_hz: float = 40.0,
                robot_rate_hz: float = 200.0, duration_s: float = 20.0, family_params: dict | None = None
                ) -> HandEyeCase:
    """A KinHEC eye-to-hand sequence as an EM recording (see the module docstring). ``family``:
    ``joint_sinusoid`` (continuous motion) or ``joint_waypoints`` (move and dwell). ``time_offset_s``: the
    clocks' offset on top of their different epochs. ``noise`` False: KinHEC's robot log without its noise
    and the tracker without EM noise (outliers still as asked). ``family_params``: KinHEC's trajectory
    parameters (``joints``, ``amplitude_frac``...)."""
    from kinhec import Sequence, generate_sequence

    name = f"{robot}-{'continuous' if family == 'joint_sinusoid' else 'dwell'}-{seed}"
    config = _config(name, robot, family, seed, time_offset_s, tracker_rate_hz, robot_rate_hz, duration_s,
                     family_params)
    if not noise:
        config.robot_noise = {**config.robot_noise, "models": ["none"]}
    record = generate_sequence(config)
    sequence = Sequence(record.manifest, record.robot_table, record.camera_table)
    rng = np.random.default_rng(seed + 1000)
    tracker = _mm(sequence.camera.T_cam_target_gt)
    if noise:
        tracker = _em_noise(rng, tracker, em_position_mm, em_rotation_deg, tail_dof)
    tracker, wrong = _outliers(rng, tracker, outlier_fraction)
    return HandEyeCase(
        name=name, robot_time_s=sequence.robot.t + ROBOT_EPOCH_S, flange_to_base=_mm(sequence.robot.T_base_ee_meas),
        tracker_time_s=sequence.camera.t + TRACKER_EPOCH_S, sensor_to_tracker=tracker, outlier=wrong,
        sensor_to_flange=_mm(sequence.X), tracker_to_base=_mm(sequence.Y),
        time_offset_s=sequence.time_offset + TRACKER_EPOCH_S - ROBOT_EPOCH_S,
        true_flange_to_base=_mm(sequence.camera.T_base_ee_gt))


def tip_error_mm(sensor_to_flange: np.ndarray, truth: np.ndarray, tip_mm=(0.0, 0.0, 150.0)) -> float:
    """Distance (mm) between where two ``SensorToFlange`` put the tool point ``tip_mm`` (Sensor frame)."""
    tip = np.append(np.asarray(tip_mm, dtype=float), 1.0)
    return float(np.linalg.norm((sensor_to_flange @ tip - truth @ tip)[:3]))


def tracker_point_error_mm(tracker_to_base: np.ndarray, truth: np.ndarray, point_mm=(0.0, 0.0, 300.0)) -> float:
    """Distance (mm) between where two ``TrackerToBase`` put a point 300 mm in front of the tracker."""
    point = np.append(np.asarray(point_mm, dtype=float), 1.0)
    return float(np.linalg.norm((tracker_to_base @ point - truth @ point)[:3]))


def rotation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Angle (degrees) between two rotations (the 3x3 parts of two poses)."""
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(estimate[:3, :3].T @ truth[:3, :3]).as_rotvec())))


def pose(rotvec_deg, translation) -> np.ndarray:
    """A 4x4 pose (mm) from a rotation vector (degrees) and a translation (mm)."""
    return make_transform(rotation_matrices(np.radians(rotvec_deg)), translation)


def write_targeting_inputs(folder: Path) -> dict:
    """What ``emreg robot-target`` needs beside a calibration, written into ``folder``: ``reg/registration.json``,
    the reference sensor's recording ``reference.csv`` (port 1, 300 mm before the field generator), the plan
    ``plan.mrk.json`` (a Line Entry -> Target, LPS) and the needle guide as ``guide.json`` and ``guide.xml``; returns
    the truth (``reference_to_image``, ``reference_to_tracker``, ``entry``, ``target``, ``guide_to_sensor``)."""
    from EMRegModule.core.registration import RegistrationResult
    from EMRegModule.io.registration_files import write_registration

    reference_to_image = pose([10.0, -20.0, 150.0], [-40.0, 120.0, -300.0])
    write_registration(RegistrationResult(reference_to_image, 14.0, 0.2, []), folder / "reg")
    reference_to_tracker = pose([5.0, 30.0, -10.0], [20.0, -30.0, 300.0])
    rng = np.random.default_rng(3)
    lines = ["time_s,sensor,x_mm,y_mm,z_mm,qw,qx,qy,qz,quality,label"]
    q = Rotation.from_matrix(reference_to_tracker[:3, :3]).as_quat()
    for k in range(60):
        p = reference_to_tracker[:3, 3] + rng.normal(0.0, 0.1, 3)
        lines.append(f"{k / 40:.4f},1,{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{q[3]:.8f},{q[0]:.8f},{q[1]:.8f},{q[2]:.8f},,")
    (folder / "reference.csv").write_text("\n".join(lines) + "\n")
    entry_ref, target_ref = np.array([30.0, 10.0, 60.0]), np.array([10.0, -15.0, -20.0])
    entry = (reference_to_image @ np.append(entry_ref, 1))[:3]
    target = (reference_to_image @ np.append(target_ref, 1))[:3]
    plan = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                       "Schema/markups-schema-v1.0.3.json#",
            "markups": [{"type": "Line", "coordinateSystem": "LPS", "controlPoints": [
                {"label": "Entry", "position": entry.tolist()}, {"label": "Target", "position": target.tolist()}]}]}
    (folder / "plan.mrk.json").write_text(json.dumps(plan))
    guide_to_sensor = pose([0.0, 20.0, 0.0], [5.0, -3.0, 60.0])
    (folder / "guide.json").write_text(json.dumps({"TipToProbe": guide_to_sensor.tolist(), "rms_mm": 0.1}))
    matrix = " ".join(f"{v:.9g}" for v in guide_to_sensor.ravel())
    (folder / "guide.xml").write_text(f'<PlusConfiguration><CoordinateDefinitions><Transform From="NeedleGuide" '
                                      f'To="Sensor" Matrix="{matrix}"/></CoordinateDefinitions></PlusConfiguration>')
    return {"folder": folder, "reference_to_image": reference_to_image, "reference_to_tracker": reference_to_tracker,
            "entry": entry, "target": target, "guide_to_sensor": guide_to_sensor}
