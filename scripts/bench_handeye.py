"""Benchmark of ``emreg handeye``'s algorithm against its peers on KinHEC sequences (issue 39, section 1).

    PYTHONPATH=. .venv/bin/python scripts/bench_handeye.py [--quick] [--json OUT.json]

Sequences: KinHEC (published Panda, UR5e and iiwa 7 kinematics; eye-to-hand scene = a sensor on the flange and
a fixed field generator), continuous motion (``joint_sinusoid``, 20 s) and move-and-dwell (``joint_waypoints``,
10 stations), each with EM-like noise (Student-t, 3 degrees of freedom, 0.2 mm / 0.1 deg scale) and
(a) synchronous clocks, no wrong poses; (b) a 40 ms clock offset on top of different epochs, 4% wrong poses.

Peers, on the same data in the same run: every method of OpenCV's ``cv2.calibrateHandEye`` (TSAI, PARK, HORAUD,
ANDREFF, DANIILIDIS) and ``cv2.calibrateRobotWorldHandEye`` (SHAH, LI), and every reference solver KinHEC ships
(Shah, Li for A X = Y B; Tsai-Lenz, Park-Martin, Horaud-Dornaika, Daniilidis, Andreff for A X = X B; its RANSAC;
and KinHEC's own pipeline: its cross-correlation clock offset, Shah, its robust (Huber) Levenberg-Marquardt). The
peers have no clock model: they get each tracker sample paired with the robot sample nearest in time after the
epochs are lined up (as if both clocks were set by NTP), so a clock offset stays in their pairs; the KinHEC
pipeline estimates it. They get KinHEC's own keyframe protocol (poses at least 5 deg or 2 cm apart, at most 200).
Before any comparison, every peer is run on noise-free pairs and must recover the truth (a peer wrong on clean data
would mean a wrong frame mapping).

Accuracy: the error of ``SensorToFlange`` at a tool tip 150 mm out (Sensor +z) and of ``TrackerToBase`` at a point
300 mm in front of the tracker (Tracker +z), in mm; time: the solver's wall time (EMReg's includes finding the
clock offset and the outliers). Ratios are EMReg / the best peer on that sequence (below 1: EMReg better).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "Testing" / "Python"))

from handeye_sequences import (  # noqa: E402
    ROBOT_EPOCH_S,
    TRACKER_EPOCH_S,
    HandEyeCase,
    kinhec_case,
    tip_error_mm,
    tracker_point_error_mm,
)

from EMRegModule.core.handeye import calibrate_hand_eye  # noqa: E402

Solver = Callable[[np.ndarray, np.ndarray, HandEyeCase], tuple[np.ndarray, np.ndarray]]


def _inverse(poses: np.ndarray) -> np.ndarray:
    out = np.tile(np.eye(4), (len(poses), 1, 1)) if poses.ndim == 3 else np.eye(4)
    rotation_t = np.swapaxes(poses[..., :3, :3], -1, -2)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -(rotation_t @ poses[..., :3, 3, None])[..., 0]
    return out


def _pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, np.ravel(translation)
    return pose


def _world_from_hand_eye(flange: np.ndarray, tracker: np.ndarray, sensor_to_flange: np.ndarray) -> np.ndarray:
    """``TrackerToBase`` for a hand-eye-only method: the average of ``A_i X inv(B_i)`` (rotations projected)."""
    each = flange @ sensor_to_flange @ _inverse(tracker)
    u, _, vt = np.linalg.svd(each[:, :3, :3].sum(axis=0))
    rotation = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt
    return _pose(rotation, each[:, :3, 3].mean(axis=0))


def _rotations(poses: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray(r, dtype=np.float64) for r in poses[:, :3, :3]]


def _translations(poses: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray(t.reshape(3, 1), dtype=np.float64) for t in poses[:, :3, 3]]


def _opencv_hand_eye(method: int) -> Solver:
    """cv2.calibrateHandEye, eye-in-hand form: the EM sensor on the flange is the "camera", the field generator its
    "target": gripper2base = FlangeToBase, target2cam = TrackerToSensor -> cam2gripper = SensorToFlange."""
    def solve(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        target2cam = _inverse(tracker)
        rotation, translation = cv2.calibrateHandEye(_rotations(flange), _translations(flange),
                                                     _rotations(target2cam), _translations(target2cam), method=method)
        sensor_to_flange = _pose(rotation, translation)
        return sensor_to_flange, _world_from_hand_eye(flange, tracker, sensor_to_flange)
    return solve


def _opencv_robot_world(method: int) -> Solver:
    """cv2.calibrateRobotWorldHandEye: world2cam = TrackerToSensor, base2gripper = BaseToFlange -> base2world =
    BaseToTracker (Y inverted) and gripper2cam = FlangeToSensor (X inverted)."""
    def solve(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        world2cam, base2gripper = _inverse(tracker), _inverse(flange)
        r_b2w, t_b2w, r_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(
            _rotations(world2cam), _translations(world2cam), _rotations(base2gripper), _translations(base2gripper),
            method=method)
        return _inverse(_pose(r_g2c, t_g2c)), _inverse(_pose(r_b2w, t_b2w))
    return solve


def _metres(poses: np.ndarray) -> np.ndarray:
    out = np.array(poses, dtype=float)
    out[..., :3, 3] /= 1000.0
    return out


def _millimetres(pose: np.ndarray) -> np.ndarray:
    out = np.array(pose, dtype=float)
    out[:3, 3] *= 1000.0
    return out


def _kinhec_axyb(name: str) -> Solver:
    def solve(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
        from kinhec import solvers

        x, y = getattr(solvers, name)(_metres(flange), _metres(tracker))
        return _millimetres(x), _millimetres(y)
    return solve


def _kinhec_axxb(name: str) -> Solver:
    """KinHEC's A X = X B solvers on consecutive keyframe motions (its protocol)."""
    def solve(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
        from kinhec import solvers

        a, b = _metres(flange), _metres(tracker)
        motion_a = _inverse(a[:-1]) @ a[1:]
        motion_b = _inverse(b[:-1]) @ b[1:]
        x = _millimetres(getattr(solvers, name)(motion_a, motion_b))
        return x, _world_from_hand_eye(flange, tracker, x)
    return solve


def _kinhec_ransac(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
    """KinHEC's robust A X = X B: RANSAC over consecutive keyframe motions (Park-Martin), then its Huber LM."""
    from kinhec import solvers

    a, b = _metres(flange), _metres(tracker)
    x, _ = solvers.ransac_axxb(_inverse(a[:-1]) @ a[1:], _inverse(b[:-1]) @ b[1:], np.random.default_rng(0))
    x = _millimetres(x)
    return x, _world_from_hand_eye(flange, tracker, x)


def _kinhec_pipeline(flange: np.ndarray, tracker: np.ndarray, case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
    """KinHEC's own chain: its angular-speed cross-correlation offset, the robot interpolated there, keyframes,
    Shah, then its robust (Huber) LM refinement. Gets the raw streams (epochs lined up), not the naive pairs."""
    from kinhec import motions, se3, solvers

    robot_t, tracker_t = case.robot_time_s - ROBOT_EPOCH_S, case.tracker_time_s - TRACKER_EPOCH_S
    robot_m, tracker_m = _metres(case.flange_to_base), _metres(case.sensor_to_tracker)
    offset, _ = solvers.estimate_time_offset(robot_t, robot_m, tracker_t, tracker_m, max_offset_s=0.5)
    inside = (tracker_t - offset >= robot_t[0]) & (tracker_t - offset <= robot_t[-1])
    a = se3.interpolate_poses(robot_t, robot_m, tracker_t[inside] - offset)
    b = tracker_m[inside]
    keep = motions.select_keyframes(a)
    x, y = solvers.shah(a[keep], b[keep])
    x, y = solvers.refine_lm_axyb(a[keep], b[keep], x, y, loss="huber")
    return _millimetres(x), _millimetres(y)


def peers() -> dict[str, Solver]:
    import cv2

    table: dict[str, Solver] = {f"cv2.HE.{n}": _opencv_hand_eye(getattr(cv2, f"CALIB_HAND_EYE_{n}"))
                                for n in ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")}
    table.update({f"cv2.RWHE.{n}": _opencv_robot_world(getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{n}"))
                  for n in ("SHAH", "LI")})
    table.update({"kinhec.shah": _kinhec_axyb("shah"), "kinhec.li_kronecker": _kinhec_axyb("li_kronecker"),
                  "kinhec.xcorr+shah+LM": _kinhec_pipeline, "kinhec.ransac_axxb": _kinhec_ransac})
    table.update({f"kinhec.{n}": _kinhec_axxb(n) for n in ("tsai_lenz", "park_martin", "horaud_dornaika",
                                                          "daniilidis", "andreff")})
    return table


def naive_pairs(case: HandEyeCase) -> tuple[np.ndarray, np.ndarray]:
    """What a peer without a clock model gets: each tracker sample with the robot sample nearest in time once the
    epochs are lined up (any clock offset stays), then KinHEC's keyframes (5 deg or 2 cm apart, at most 200)."""
    from kinhec import motions

    robot_t, tracker_t = case.robot_time_s - ROBOT_EPOCH_S, case.tracker_time_s - TRACKER_EPOCH_S
    after = np.clip(np.searchsorted(robot_t, tracker_t), 1, len(robot_t) - 1)
    nearest = np.where(np.abs(robot_t[after - 1] - tracker_t) <= np.abs(robot_t[after] - tracker_t), after - 1, after)
    flange = case.flange_to_base[nearest]
    keep = motions.select_keyframes(_metres(flange))
    return flange[keep], case.sensor_to_tracker[keep]


def check_peers_on_clean_data(table: dict[str, Solver]) -> None:
    """Every peer must recover the truth from noise-free pairs: else the frame mapping is wrong."""
    for robot in ("panda", "ur", "iiwa"):
        case = kinhec_case(robot, "joint_sinusoid", seed=50, noise=False, time_offset_s=0.0, duration_s=10.0)
        from kinhec import motions

        keep = motions.select_keyframes(_metres(case.true_flange_to_base))
        for name, solve in table.items():
            if name == "kinhec.xcorr+shah+LM":
                continue  # works on the streams, not on pairs
            x, y = solve(case.true_flange_to_base[keep], case.sensor_to_tracker[keep], case)
            tip, point = tip_error_mm(x, case.sensor_to_flange), tracker_point_error_mm(y, case.tracker_to_base)
            if not (tip < 1e-3 and point < 1e-2):
                raise SystemExit(f"peer {name} is wrong on noise-free {robot} data (tip {tip:.3g} mm, tracker point "
                                 f"{point:.3g} mm): the frame mapping is wrong")
    print("clean-data check: every peer recovers the truth on noise-free Panda, UR5e and iiwa pairs "
          "(tool tip < 1e-3 mm, tracker point < 1e-2 mm)\n")


def run_case(case: HandEyeCase, table: dict[str, Solver]) -> dict:
    """EMReg and every peer on one sequence: errors (mm) and times (s)."""
    results = {}
    start = time.perf_counter()
    mine = calibrate_hand_eye(case.robot_time_s, case.flange_to_base, case.tracker_time_s, case.sensor_to_tracker)
    elapsed = time.perf_counter() - start
    results["EMReg"] = {"tip_mm": tip_error_mm(mine.sensor_to_flange, case.sensor_to_flange),
                        "point_mm": tracker_point_error_mm(mine.tracker_to_base, case.tracker_to_base),
                        "time_s": elapsed, "offset_error_ms": 1000 * (mine.time_offset_s - case.time_offset_s)}
    flange, tracker = naive_pairs(case)
    for name, solve in table.items():
        start = time.perf_counter()
        try:
            x, y = solve(flange, tracker, case)
            tip, point = tip_error_mm(x, case.sensor_to_flange), tracker_point_error_mm(y, case.tracker_to_base)
        except Exception:  # a peer that fails on a sequence scores infinitely wrong there
            tip = point = float("inf")
        results[name] = {"tip_mm": tip, "point_mm": point, "time_s": time.perf_counter() - start}
    return results


CONDITIONS = {"sync": {"time_offset_s": 0.0, "outlier_fraction": 0.0},
              "offset40ms+outliers4%": {"time_offset_s": 0.040, "outlier_fraction": 0.04}}


def _best(results: dict, key: str) -> tuple[str, dict]:
    name = min((n for n in results if n != "EMReg"), key=lambda n: results[n][key])
    return name, results[name]


def _row(label: str, results: dict) -> tuple[str, dict]:
    mine = results["EMReg"]
    tip_name, tip_peer = _best(results, "tip_mm")
    point_name, point_peer = _best(results, "point_mm")
    line = (f"| {label} | {mine['tip_mm']:.3f} | {tip_peer['tip_mm']:.3f} ({tip_name}) | "
            f"{mine['tip_mm'] / tip_peer['tip_mm']:.2f} | {mine['point_mm']:.3f} | {point_peer['point_mm']:.3f} "
            f"({point_name}) | {mine['point_mm'] / point_peer['point_mm']:.2f} | {mine['time_s']:.2f} | "
            f"{tip_peer['time_s']:.4f} | {mine['time_s'] / tip_peer['time_s']:.0f} | {mine['offset_error_ms']:+.2f} |")
    return line, {"tip_ratio": mine["tip_mm"] / tip_peer["tip_mm"],
                  "point_ratio": mine["point_mm"] / point_peer["point_mm"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="Panda only (a smoke run)")
    parser.add_argument("--json", type=Path, default=None, help="write every result to this JSON file")
    args = parser.parse_args(argv)
    table = peers()
    check_peers_on_clean_data(table)
    robots = ("panda",) if args.quick else ("panda", "ur", "iiwa")
    print("Peers pair each tracker sample with the nearest robot sample after lining up the epochs (no clock "
          "model: a clock offset stays in their pairs), on KinHEC's keyframes; kinhec.xcorr+shah+LM estimates the "
          "offset itself. Errors in mm: tool tip 150 mm out (SensorToFlange), point 300 mm in front of the tracker "
          "(TrackerToBase). Ratio = EMReg / best peer (below 1: EMReg better). Time: EMReg's whole solve (offset, "
          "outliers, refinement) against the best peer's solver call.\n")
    print("| sequence | EMReg tip | best peer tip | ratio | EMReg pt300 | best peer pt300 | ratio | EMReg s | "
          "peer s | time ratio | EMReg offset err ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    everything, ratios = {}, []
    for robot in robots:
        for family, label in (("joint_sinusoid", "continuous"), ("joint_waypoints", "dwell")):
            for condition, options in CONDITIONS.items():
                case = kinhec_case(robot, family, seed=21, **options)
                results = run_case(case, table)
                name = f"{robot} {label} {condition}"
                line, ratio = _row(name, results)
                print(line, flush=True)
                everything[name], ratios = results, ratios + [ratio]
    _summary(everything, ratios)
    if args.json:
        args.json.write_text(json.dumps(everything, indent=1))
    return 0


def _summary(everything: dict, ratios: list[dict]) -> None:
    methods = list(next(iter(everything.values())))
    print("\nMedian over the sequences, per method (tip mm / pt300 mm), and how many sequences each fails "
          "(tip error above 0.5 mm):\n")
    print("| method | median tip mm | median pt300 mm | sequences with tip > 0.5 mm |")
    print("|---|---|---|---|")
    for method in methods:
        tips = np.array([everything[s][method]["tip_mm"] for s in everything])
        points = np.array([everything[s][method]["point_mm"] for s in everything])
        print(f"| {method} | {np.median(tips):.3f} | {np.median(points):.3f} | {np.count_nonzero(tips > 0.5)} "
              f"of {len(tips)} |")
    worst_tip = max(r["tip_ratio"] for r in ratios)
    worst_point = max(r["point_ratio"] for r in ratios)
    print(f"\nEMReg / best peer, worst sequence: tool tip {worst_tip:.2f}, tracker point {worst_point:.2f} "
          f"({'at or ahead of every peer' if max(worst_tip, worst_point) <= 1.0 else 'behind a peer somewhere'})")


if __name__ == "__main__":
    sys.exit(main())
