"""``emreg handeye`` (issue 39, section 1) on recordings with known truth from KinHEC (published Panda, UR and
iiwa kinematics, a generator we did not write), made into what a user has: the robot's log as a TUM file or a PLUS
sequence file, the tracker's recording as EMReg CSV or a PLUS sequence file, with heavy-tailed EM noise, a clock
offset on top of different epochs, and wrong poses (glitches, distorted bursts). Then the refusals: motion that
cannot determine the answer (exit 3) and bad input (exit 2), with nothing written.

Tolerances: the issue asks for a tool-tip error (150 mm out) of at most 0.5 mm at EM noise; EMReg measures
0.01-0.1 mm on these recordings, so the tests hold it to 0.25 mm (a regression shows), and to its own prediction.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.core.handeye import motion_spread, solve_ax_yb
from EMRegModule.io.itk_transform import read_slicer_frame_transform
from EMRegModule.io.tum import read_tum, write_tum
from EMRegModule.pipeline.robot_live import read_target

sys.path.insert(0, str(Path(__file__).parent))
from handeye_sequences import (  # noqa: E402
    kinhec_case,
    pose,
    rotation_error_deg,
    tip_error_mm,
    tracker_point_error_mm,
    write_targeting_inputs,
)

ROOT = Path(__file__).resolve().parents[2]
KEYS = {"SensorToFlange", "TrackerToBase", "time_offset_s", "residuals", "frames", "uncertainty"}


def _check_calibration(out: Path, case, tip_mm: float = 0.25) -> dict:
    """The answer against KinHEC's truth: tool tip 150 mm out, rotation, a point 300 mm before the tracker, the
    clock offset; the prediction honest; the Slicer transforms the same as the JSON."""
    document = json.loads((out / "robot_calibration.json").read_text())
    assert KEYS <= set(document)
    sensor_to_flange, tracker_to_base = np.array(document["SensorToFlange"]), np.array(document["TrackerToBase"])
    tip = tip_error_mm(sensor_to_flange, case.sensor_to_flange)
    assert tip <= tip_mm
    assert tip <= 5.0 * document["uncertainty"]["tool_tip_rms_mm"] + 0.02
    assert rotation_error_deg(sensor_to_flange, case.sensor_to_flange) <= 0.05
    assert tracker_point_error_mm(tracker_to_base, case.tracker_to_base) <= 0.6
    assert abs(document["time_offset_s"] - case.time_offset_s) <= 0.002
    np.testing.assert_allclose(read_slicer_frame_transform(out / "SensorToFlange.h5"), sensor_to_flange, atol=1e-6)
    np.testing.assert_allclose(read_slicer_frame_transform(out / "TrackerToBase.h5"), tracker_to_base, atol=1e-6)
    return document


@pytest.fixture(scope="module")
def continuous_case():
    return kinhec_case("panda", "joint_sinusoid", seed=11, outlier_fraction=0.04)


def test_continuous_motion_with_clock_offset_and_wrong_poses(continuous_case, tmp_path, capsys):
    """Panda, continuous motion, 4% wrong poses, the flange sensor on port 3 of a CSV that also holds a reference
    sensor: --sensor picks it; every injected glitch is rejected with a reason."""
    case = continuous_case
    robot, tracker = case.write_recordings(tmp_path)
    code = main(["handeye", "--robot-poses", str(robot), "--tracker", str(tracker), "--sensor", "3", "--out",
                 str(tmp_path / "out")])
    assert code == 0, capsys.readouterr().err
    document = _check_calibration(tmp_path / "out", case)
    rejected = {frame["index"] for frame in document["frames"]["rejected_frames"]}
    assert set(np.nonzero(case.outlier)[0]) <= rejected
    assert all(frame["reason"] for frame in document["frames"]["rejected_frames"])
    assert len(rejected) <= 3 * np.count_nonzero(case.outlier)  # heavy tails cost some good frames, not many
    assert "robot_calibration.json" in capsys.readouterr().out


def test_move_and_dwell_from_plus_sequence(tmp_path, capsys):
    """iiwa, move and dwell, 3% wrong poses, the tracker's recording a PLUS sequence file with one transform: the
    dwells are found and the answer is as good."""
    case = kinhec_case("iiwa", "joint_waypoints", seed=12, outlier_fraction=0.03)
    case.write_tum(tmp_path / "robot.tum")
    case.write_sequence(tmp_path / "tracker.seq.mha")
    code = main(["handeye", "--robot-poses", str(tmp_path / "robot.tum"), "--tracker",
                 str(tmp_path / "tracker.seq.mha"), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 0, capsys.readouterr().err
    document = _check_calibration(tmp_path / "out", case, tip_mm=0.1)
    assert document["frames"]["dwells"] >= 5
    assert document["frames"]["still"] >= 100


def test_robot_log_as_plus_sequence_file_in_a_process(tmp_path):
    """UR5e, continuous, the robot's log a PLUS sequence file (FlangeToBase), run as a user runs emreg."""
    case = kinhec_case("ur", "joint_sinusoid", seed=13, outlier_fraction=0.02)
    case.write_sequence(tmp_path / "robot.seq.mha", name="FlangeToBase", robot=True)
    case.write_csv(tmp_path / "tracker.csv")
    result = subprocess.run([sys.executable, "-m", "EMRegModule", "handeye", "--robot-poses",
                             str(tmp_path / "robot.seq.mha"), "--tracker", str(tmp_path / "tracker.csv"), "--out",
                             str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    _check_calibration(tmp_path / "out", case)


def test_closed_form_recovers_noise_free_truth():
    """The closed-form start is exact on noise-free pose pairs (KinHEC's truth at the tracker's instants)."""
    case = kinhec_case("panda", "joint_sinusoid", seed=14, noise=False, duration_s=6.0)
    sensor_to_flange, tracker_to_base = solve_ax_yb(case.true_flange_to_base, case.sensor_to_tracker)
    np.testing.assert_allclose(sensor_to_flange, case.sensor_to_flange, atol=1e-6)
    np.testing.assert_allclose(tracker_to_base, case.tracker_to_base, atol=1e-5)


@pytest.mark.parametrize(("family_params", "duration_s", "message"), [
    ({"joints": [6]}, 20.0, "about one axis only"),
    ({"amplitude_frac": 0.01}, 20.0, "too small a range"),
    ({}, 0.4, "too few frames"),
])
def test_motion_that_cannot_determine_the_answer_is_refused(tmp_path, capsys, family_params, duration_s, message):
    """Exit 3 and one line, nothing written: the wrist's last joint alone (one axis), a tiny motion, 16 frames."""
    case = kinhec_case("panda", "joint_sinusoid", seed=15, family_params=family_params, duration_s=duration_s)
    case.write_tum(tmp_path / "robot.tum")
    case.write_csv(tmp_path / "tracker.csv")
    code = main(["handeye", "--robot-poses", str(tmp_path / "robot.tum"), "--tracker", str(tmp_path / "tracker.csv"),
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 3
    assert message in err and len(err.strip().splitlines()) == 1
    assert list((tmp_path / "out").iterdir()) == []


def test_recordings_of_different_motions_are_refused(continuous_case, tmp_path, capsys):
    """A robot log and a tracker recording that do not belong together: exit 3, not a calibration."""
    other = kinhec_case("panda", "joint_sinusoid", seed=16)
    continuous_case.write_tum(tmp_path / "robot.tum")
    other.write_csv(tmp_path / "tracker.csv")
    code = main(["handeye", "--robot-poses", str(tmp_path / "robot.tum"), "--tracker", str(tmp_path / "tracker.csv"),
                 "--out", str(tmp_path / "out")])
    assert code == 3, capsys.readouterr().err
    assert not (tmp_path / "out" / "robot_calibration.json").exists()


def _bad_tum(path: Path, text: str) -> None:
    path.write_text("# timestamp tx ty tz qx qy qz qw\n0.0 0.1 0.2 0.3 0 0 0 1\n" + text)


@pytest.mark.parametrize(("robot_text", "sensor", "message"), [
    ("0.1 0.1 0.2 0.3 0 0 1\n", "3", "line 3: 7 fields"),
    ("0.1 0.1 0.2 abc 0 0 0 1\n", "3", "line 3: holds a non-numeric value"),
    ("0.1 100 200 300 0 0 0 1\n", "3", "in millimetres"),
    ("0.1 0.1 0.2 0.3 0 0 0 2\n", "3", "length 2"),
    ("0.05 0.1 0.2 0.3 0 0 0 1\n-0.1 0.1 0.2 0.3 0 0 0 1\n", "3", "the time goes back"),
    ("0.1 0.1 0.2 0.3 0 0 0 1\n", "7", "no sensor '7'"),
    ("0.1 0.1 0.2 0.3 0 0 0 1\n", None, "choose the flange's sensor"),
])
def test_bad_input_is_one_line_and_exit_2(continuous_case, tmp_path, capsys, robot_text, sensor, message):
    """Malformed TUM lines, a missing sensor, an ambiguous one (no --sensor for a file with two): exit 2, one line
    naming the file, nothing written."""
    _bad_tum(tmp_path / "robot.tum", robot_text)
    continuous_case.write_csv(tmp_path / "tracker.csv", port=3, with_reference=True)
    argv = ["handeye", "--robot-poses", str(tmp_path / "robot.tum"), "--tracker", str(tmp_path / "tracker.csv"),
            "--out", str(tmp_path / "out")] + (["--sensor", sensor] if sensor else [])
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "robot_calibration.json").exists()


def test_tum_round_trip_and_motion_spread(continuous_case, tmp_path):
    """write_tum / read_tum keep poses to the micrometre (metres on file, mm in EMReg); the motion's spread is
    that of the flange."""
    write_tum(tmp_path / "t.tum", continuous_case.robot_time_s, continuous_case.flange_to_base)
    time_s, poses = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(time_s, continuous_case.robot_time_s, atol=1e-6)
    np.testing.assert_allclose(poses, continuous_case.flange_to_base, atol=1e-5)
    spread, second = motion_spread(poses)
    assert spread > 20.0 and second > 3.0


# --- emreg robot-target (issue 39, section 2) ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def targeting_case(continuous_case, tmp_path_factory):
    """A hand-eye calibration made by emreg handeye from the KinHEC recording, a registration, the reference
    sensor's recording (300 mm before the field generator), a plan and a needle guide, with the truth beside."""
    folder = tmp_path_factory.mktemp("target")
    robot, tracker = continuous_case.write_recordings(folder)
    assert main(["handeye", "--robot-poses", str(robot), "--tracker", str(tracker), "--sensor", "3", "--out",
                 str(folder / "calib"), "--quiet"]) == 0
    return {**write_targeting_inputs(folder), "case": continuous_case}


def _target_args(folder: Path, tool: str = "guide.json", plan: str = "plan.mrk.json", out: str = "out") -> list[str]:
    return ["robot-target", "--registration", str(folder / "reg" / "registration.json"), "--robot-calibration",
            str(folder / "calib" / "robot_calibration.json"), "--reference", str(folder / "reference.csv"),
            "--plan", str(folder / plan), "--tool", str(folder / tool), "--out", str(folder / out)]


@pytest.mark.parametrize("tool", ["guide.json", "guide.xml"])
def test_robot_target_puts_the_guide_on_the_plan(targeting_case, capsys, tool):
    """The flange pose, applied with the TRUE hand-eye and robot-world transforms: the guide's exit lands on Entry,
    its axis along Entry -> Target and the needle tip at the planned depth on Target, within the predicted error."""
    folder, case = targeting_case["folder"], targeting_case["case"]
    out = f"out-{tool}"
    assert main(_target_args(folder, tool, out=out)) == 0, capsys.readouterr().err
    document = json.loads((folder / out / "robot_target.json").read_text())
    flange_to_base = np.array(document["FlangeToBase"])
    guide_to_base = flange_to_base @ case.sensor_to_flange @ targeting_case["guide_to_sensor"]
    image_to_base = case.tracker_to_base @ targeting_case["reference_to_tracker"] @ np.linalg.inv(
        targeting_case["reference_to_image"])
    guide_in_image = np.linalg.inv(image_to_base) @ guide_to_base
    entry, target = targeting_case["entry"], targeting_case["target"]
    axis = (target - entry) / np.linalg.norm(target - entry)
    exit_error = np.linalg.norm(guide_in_image[:3, 3] - entry)
    tip = guide_in_image[:3, 3] + document["depth_mm"] * guide_in_image[:3, 2]
    predicted = document["predicted_error_mm"]["total"]
    angle = np.degrees(np.arccos(np.clip(guide_in_image[:3, 2] @ axis, -1, 1)))
    print(f"exit {exit_error:.3f} mm, tip {np.linalg.norm(tip - target):.3f} mm, axis {angle:.4f} deg, "
          f"predicted {predicted:.3f} mm")
    assert exit_error <= 3.0 * predicted
    assert np.linalg.norm(tip - target) <= 3.0 * predicted
    assert angle <= 0.2
    assert 0.2 <= predicted <= 1.0  # the registration's 0.2 mm, the guide's 0.1 mm, the hand-eye's share
    # emreg robot-go takes all it needs from the file alone (the calibration, the guide, the registration, the plan)
    plan = read_target(str(folder / out / "robot_target.json"))
    assert np.allclose(plan["NeedleGuideToSensor"], targeting_case["guide_to_sensor"], atol=1e-9)
    assert np.allclose(plan["entry"], entry) and np.allclose(plan["target"], target)


def test_robot_target_with_a_live_reference(targeting_case, capsys):
    """The reference sensor from a live source (the replay device of the same recording): the same flange pose."""
    folder = targeting_case["folder"]
    args = _target_args(folder, out="live")
    args[args.index("--reference") + 1] = f"replay:{folder / 'reference.csv'}"
    assert main(args) == 0, capsys.readouterr().err
    live = json.loads((folder / "live" / "robot_target.json").read_text())
    assert main(_target_args(folder, out="recorded")) == 0
    recorded = json.loads((folder / "recorded" / "robot_target.json").read_text())
    np.testing.assert_allclose(live["FlangeToBase"], recorded["FlangeToBase"], atol=0.05)


def test_robot_target_refusals(targeting_case, capsys):
    """A plan beyond the tracker's volume: exit 3; a live source without the reference sensor: exit 2."""
    folder = targeting_case["folder"]
    far = json.loads((folder / "plan.mrk.json").read_text())
    for point in far["markups"][0]["controlPoints"]:
        point["position"] = (np.array(point["position"]) + [0.0, 0.0, 2000.0]).tolist()
    (folder / "far.mrk.json").write_text(json.dumps(far))
    assert main(_target_args(folder, plan="far.mrk.json", out="far")) == 3
    assert "outside the tracker's volume" in capsys.readouterr().err
    args = _target_args(folder, out="absent") + ["--reference-sensor", "4"]
    args[args.index("--reference") + 1] = f"replay:{folder / 'reference.csv'}"
    assert main(args) == 2
    assert "valid samples of the reference sensor (port 4)" in capsys.readouterr().err
    assert not (folder / "far" / "robot_target.json").exists()


def test_robot_target_with_the_robots_model(targeting_case, capsys):
    """``[robot] model = "panda"`` (the KinHEC recording's robot), a plan where the recorded flange once held the
    guide: the flange pose comes with the joint angles that reach it (forward kinematics of them is the flange
    pose) and their margin to the limits; a plan beyond the arm's reach is refused with one line, exit 3, before
    the tracker's volume is looked at."""
    from EMRegModule.core.robot_kinematics import robot_model

    folder, case = targeting_case["folder"], targeting_case["case"]
    guide = case.true_flange_to_base[len(case.true_flange_to_base) // 2] @ case.sensor_to_flange @ \
        targeting_case["guide_to_sensor"]
    base_to_image = targeting_case["reference_to_image"] @ np.linalg.inv(
        case.tracker_to_base @ targeting_case["reference_to_tracker"])
    plan = json.loads((folder / "plan.mrk.json").read_text())
    for point, depth in zip(plan["markups"][0]["controlPoints"], (0.0, 60.0), strict=True):
        point["position"] = (base_to_image @ np.append(guide[:3, 3] + depth * guide[:3, 2], 1.0))[:3].tolist()
    (folder / "reachable.mrk.json").write_text(json.dumps(plan))
    settings = folder / "panda.toml"
    settings.write_text('[robot]\nmodel = "panda"\nmax_tracker_distance_mm = 5000.0\n', encoding="utf-8")
    assert main(_target_args(folder, plan="reachable.mrk.json", out="panda") + ["--settings", str(settings)]) == 0, \
        capsys.readouterr().err
    document = json.loads((folder / "panda" / "robot_target.json").read_text())
    joints = np.array(document["joints_rad"])
    np.testing.assert_allclose(robot_model("panda").forward(joints), document["FlangeToBase"], atol=1e-2)
    assert document["robot_model"] == "panda" and 0.0 < document["joint_limit_margin"] <= 1.0
    for point in plan["markups"][0]["controlPoints"]:
        point["position"] = (np.array(point["position"]) + [0.0, 0.0, 2000.0]).tolist()
    (folder / "unreachable.mrk.json").write_text(json.dumps(plan))
    assert main(_target_args(folder, plan="unreachable.mrk.json", out="far-panda") + ["--settings", str(settings)]) == 3
    error = capsys.readouterr().err
    assert "PANDA cannot reach the plan" in error and len(error.strip().splitlines()) == 1


def test_the_roll_keeps_the_flange_nearest_its_preferred_orientation():
    """best_roll's closed form is the best of every roll about the guide's axis."""
    from scipy.spatial.transform import Rotation

    from EMRegModule.core.robot_target import best_roll

    rng = np.random.default_rng(5)
    guide, guide_to_flange, preferred = Rotation.random(3, random_state=rng).as_matrix()
    rolls = np.radians(np.arange(0.0, 360.0, 0.5))
    distance = [np.linalg.norm(guide @ Rotation.from_rotvec([0, 0, r]).as_matrix() @ guide_to_flange.T - preferred)
                for r in rolls]
    roll = best_roll(guide, guide_to_flange, preferred)
    best = guide @ Rotation.from_rotvec([0, 0, roll]).as_matrix() @ guide_to_flange.T
    assert np.linalg.norm(best - preferred) <= min(distance) + 1e-9


def test_slicer_reads_the_calibration_transforms_as_they_are(slicer_core, tmp_path):
    """3D Slicer's own transform storage node reads SensorToFlange.h5 / TrackerToBase.h5 as a linear transform
    whose "to parent" matrix is exactly the calibration's (robot and tracker frames are not converted)."""
    import slicer.util

    from EMRegModule.io.itk_transform import write_slicer_frame_transform

    a_to_b = pose([20.0, -35.0, 110.0], [-41.4, 26.3, 80.1])
    write_slicer_frame_transform(tmp_path / "SensorToFlange.h5", a_to_b)
    scene = slicer_core.scene
    transform = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "read")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(tmp_path / "SensorToFlange.h5"))
    assert storage.ReadData(transform) == 1
    assert transform.IsLinear()
    np.testing.assert_allclose(slicer.util.arrayFromTransformMatrix(transform), a_to_b, atol=1e-6)


def test_a_robot_log_shorter_than_the_tracker_recording_and_with_a_gap():
    """The robot's log covers the middle of the tracker's recording and misses half a second: the frames without
    a robot pose are left out with that reason, the answer stays as good (150 ms clock offset)."""
    from EMRegModule.core.handeye import calibrate_hand_eye

    case = kinhec_case("panda", "joint_sinusoid", seed=61, outlier_fraction=0.03, time_offset_s=0.15)
    n = len(case.robot_time_s)
    keep = np.zeros(n, dtype=bool)
    keep[int(0.2 * n):int(0.8 * n)] = True
    keep[n // 2:n // 2 + 100] = False
    result = calibrate_hand_eye(case.robot_time_s[keep], case.flange_to_base[keep], case.tracker_time_s,
                                case.sensor_to_tracker)
    assert tip_error_mm(result.sensor_to_flange, case.sensor_to_flange) <= 0.25
    assert abs(result.time_offset_s - case.time_offset_s) <= 0.002
    no_pose = [r for r in result.rejected if r.reason.startswith("no robot pose")]
    assert len(no_pose) >= 0.4 * len(case.tracker_time_s)
    assert not set(result.used) & {r.index for r in result.rejected}


def test_the_robot_log_is_smoothed_where_noise_dominates_and_kept_where_it_curves():
    """A 200 Hz log of a smooth motion with white noise in its translation comes out nearer the truth; a
    noise-free log of a fast curving motion comes out as it was (the cross-validation picks a narrow window)."""
    from EMRegModule.core.handeye_sync import smooth_poses
    from EMRegModule.core.transforms import rotation_matrices

    time_s = np.arange(0.0, 5.0, 0.005)
    truth = np.tile(np.eye(4), (len(time_s), 1, 1))
    truth[:, :3, 3] = 100.0 * np.column_stack([np.sin(time_s), np.cos(0.7 * time_s), 0.3 * time_s])
    truth[:, :3, :3] = rotation_matrices(0.5 * np.column_stack([np.sin(time_s), np.cos(time_s), time_s / 5]))
    rng = np.random.default_rng(3)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(0.0, 0.2, (len(time_s), 3))
    smoothed, width = smooth_poses(time_s, noisy)
    before = np.sqrt(np.mean(np.sum((noisy - truth)[:, :3, 3] ** 2, axis=1)))
    after = np.sqrt(np.mean(np.sum((smoothed - truth)[:, :3, 3] ** 2, axis=1)))
    assert width[1] >= 8 and after < 0.4 * before
    fast = truth.copy()
    fast[:, :3, 3] = 100.0 * np.column_stack([np.sin(8 * time_s), np.cos(8 * time_s), time_s])
    kept, width = smooth_poses(time_s, fast)
    assert width[1] == 2 and np.max(np.abs(kept - fast)[:, :3, 3]) < 0.01


@pytest.mark.parametrize("robot, family", [("ur", "joint_sinusoid"), ("iiwa", "joint_waypoints")])
def test_the_predicted_uncertainty_matches_the_error_over_seeds(robot, family):
    """Over several recordings the tool-tip and tracker-point errors are as large as predicted (their RMS ratio to
    the predicted RMS near 1: neither optimistic nor pessimistic)."""
    from EMRegModule.core.handeye import calibrate_hand_eye

    tip_ratio, point_ratio = [], []
    for seed in range(31, 37):
        case = kinhec_case(robot, family, seed=seed, outlier_fraction=0.02)
        result = calibrate_hand_eye(case.robot_time_s, case.flange_to_base, case.tracker_time_s,
                                    case.sensor_to_tracker)
        tip_ratio.append(tip_error_mm(result.sensor_to_flange, case.sensor_to_flange) / result.tool_tip_rms_mm)
        point_ratio.append(tracker_point_error_mm(result.tracker_to_base, case.tracker_to_base)
                           / result.tracker_point_rms_mm)
    tip, point = np.sqrt(np.mean(np.square(tip_ratio))), np.sqrt(np.mean(np.square(point_ratio)))
    print(f"\n{robot} {family}: measured / predicted RMS, tool tip {tip:.2f}, tracker point {point:.2f}")
    assert 0.6 < tip < 1.6 and 0.6 < point < 1.6


def test_the_predicted_error_at_the_target_matches_the_needle_tips_error_over_seeds():
    """robot-target's prediction is honest: over KinHEC recordings of several seeds, the needle tip where the flange
    pose truly puts it (the true X and Y, the robot's positioning off by its RMS error in a random direction)
    is as far from the target as predicted (the RMS ratio near 1), the hand-eye term through X's and Y's full
    covariance, the robot's own term from its positioning error."""
    from scipy.spatial.transform import Rotation

    from EMRegModule.core.handeye import calibrate_hand_eye
    from EMRegModule.core.robot_target import robot_target

    rng = np.random.default_rng(5)
    guide_to_sensor = pose([0.0, 20.0, 0.0], [5.0, -3.0, 60.0])
    reference_to_tracker = pose([5.0, 30.0, -10.0], [20.0, -30.0, 300.0])
    positioning = (0.1, 0.09)  # mm, degrees RMS: what franky-sim's controller leaves
    ratios, hand_eye_ratios = [], []

    def tip_guide(depth_mm: float) -> np.ndarray:
        return np.array([0.0, 0.0, depth_mm, 1.0])

    for seed in range(41, 49):
        case = kinhec_case("panda", "joint_sinusoid", seed=seed, outlier_fraction=0.02)
        result = calibrate_hand_eye(case.robot_time_s, case.flange_to_base, case.tracker_time_s,
                                    case.sensor_to_tracker)
        # a plan where the flange once held the guide, 70 mm deep, the registration exact (reference = image)
        guide = case.true_flange_to_base[rng.integers(len(case.true_flange_to_base))] @ case.sensor_to_flange @ \
            guide_to_sensor
        base_to_image = np.linalg.inv(case.tracker_to_base @ reference_to_tracker)
        entry, target = (base_to_image @ np.array([[*guide[:3, 3], 1.0],
                                                   [*(guide[:3, 3] + 70.0 * guide[:3, 2]), 1.0]]).T).T[:, :3]
        answer = robot_target(entry, target, np.eye(4), reference_to_tracker, result.tracker_to_base,
                              result.sensor_to_flange, guide_to_sensor, result.covariance, 0.0,
                              positioning_rms=positioning)
        reached = answer.flange_to_base.copy()
        axis = rng.normal(size=3)
        reached[:3, :3] = reached[:3, :3] @ Rotation.from_rotvec(
            axis / np.linalg.norm(axis) * np.radians(positioning[1]) * rng.normal(0.0, 1.0)).as_matrix()
        reached[:3, 3] += rng.normal(0.0, positioning[0] / np.sqrt(3.0), 3)
        tip = reached @ case.sensor_to_flange @ guide_to_sensor @ tip_guide(answer.depth_mm)
        target_base = case.tracker_to_base @ reference_to_tracker @ np.append(target, 1.0)
        ratios.append(np.linalg.norm((tip - target_base)[:3]) / answer.predicted_error_mm["total"])
        tip_hand_eye = answer.flange_to_base @ case.sensor_to_flange @ guide_to_sensor @ tip_guide(answer.depth_mm)
        hand_eye_ratios.append(np.linalg.norm((tip_hand_eye - target_base)[:3]) / answer.predicted_error_mm["hand_eye"])
    ratio, hand_eye = (float(np.sqrt(np.mean(np.square(r)))) for r in (ratios, hand_eye_ratios))
    print(f"\nneedle tip error / predicted over {len(ratios)} seeds, RMS: {ratio:.2f}; the hand-eye's part alone (the "
          f"robot exactly where sent) / its term: {hand_eye:.2f}")
    assert 0.6 < ratio < 1.5 and 0.5 < hand_eye < 1.6
