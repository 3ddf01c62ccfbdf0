"""Hand-eye and robot-world calibration with the EM tracker: ``FlangeToBase @ SensorToFlange = TrackerToBase @
SensorToTracker`` (the AX = YB form) from a robot's log and a tracker's recording on two clocks.

An EM sensor is fixed to the robot's flange; the field generator stands still beside the robot. The unknowns
are ``SensorToFlange`` (X, hand-eye) and ``TrackerToBase`` (Y, robot-world), both 4x4 in mm, and the clock
offset ``time_offset_s`` with ``t_tracker = t_robot + time_offset_s``. Pure: arrays in, a
:class:`HandEyeResult` out, :class:`~EMRegModule.errors.NoSafeAnswerError` when the motion cannot determine it.

The steps (:func:`calibrate_hand_eye`):

0. the robot's log smoothed (:func:`EMRegModule.core.handeye_sync.smooth_poses`: local quadratics in time, their
   width by cross-validation on the log): a robot logs faster than the tracker, with noise of its own;
1. the clock offset from the angular speeds (:func:`EMRegModule.core.handeye_sync.estimate_clock_offset`); the
   robot's flange pose interpolated at every tracker instant;
2. whether the motion can determine the answer: enough frames, a large enough rotation, rotations about at
   least two non-parallel axes (:func:`motion_spread`);
3. a robust closed-form start: least median of residuals over closed-form solutions (:func:`solve_ax_yb`, a
   Kronecker-product rotation solve and linear translations) of small frame sets spread over the recording, as
   many as make missing an all-good set unlikely (adaptive RANSAC);
4. the offset refined on the calibration residual (a scan around the cross-correlation's answer);
5. a robust nonlinear refinement of X, Y and the offset together, each frame's residual normalised by the
   noise it should have (per axis ``sigma^2 + (speed x jitter)^2``, both sigmas and the tracker's timing jitter
   fitted to how the residuals grow with the flange's speed, so the still frames of dwells count most), the
   frames weighed as under a Student-t (EM noise is heavy-tailed), frames far beyond it rejected with the reason;
6. the covariance of the answer (a sandwich estimate: what the residuals show, not the noise model alone),
   propagated to a tool point (150 mm out by default) and to a point in front of the tracker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from ..errors import EMRegError, NoSafeAnswerError
from ..settings import HandEyeSettings
from .error_model import skew
from .handeye_sync import estimate_clock_offset, interpolate_poses, pose_speeds, prepared_log
from .transforms import rotation_matrices, rotation_vectors

#: A point this far in front of the tracker (its +z, mm) measures the error of ``TrackerToBase``.
TRACKER_POINT_MM = (0.0, 0.0, 300.0)

#: The lever (mm) that turns a rotation residual into a distance when frames are ranked before the noise is
#: known (the default tool tip's distance).
LEVER_MM = 150.0

#: The offset scan around the cross-correlation's answer: half width and step (s).
SCAN_HALF_WIDTH_S = 0.2
SCAN_STEP_S = 0.01

#: The robust start and the offset scan rank their candidates on at most this many frames, spread over the
#: recording.
MOST_SCORED = 400

#: Degrees of freedom of the Student-t the refinement assumes of each frame's residual (4: the robust default of
#: Lange, Little and Taylor 1989; Gaussian noise loses little, heavy-tailed EM noise gains much).
TAIL_DOF = 4.0

#: Frames within this time (s) are taken as sharing errors when the covariance is estimated.
COVARIANCE_BLOCK_S = 0.5

#: Frames with the flange slower than these count as still (mm/s, rad/s), its speed taken over this window (s).
STILL_SPEED_MM_S = 3.0
STILL_SPEED_RAD_S = np.radians(1.0)
STILL_WINDOW_S = 0.3


@dataclass(frozen=True)
class RejectedFrame:
    """A tracker sample not used: its index in the tracker's samples, its time (s, tracker clock), why."""

    index: int
    time_s: float
    reason: str


@dataclass(frozen=True)
class HandEyeResult:
    """The calibration and what backs it.

    ``sensor_to_flange`` (X) and ``tracker_to_base`` (Y): 4x4, mm. ``time_offset_s``: ``t_tracker = t_robot +
    time_offset_s`` (``xcorr_offset_s`` the cross-correlation's estimate, ``correlation`` its peak).
    ``used``: indices of the tracker samples used; ``rotation_residual_deg`` / ``translation_residual_mm``
    theirs (the sensor's pose by the robot against by the tracker, in the base frame). ``still``: how many of
    them the flange was still for, in ``dwells`` still periods. ``covariance``: of the 13 parameters (X's
    rotation vector rad, translation mm; Y's; the offset s). ``tool_tip_mm`` (Sensor frame) and
    ``tracker_point_mm`` (Tracker frame) with the predicted covariance (mm^2) of their place in the base frame.
    """

    sensor_to_flange: np.ndarray
    tracker_to_base: np.ndarray
    time_offset_s: float
    xcorr_offset_s: float
    correlation: float
    used: np.ndarray
    rotation_residual_deg: np.ndarray
    translation_residual_mm: np.ndarray
    rejected: tuple[RejectedFrame, ...]
    still: int
    dwells: int
    noise_rotation_deg: float
    noise_position_mm: float
    rotation_range_deg: float
    second_axis_deg: float
    covariance: np.ndarray
    tool_tip_mm: np.ndarray
    tool_tip_covariance_mm2: np.ndarray
    tracker_point_mm: np.ndarray
    tracker_point_covariance_mm2: np.ndarray
    #: The flange's mean orientation over the frames used (3x3, Base frame): a pose the robot has reached.
    mean_flange_rotation: np.ndarray

    @property
    def time_offset_std_s(self) -> float:
        """Predicted standard deviation of ``time_offset_s`` (s)."""
        return float(np.sqrt(max(self.covariance[12, 12], 0.0)))

    @property
    def tool_tip_rms_mm(self) -> float:
        """Predicted RMS error (mm) of the tool point's place in the flange frame."""
        return float(np.sqrt(max(np.trace(self.tool_tip_covariance_mm2), 0.0)))

    @property
    def tracker_point_rms_mm(self) -> float:
        """Predicted RMS error (mm) of the point in front of the tracker, placed in the base frame."""
        return float(np.sqrt(max(np.trace(self.tracker_point_covariance_mm2), 0.0)))


def _project_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to a 3x3 matrix (Frobenius)."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def solve_ax_yb(flange_to_base: np.ndarray, sensor_to_tracker: np.ndarray, weights: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form ``(SensorToFlange, TrackerToBase)`` (4x4, mm) from pose pairs (N, 4, 4, mm, N >= 3).

    Rotations: every pair says ``R_Y = R_A R_X R_B^T``; the sum of ``R_B (x) R_A`` over the pairs maps
    ``vec(R_X)`` onto a multiple of ``vec(R_Y)``, so its leading singular vectors give both (then a few
    alternating Procrustes steps, which are exact for noisy data's least squares on rotations). Translations:
    linear least squares of ``R_A t_X - t_Y = R_Y t_B - t_A``. ``weights`` (N,) weigh the pairs."""
    rot_a, rot_b = flange_to_base[:, :3, :3], sensor_to_tracker[:, :3, :3]
    w = np.ones(len(rot_a)) if weights is None else np.asarray(weights, dtype=float)
    kron = np.einsum("i,iab,icd->acbd", w, rot_b, rot_a).reshape(9, 9)
    u, _, vt = np.linalg.svd(kron)
    rot_x, rot_y = vt[0].reshape(3, 3, order="F"), u[:, 0].reshape(3, 3, order="F")
    if np.linalg.det(rot_x) < 0:
        rot_x, rot_y = -rot_x, -rot_y
    rot_x, rot_y = _project_rotation(rot_x), _project_rotation(rot_y)
    weighted_a, rot_b_t = rot_a * w[:, None, None], np.swapaxes(rot_b, 1, 2)
    for _ in range(3):
        rot_y = _project_rotation(((weighted_a @ rot_x) @ rot_b_t).sum(axis=0))
        rot_x = _project_rotation((np.swapaxes(weighted_a, 1, 2) @ rot_y @ rot_b).sum(axis=0))
    root = np.sqrt(w)[:, None, None]
    lhs = np.concatenate([rot_a, np.broadcast_to(-np.eye(3), rot_a.shape)], axis=2) * root
    rhs = (np.einsum("ab,ib->ia", rot_y, sensor_to_tracker[:, :3, 3]) - flange_to_base[:, :3, 3]) * root[:, :, 0]
    solution = np.linalg.lstsq(lhs.reshape(-1, 6), rhs.reshape(-1), rcond=None)[0]
    sensor_to_flange, tracker_to_base = np.eye(4), np.eye(4)
    sensor_to_flange[:3, :3], sensor_to_flange[:3, 3] = rot_x, solution[:3]
    tracker_to_base[:3, :3], tracker_to_base[:3, 3] = rot_y, solution[3:]
    return sensor_to_flange, tracker_to_base


def pose_residuals(flange_to_base: np.ndarray, sensor_to_tracker: np.ndarray, sensor_to_flange: np.ndarray,
                   tracker_to_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair, the sensor's pose by the robot (``FlangeToBase @ SensorToFlange``) against by the tracker
    (``TrackerToBase @ SensorToTracker``): the rotation vector between them (N, 3, rad, Sensor frame) and
    the difference of the sensor's origin (N, 3, mm, Base frame)."""
    by_robot = flange_to_base @ sensor_to_flange
    by_tracker = tracker_to_base @ sensor_to_tracker
    turn = rotation_vectors(np.swapaxes(by_tracker[:, :3, :3], 1, 2) @ by_robot[:, :3, :3])
    return turn, by_robot[:, :3, 3] - by_tracker[:, :3, 3]


def motion_spread(flange_to_base: np.ndarray) -> tuple[float, float]:
    """How the flange turned (degrees): the largest rotation from its mean orientation, and the RMS rotation
    about the second principal axis of those rotations (near 0: every rotation about one axis, which cannot
    determine ``SensorToFlange``)."""
    rotations = flange_to_base[:, :3, :3]
    mean = _project_rotation(rotations.sum(axis=0))
    vectors = np.degrees(rotation_vectors(mean.T @ rotations))
    if len(vectors) < 2:
        return 0.0, 0.0
    eigen = np.sort(np.linalg.eigvalsh(vectors.T @ vectors / len(vectors)))[::-1]
    return float(np.max(np.linalg.norm(vectors, axis=1))), float(np.sqrt(max(eigen[1], 0.0)))


def residual_distances(flange_to_base: np.ndarray, sensor_to_tracker: np.ndarray, sensor_to_flange: np.ndarray,
                       tracker_to_base: np.ndarray) -> np.ndarray:
    """Residual of each pair as one distance (mm): the sensor origin's, and the rotation's at ``LEVER_MM``."""
    turn, shift = pose_residuals(flange_to_base, sensor_to_tracker, sensor_to_flange, tracker_to_base)
    return np.hypot(np.linalg.norm(shift, axis=1), LEVER_MM * np.linalg.norm(turn, axis=1))


def _spread_rows(n: int, most: int = MOST_SCORED) -> np.ndarray:
    """At most ``most`` indices of ``n`` frames, evenly spread over them."""
    return np.unique(np.linspace(0, n - 1, min(n, most)).round().astype(int))


def robust_start(flange_to_base: np.ndarray, sensor_to_tracker: np.ndarray, trials: int = 120, size: int = 6,
                 seed: int = 0, confidence: float = 0.9999) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form ``(SensorToFlange, TrackerToBase, inliers)`` robust to wrong poses: least median of the
    residual distances over solutions from ``size`` pairs drawn one from each part of the recording, then one
    weighted solve on the pairs within three robust standard deviations.

    At most ``trials`` draws; fewer when, with the inlier fraction ``w`` the best solution so far shows, the
    chance that no draw was all inliers, ``(1 - w^size)^draws``, is below ``1 - confidence`` (adaptive RANSAC)."""
    n = len(flange_to_base)
    rng = np.random.default_rng(seed)
    bins = np.array_split(np.arange(n), size)
    scored = _spread_rows(n)  # the median of a few hundred frames ranks the candidates as well as all
    best, best_score, needed = None, np.inf, trials
    for draw in range(trials):
        if draw >= needed:
            break
        pick = np.array([rng.choice(b) for b in bins if len(b)])
        try:
            x, y = solve_ax_yb(flange_to_base[pick], sensor_to_tracker[pick])
        except np.linalg.LinAlgError:
            continue
        distances = residual_distances(flange_to_base[scored], sensor_to_tracker[scored], x, y)
        score = float(np.median(distances))
        if score < best_score:
            best, best_score = (x, y), score
            inlier_fraction = float(np.mean(distances <= 3.0 * 1.4826 * score))
            all_inliers = inlier_fraction ** size
            needed = (trials if all_inliers <= 0.0 else
                      int(np.ceil(np.log(1.0 - confidence) / np.log(max(1.0 - all_inliers, 1e-12)))))
    if best is None:
        raise NoSafeAnswerError("hand-eye: no frame set gives a solution; the motion cannot determine the answer")
    distances = residual_distances(flange_to_base, sensor_to_tracker, *best)
    inliers = distances <= max(3.0 * 1.4826 * np.median(distances), 1e-6)
    x, y = solve_ax_yb(flange_to_base[inliers], sensor_to_tracker[inliers])
    return x, y, inliers


@dataclass(frozen=True)
class _Frames:
    """The tracker's samples and the robot's log, on the tracker's clock (internal)."""

    robot_time_s: np.ndarray
    flange_to_base: np.ndarray
    time_s: np.ndarray
    sensor_to_tracker: np.ndarray
    max_gap_s: float

    def flange_at(self, offset_s: float, rows: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """``FlangeToBase`` at the tracker instants ``rows`` for an offset, and where the robot has a pose."""
        return interpolate_poses(self.robot_time_s, self.flange_to_base, self.time_s[rows] - offset_s,
                                 self.max_gap_s)


def _scan_offset(frames: _Frames, rows: np.ndarray, offset_s: float) -> float:
    """The offset (s) near ``offset_s`` with the smallest median residual distance of a closed-form solve on
    the frames ``rows`` (paired at every offset scanned), refined by a parabola through the best three."""
    rows = rows[_spread_rows(len(rows))]
    steps = np.arange(-SCAN_HALF_WIDTH_S, SCAN_HALF_WIDTH_S + SCAN_STEP_S / 2, SCAN_STEP_S)
    costs = np.full(len(steps), np.inf)
    for k, step in enumerate(steps):
        flange, valid = frames.flange_at(offset_s + step, rows)
        if np.count_nonzero(valid) < 10:
            continue
        x, y = solve_ax_yb(flange[valid], frames.sensor_to_tracker[rows][valid])
        costs[k] = np.median(residual_distances(flange[valid], frames.sensor_to_tracker[rows][valid], x, y))
    if not np.any(np.isfinite(costs)):
        return float(offset_s)
    k = int(np.argmin(costs))
    best = offset_s + steps[k]
    if 0 < k < len(steps) - 1 and np.all(np.isfinite(costs[k - 1:k + 2])):
        curvature = costs[k - 1] - 2 * costs[k] + costs[k + 1]
        if curvature > 0:
            best += 0.5 * (costs[k - 1] - costs[k + 1]) / curvature * SCAN_STEP_S
    return float(best)


#: Median of a chi-square variable with 3 degrees of freedom: ``|v|^2`` of a 3D vector with per-axis variance 1.
_MEDIAN_CHI2_3 = 2.366

#: The noise model is fitted on frames grouped in this many speed classes (quantiles), each of at least
#: ``NOISE_BIN_FRAMES`` frames.
NOISE_BINS = 10
NOISE_BIN_FRAMES = 15


@dataclass(frozen=True)
class _Noise:
    """A frame's residual noise (internal): per axis, variance ``sigma^2 + (speed x jitter_s)^2`` for rotation
    (``sigma_rotation`` rad, angular speed rad/s) and position (``sigma_position`` mm, linear speed mm/s)."""

    sigma_rotation: float
    sigma_position: float
    jitter_s: float

    def scales(self, linear: np.ndarray, angular: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per frame, the standard deviation per axis of the rotation (rad) and position (mm) residuals."""
        return np.hypot(self.sigma_rotation, angular * self.jitter_s), np.hypot(self.sigma_position,
                                                                                 linear * self.jitter_s)


def _fit_noise(turn: np.ndarray, shift: np.ndarray, speeds: tuple[np.ndarray, np.ndarray],
               least_jitter_s: float) -> _Noise:
    """The noise model (:class:`_Noise`) of the residuals, robustly: the frames grouped by speed, each group's
    median squared residual (per axis) is ``sigma^2 + speed^2 jitter^2`` for rotation and position with one
    jitter (the tracker's time stamps' scatter, the same for both), fitted by non-negative least squares
    relative to each group's value; the jitter never below ``least_jitter_s``."""
    linear, angular = speeds
    rotation_var = np.sum(turn ** 2, axis=1) / _MEDIAN_CHI2_3  # its median: the per-axis variance
    position_var = np.sum(shift ** 2, axis=1) / _MEDIAN_CHI2_3
    rows = []
    groups = np.array_split(np.argsort(linear / max(float(np.median(linear)), 1e-9)
                                       + angular / max(float(np.median(angular)), 1e-12)),
                            max(1, min(NOISE_BINS, len(linear) // NOISE_BIN_FRAMES)))
    for group in groups:
        rot, pos = float(np.median(rotation_var[group])), float(np.median(position_var[group]))
        w_sq, v_sq = float(np.median(angular[group] ** 2)), float(np.median(linear[group] ** 2))
        rows += [([1.0 / max(rot, 1e-14), 0.0, w_sq / max(rot, 1e-14)], 1.0),
                 ([0.0, 1.0 / max(pos, 1e-10), v_sq / max(pos, 1e-10)], 1.0)]
    lhs, rhs = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    var_rot, var_pos, jitter_sq = nnls(lhs, rhs)[0]
    jitter = max(float(np.sqrt(jitter_sq)), least_jitter_s)
    if jitter > float(np.sqrt(jitter_sq)):  # the floor raised the jitter: the still variances from the slow frames
        slow = groups[0]
        var_rot = max(float(np.median(rotation_var[slow])) - jitter ** 2 * float(np.median(angular[slow] ** 2)), 0.0)
        var_pos = max(float(np.median(position_var[slow])) - jitter ** 2 * float(np.median(linear[slow] ** 2)), 0.0)
    return _Noise(max(float(np.sqrt(var_rot)), 1e-6), max(float(np.sqrt(var_pos)), 1e-4), jitter)


def _params_to_poses(x: np.ndarray, start: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """X and Y from the 12 parameters: rotation vectors applied on the right (rad), translations added (mm)."""
    poses = []
    for k, pose in enumerate(start):
        moved = pose.copy()
        moved[:3, :3] = pose[:3, :3] @ rotation_matrices(x[6 * k:6 * k + 3])
        moved[:3, 3] = pose[:3, 3] + x[6 * k + 3:6 * k + 6]
        poses.append(moved)
    return poses[0], poses[1]


def _linearise(frames: _Frames, rows: np.ndarray, pose: tuple[np.ndarray, np.ndarray], offset_s: float,
               scales: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Noise-normalised residuals (N, 6: rotation, position) of the frames ``rows`` and their Jacobian (N, 6, 13)
    with respect to X's rotation vector (right, rad) and translation (mm), Y's, and the offset (s)."""
    sensor_to_flange, tracker_to_base = pose
    tracker = frames.sensor_to_tracker[rows]
    flange, _, linear, angular = interpolate_poses(frames.robot_time_s, frames.flange_to_base,
                                                   frames.time_s[rows] - offset_s, frames.max_gap_s, velocities=True)
    turn, shift = pose_residuals(flange, tracker, sensor_to_flange, tracker_to_base)
    # the offset's column: the robot's pose is taken at t_tracker - offset, a larger offset takes it earlier
    turn_dt = -angular @ sensor_to_flange[:3, :3]  # rows: R_X^T w
    shift_dt = -(linear + (flange[:, :3, :3] @ np.cross(angular, sensor_to_flange[:3, 3])[:, :, None])[:, :, 0])
    jac = np.zeros((len(rows), 6, 13))
    jac[:, :3, 0:3] = np.eye(3)
    jac[:, :3, 6:9] = -np.swapaxes(tracker[:, :3, :3], 1, 2)
    jac[:, :3, 12] = turn_dt
    jac[:, 3:, 3:6] = flange[:, :3, :3]
    jac[:, 3:, 6:9] = tracker_to_base[:3, :3] @ skew(tracker[:, :3, 3])
    jac[:, 3:, 9:12] = -np.eye(3)
    jac[:, 3:, 12] = shift_dt
    divide = np.concatenate([np.repeat(scales[0][:, None], 3, 1), np.repeat(scales[1][:, None], 3, 1)], axis=1)
    return np.concatenate([turn, shift], axis=1) / divide, jac / divide[:, :, None]


def _gauss_newton(frames: _Frames, rows: np.ndarray, pose: tuple[np.ndarray, np.ndarray], offset_s: float,
                  scales: tuple[np.ndarray, np.ndarray], iterations: int = 15
                  ) -> tuple[tuple[np.ndarray, np.ndarray], float, np.ndarray]:
    """Iteratively reweighted Gauss-Newton of X, Y and the offset on the frames ``rows``: the maximum likelihood
    under a multivariate Student-t of ``TAIL_DOF`` degrees of freedom on each frame's noise-normalised 6-vector
    residual (EM noise is heavy-tailed: a frame far off counts less, smoothly). Returns the pose pair, the offset
    and the covariance of the 13 parameters (:func:`_sandwich_covariance`)."""
    for _ in range(iterations):
        residual, jac = _linearise(frames, rows, pose, offset_s, scales)
        root = np.sqrt(_tail_weights(residual))[:, None]
        weighted_jac = (jac * root[:, :, None]).reshape(-1, 13)
        step = -np.linalg.lstsq(weighted_jac.T @ weighted_jac, weighted_jac.T @ (residual * root).reshape(-1),
                                rcond=None)[0]
        pose = _params_to_poses(step[:12], pose)
        offset_s += float(step[12])
        if np.max(np.abs(step[[0, 1, 2, 6, 7, 8]])) < 1e-9 and np.max(np.abs(step[[3, 4, 5, 9, 10, 11]])) < 1e-6:
            break
    residual, jac = _linearise(frames, rows, pose, offset_s, scales)
    return pose, offset_s, _sandwich_covariance(frames.time_s[rows], residual, jac)


def _tail_weights(residual: np.ndarray) -> np.ndarray:
    """Each frame's weight under the multivariate Student-t (``TAIL_DOF``) of its normalised residual (N, 6)."""
    return (TAIL_DOF + residual.shape[1]) / (TAIL_DOF + np.sum(residual ** 2, axis=1))


def _sandwich_covariance(time_s: np.ndarray, residual: np.ndarray, jac: np.ndarray) -> np.ndarray:
    """The covariance (13x13) of the weighted estimate from what the residuals show, not from the noise model
    alone: ``inv(H) M inv(H)`` with ``H`` the weighted normal matrix and ``M`` the scatter of the weighted
    gradient summed over blocks of ``COVARIANCE_BLOCK_S`` (frames within a block may share errors: the smoothed
    robot log, a slow EM drift)."""
    weight = _tail_weights(residual)
    weighted_jac = jac * weight[:, None, None]
    normal_inverse = np.linalg.pinv(weighted_jac.reshape(-1, 13).T @ jac.reshape(-1, 13))
    scores = (np.swapaxes(weighted_jac, 1, 2) @ residual[:, :, None])[:, :, 0]
    block = np.floor((time_s - time_s[0]) / COVARIANCE_BLOCK_S).astype(int)
    summed = np.zeros((block.max() + 1, scores.shape[1]))
    np.add.at(summed, block, scores)
    count = len(np.unique(block))
    scatter = summed.T @ summed * count / max(count - 1, 1)
    return normal_inverse @ scatter @ normal_inverse


def _point_covariance(pose: np.ndarray, block: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Covariance (mm^2) of ``pose @ point`` from the 6x6 covariance of the pose's parameters (rotation
    vector on the right, rad; translation, mm)."""
    jac = np.hstack([-pose[:3, :3] @ skew(point), np.eye(3)])
    return jac @ block @ jac.T


@dataclass(frozen=True)
class _Fit:
    """One refinement's answer (internal)."""

    sensor_to_flange: np.ndarray
    tracker_to_base: np.ndarray
    offset_s: float
    keep: np.ndarray
    distance: np.ndarray
    noise: _Noise
    covariance: np.ndarray


def _distances_normalised(frames: _Frames, rows: np.ndarray, pose: tuple[np.ndarray, np.ndarray], offset_s: float,
                          scales: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    flange, _ = frames.flange_at(offset_s, rows)
    turn, shift = pose_residuals(flange, frames.sensor_to_tracker[rows], *pose)
    return np.sqrt(np.sum((turn / scales[0][:, None]) ** 2 + (shift / scales[1][:, None]) ** 2, axis=1))


def _refine(frames: _Frames, rows: np.ndarray, keep: np.ndarray, start: tuple[np.ndarray, np.ndarray],
            offset_s: float, settings: HandEyeSettings) -> _Fit:
    """Robust nonlinear refinement of X, Y and the offset on the frames ``rows``, rejecting frames whose
    noise-normalised residual (a Mahalanobis distance over 6 components) exceeds ``outlier_limit``, until the
    kept frames settle."""
    tracker = frames.sensor_to_tracker[rows]
    linear, angular = pose_speeds(frames.robot_time_s, frames.flange_to_base, frames.time_s[rows] - offset_s)
    pose = start
    covariance = np.zeros((13, 13))
    for _ in range(4):
        flange, _ = frames.flange_at(offset_s, rows)
        turn, shift = pose_residuals(flange, tracker, *pose)
        noise = _fit_noise(turn[keep], shift[keep], (linear[keep], angular[keep]), settings.timing_jitter_s)
        scales = noise.scales(linear, angular)
        new_keep = _distances_normalised(frames, rows, pose, offset_s, scales) <= settings.outlier_limit
        if np.count_nonzero(new_keep) < 3:
            break
        settled = np.array_equal(new_keep, keep)
        keep = new_keep
        pose, offset_s, covariance = _gauss_newton(frames, rows[keep], pose, offset_s,
                                                   (scales[0][keep], scales[1][keep]))
        if settled:
            break
    distance = _distances_normalised(frames, rows, pose, offset_s, scales)
    return _Fit(pose[0], pose[1], offset_s, distance <= settings.outlier_limit, distance, noise, covariance)


def _prepare(robot_time_s: np.ndarray, flange_to_base: np.ndarray, tracker_time_s: np.ndarray,
             sensor_to_tracker: np.ndarray, settings: HandEyeSettings) -> _Frames:
    """Check the arrays (shapes, finite numbers, enough samples) and sort the robot's log by time."""
    robot_time_s, tracker_time_s = np.asarray(robot_time_s, float), np.asarray(tracker_time_s, float)
    flange_to_base, sensor_to_tracker = np.asarray(flange_to_base, float), np.asarray(sensor_to_tracker, float)
    for name, times, poses in (("robot poses", robot_time_s, flange_to_base),
                               ("tracker poses", tracker_time_s, sensor_to_tracker)):
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or times.shape != (len(poses),):
            raise EMRegError(f"hand-eye: {name} must be N times and N 4x4 poses")
        if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(times))):
            raise EMRegError(f"hand-eye: {name} hold NaN or infinite values")
        if len(times) < max(settings.min_frames, 2):
            raise NoSafeAnswerError(f"hand-eye: too few frames: {len(times)} {name} (at least "
                                    f"{max(settings.min_frames, 2)}, [handeye] min_frames); record longer")
    robot_time_s, flange_to_base = prepared_log(robot_time_s, flange_to_base)
    steps = np.diff(robot_time_s)
    max_gap = max(5.0 * float(np.median(steps)), 0.05) if len(steps) else 0.05
    return _Frames(robot_time_s, flange_to_base, tracker_time_s, sensor_to_tracker, max_gap)


def _pairable(frames: _Frames, offset_s: float) -> tuple[np.ndarray, list[RejectedFrame]]:
    """The tracker samples with a robot pose at every offset the scan and refinement may try, and the others
    with the reason."""
    margin = SCAN_HALF_WIDTH_S + 0.05
    ok = frames.flange_at(offset_s - margin)[1] & frames.flange_at(offset_s + margin)[1]
    ok &= frames.flange_at(offset_s)[1]
    rejected = [RejectedFrame(int(i), float(frames.time_s[i]),
                              "no robot pose at this instant (outside the robot's log, within "
                              f"{margin:g} s of its ends, or in a gap of it)") for i in np.nonzero(~ok)[0]]
    return np.nonzero(ok)[0], rejected


def _check_motion(flange_to_base: np.ndarray, settings: HandEyeSettings, what: str) -> tuple[float, float]:
    """Refuse (exit 3) motion that cannot determine X and Y: too few frames, too small a rotation, rotations
    about one axis only. Returns the rotation range and the second axis's RMS rotation (degrees)."""
    if len(flange_to_base) < settings.min_frames:
        raise NoSafeAnswerError(f"hand-eye: too few frames: {len(flange_to_base)} {what} (at least "
                                f"{settings.min_frames}, [handeye] min_frames); record longer")
    spread, second = motion_spread(flange_to_base)
    if spread < settings.min_rotation_deg:
        raise NoSafeAnswerError(f"hand-eye: the flange turned at most {spread:.1f} deg from its mean orientation "
                                f"(at least {settings.min_rotation_deg:g}, [handeye] min_rotation_deg): too small a "
                                "range of motion to determine SensorToFlange; rotate it more")
    if second < settings.min_second_axis_deg:
        raise NoSafeAnswerError(f"hand-eye: the flange turned about one axis only (RMS {second:.2f} deg about any "
                                f"second axis, at least {settings.min_second_axis_deg:g}, [handeye] "
                                "min_second_axis_deg): rotations about two non-parallel axes are needed")
    return spread, second


def _dwells(time_s: np.ndarray, still: np.ndarray, min_duration_s: float = 0.3) -> int:
    """How many runs of still frames last at least ``min_duration_s`` (s)."""
    edges = np.diff(np.concatenate([[0], still.astype(int), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0] - 1
    return int(np.count_nonzero(time_s[ends] - time_s[starts] >= min_duration_s))


def _time_offset(frames: _Frames, settings: HandEyeSettings):
    """The cross-correlation's clock offset, refused (exit 3) when the speeds do not correlate."""
    clock = estimate_clock_offset(frames.robot_time_s, frames.flange_to_base[:, :3, :3], frames.time_s,
                                  frames.sensor_to_tracker[:, :3, :3], max_abs_offset_s=settings.max_time_offset_s)
    if clock.correlation < settings.min_correlation:
        raise NoSafeAnswerError(f"hand-eye: the clock offset cannot be found from the motion: the angular speeds of "
                                f"the flange and of the sensor correlate at most {clock.correlation:.2f} (at least "
                                f"{settings.min_correlation:g}, [handeye] min_correlation); are both recordings of "
                                "the same motion, and does the flange move?")
    return clock


def calibrate_hand_eye(robot_time_s: np.ndarray, flange_to_base: np.ndarray, tracker_time_s: np.ndarray,
                       sensor_to_tracker: np.ndarray, settings: HandEyeSettings | None = None) -> HandEyeResult:
    """``SensorToFlange``, ``TrackerToBase`` (4x4, mm) and the clock offset (s, ``t_tracker = t_robot +
    offset``) from the robot's ``FlangeToBase`` poses (N, 4, 4, mm) at ``robot_time_s`` (robot clock, s) and
    the tracker's ``SensorToTracker`` poses (M, 4, 4, mm) at ``tracker_time_s`` (tracker clock, s).

    Raises :class:`~EMRegModule.errors.NoSafeAnswerError` when the motion cannot determine the answer (too
    few frames, too small a rotation, rotations about one axis, no clock offset, too many frames in
    disagreement, a predicted tool-tip error above ``max_tip_uncertainty_mm``). See the module docstring."""
    settings = settings or HandEyeSettings()
    frames = _prepare(robot_time_s, flange_to_base, tracker_time_s, sensor_to_tracker, settings)
    clock = _time_offset(frames, settings)
    rows, rejected = _pairable(frames, clock.offset_s)
    flange, _ = frames.flange_at(clock.offset_s, rows)
    _check_motion(flange, settings, "tracker samples during the robot's log")
    tracker = frames.sensor_to_tracker[rows]
    _, _, inliers = robust_start(flange, tracker)
    offset = _scan_offset(frames, rows[inliers], clock.offset_s)
    flange, _ = frames.flange_at(offset, rows)
    start = solve_ax_yb(flange[inliers], tracker[inliers])  # the refinement sorts the frames out again
    fit = _refine(frames, rows, inliers, start, offset, settings)
    used = rows[fit.keep]
    flange, _ = frames.flange_at(fit.offset_s, used)
    spread, second = _check_motion(flange, settings, "frames agree with the calibration")
    if np.count_nonzero(~fit.keep) > 0.3 * len(rows):
        raise NoSafeAnswerError(f"hand-eye: {np.count_nonzero(~fit.keep)} of {len(rows)} frames disagree with the "
                                "best calibration: no consistent answer (a moved field generator, a loose sensor, "
                                "or the wrong sensor?)")
    rejected += [RejectedFrame(int(i), float(frames.time_s[i]), _reason(d, settings))
                 for i, d in zip(rows[~fit.keep], fit.distance[~fit.keep], strict=True)]
    return _result(frames, fit, clock, used, sorted(rejected, key=lambda r: r.index), (spread, second), settings)


def _reason(distance: float, settings: HandEyeSettings) -> str:
    return (f"residual {distance:.1f} times the expected noise (limit {settings.outlier_limit:g}, [handeye] "
            "outlier_limit): a wrong pose (EM glitch or distortion)")


def _result(frames: _Frames, fit: _Fit, clock, used: np.ndarray, rejected: list[RejectedFrame],
            motion: tuple[float, float], settings: HandEyeSettings) -> HandEyeResult:
    """The typed result, with the predicted errors; refused (exit 3) above ``max_tip_uncertainty_mm``."""
    flange, _ = frames.flange_at(fit.offset_s, used)
    turn, shift = pose_residuals(flange, frames.sensor_to_tracker[used], fit.sensor_to_flange, fit.tracker_to_base)
    linear, angular = pose_speeds(frames.robot_time_s, frames.flange_to_base, frames.time_s[used] - fit.offset_s,
                                  STILL_WINDOW_S)
    still = (linear < STILL_SPEED_MM_S) & (angular < STILL_SPEED_RAD_S)
    tip = np.asarray(settings.tool_tip_mm, dtype=float)
    point = np.asarray(TRACKER_POINT_MM)
    tip_cov = _point_covariance(fit.sensor_to_flange, fit.covariance[:6, :6], tip)
    point_cov = _point_covariance(fit.tracker_to_base, fit.covariance[6:12, 6:12], point)
    result = HandEyeResult(
        fit.sensor_to_flange, fit.tracker_to_base, fit.offset_s, clock.offset_s, clock.correlation, used,
        np.degrees(np.linalg.norm(turn, axis=1)), np.linalg.norm(shift, axis=1), tuple(rejected),
        int(np.count_nonzero(still)), _dwells(frames.time_s[used], still), float(np.degrees(fit.noise.sigma_rotation)),
        fit.noise.sigma_position, motion[0], motion[1], fit.covariance, tip, tip_cov, point, point_cov,
        _project_rotation(flange[:, :3, :3].sum(axis=0)))
    if result.noise_position_mm > settings.max_noise_mm or result.noise_rotation_deg > settings.max_noise_deg:
        raise NoSafeAnswerError(
            f"hand-eye: the robot's and the tracker's poses disagree by {result.noise_position_mm:.2f} mm and "
            f"{result.noise_rotation_deg:.2f} deg per axis where the flange is slow (at most {settings.max_noise_mm:g} "
            f"mm, {settings.max_noise_deg:g} deg, [handeye] max_noise_mm, max_noise_deg): not the same motion, the "
            "wrong sensor, or a moved field generator?")
    if result.tool_tip_rms_mm > settings.max_tip_uncertainty_mm:
        raise NoSafeAnswerError(f"hand-eye: the predicted error at the tool point {tip.tolist()} mm is "
                                f"{result.tool_tip_rms_mm:.2f} mm RMS (at most {settings.max_tip_uncertainty_mm:g}, "
                                "[handeye] max_tip_uncertainty_mm): the motion does not determine the answer well "
                                "enough; rotate the flange more, about more axes")
    return result
