"""Two clocks, one motion: the robot's flange poses and the EM tracker's sensor poses put on one time axis.

Pure functions (arrays in, arrays out) used by :mod:`EMRegModule.core.handeye`:

- :func:`angular_speed` and :func:`estimate_clock_offset`: the flange and the sensor on it are one rigid body,
  so their angular speeds are the same function of time whatever ``SensorToFlange`` and ``TrackerToBase`` are;
  the clock offset is where the two angular-speed signals correlate best (normalised cross-correlation over
  every lag that keeps the recordings overlapping, so clocks with different epochs need no hint).
- :func:`interpolate_poses` and :func:`pose_speeds`: the robot's ``FlangeToBase`` (mm) at the tracker's
  instants, and how fast the flange moves there (mm/s, rad/s).

Convention everywhere: ``t_tracker = t_robot + time_offset_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import correlate
from scipy.stats import rankdata

from .transforms import rotation_matrices, rotation_vectors

#: Angular speeds are taken over this window (s): long enough to average EM noise, short for the timing.
SPEED_WINDOW_S = 0.1

#: The common grid of the cross-correlation (s).
GRID_S = 0.005


@dataclass(frozen=True)
class ClockFit:
    """The clock offset found by cross-correlation: ``offset_s`` (``t_tracker = t_robot + offset_s``), the
    normalised correlation at the peak (1 = identical speed profiles) and the overlap used (s)."""

    offset_s: float
    correlation: float
    overlap_s: float


def angular_speed(time_s: np.ndarray, rotations: np.ndarray, window_s: float = SPEED_WINDOW_S
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Angular speed (rad/s) of a stream of rotations (N, 3, 3; any frame, the speed does not depend on it)
    over ``window_s``, stamped at each window's middle (s, the stream's clock). A lone wild sample (an EM
    glitch) is removed by a 7-sample median."""
    time_s = np.asarray(time_s, dtype=float)
    if len(time_s) < 3:
        return np.zeros(0), np.zeros(0)
    later = np.searchsorted(time_s, time_s + window_s)
    first = np.nonzero(later < len(time_s))[0]
    if len(first) < 3:
        return np.zeros(0), np.zeros(0)
    second = later[first]
    relative = rotation_vectors(np.swapaxes(rotations[first], 1, 2) @ rotations[second])
    dt = time_s[second] - time_s[first]
    speed = np.linalg.norm(relative, axis=1) / dt
    return 0.5 * (time_s[first] + time_s[second]), median_filter(speed, size=7, mode="nearest")


def _overlap_sums(a: np.ndarray, b: np.ndarray, mask_a: np.ndarray, mask_b: np.ndarray) -> dict[str, np.ndarray]:
    """For every lag (full cross-correlation), the sums over the samples where both signals exist."""
    def xc(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return correlate(v, u, mode="full", method="fft")

    return {"n": xc(mask_a, mask_b), "a": xc(a, mask_b), "b": xc(mask_a, b), "aa": xc(a * a, mask_b),
            "bb": xc(mask_a, b * b), "ab": xc(a, b)}


def estimate_clock_offset(robot_time_s: np.ndarray, robot_rotations: np.ndarray, tracker_time_s: np.ndarray,
                          tracker_rotations: np.ndarray, min_overlap: float = 0.5,
                          max_abs_offset_s: float | None = None) -> ClockFit:
    """The clock offset (s, ``t_tracker = t_robot + offset``) at which the angular speeds of the robot's flange
    (``FlangeToBase`` rotations) and of the tracker's sensor (``SensorToTracker`` rotations) correlate best.

    Every lag is tried at which the recordings overlap by at least ``min_overlap`` of the shorter one (and,
    with ``max_abs_offset_s``, the offset stays within it); the peak is refined to a fraction of the grid by a
    parabola. A correlation of 0 means no lag had motion to compare."""
    tr, wr = angular_speed(robot_time_s, robot_rotations)
    tc, wc = angular_speed(tracker_time_s, tracker_rotations)
    if len(tr) < 3 or len(tc) < 3:
        return ClockFit(0.0, 0.0, 0.0)
    grid_r = np.arange(tr[0], tr[-1], GRID_S)
    grid_c = np.arange(tc[0], tc[-1], GRID_S)
    # ranks, not speeds: an EM glitch makes a spike of any height, a rank it can only make the highest
    a, b = rankdata(np.interp(grid_r, tr, wr)), rankdata(np.interp(grid_c, tc, np.minimum(wc, 1.5 * np.max(wr))))
    sums = _overlap_sums(a, b, np.ones_like(a), np.ones_like(b))
    # lag index k: tracker sample j pairs with robot sample j + (len(a) - 1) - k
    lags = np.arange(-(len(a) - 1), len(b))
    offsets = tc[0] - tr[0] + lags * GRID_S  # t_tracker - t_robot of the paired samples
    n = sums["n"]
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sums["ab"] - sums["a"] * sums["b"] / n
        var = (sums["aa"] - sums["a"] ** 2 / n) * (sums["bb"] - sums["b"] ** 2 / n)
        ncc = np.where((n >= min_overlap * min(len(a), len(b))) & (var > 1e-12), cov / np.sqrt(var), -np.inf)
    if max_abs_offset_s is not None:
        ncc[np.abs(offsets) > max_abs_offset_s] = -np.inf
    if not np.any(np.isfinite(ncc)):
        return ClockFit(0.0, 0.0, 0.0)
    k = int(np.argmax(ncc))
    offset = float(offsets[k])
    if 0 < k < len(ncc) - 1 and np.isfinite(ncc[k - 1]) and np.isfinite(ncc[k + 1]):
        curvature = ncc[k - 1] - 2 * ncc[k] + ncc[k + 1]
        if curvature < 0:
            offset += 0.5 * (ncc[k - 1] - ncc[k + 1]) / curvature * GRID_S
    return ClockFit(offset, float(ncc[k]), float(n[k] * GRID_S))


def interpolate_poses(time_s: np.ndarray, poses: np.ndarray, query_s: np.ndarray, max_gap_s: float,
                      velocities: bool = False):
    """Poses (N, 4, 4; e.g. ``FlangeToBase``, mm) at the instants ``query_s`` (same clock, s): rotation by
    spherical interpolation, translation linear, between the two samples around each instant. Returns the poses
    and a mask of the instants that have samples on both sides at most ``max_gap_s`` apart (identity elsewhere);
    with ``velocities``, also the interpolated motion's velocity there: linear (N, 3, mm/s, the poses' frame)
    and angular (N, 3, rad/s, in the moving frame: ``dR/dt = R [w]x``)."""
    query_s = np.asarray(query_s, dtype=float)
    before = np.clip(np.searchsorted(time_s, query_s, side="right") - 1, 0, len(time_s) - 2)
    after = before + 1
    span = time_s[after] - time_s[before]
    valid = (query_s >= time_s[0]) & (query_s <= time_s[-1]) & (span <= max_gap_s)
    fraction = np.clip((query_s - time_s[before]) / np.maximum(span, 1e-12), 0.0, 1.0)
    step = rotation_vectors(np.swapaxes(poses[before, :3, :3], 1, 2) @ poses[after, :3, :3])
    move = poses[after, :3, 3] - poses[before, :3, 3]
    out = np.tile(np.eye(4), (len(query_s), 1, 1))
    out[:, :3, :3] = poses[before, :3, :3] @ rotation_matrices(step * fraction[:, None])
    out[:, :3, 3] = poses[before, :3, 3] + move * fraction[:, None]
    out[~valid] = np.eye(4)
    if not velocities:
        return out, valid
    rate = 1.0 / np.maximum(span, 1e-12)[:, None]
    return out, valid, move * rate, step * rate


def pose_speeds(time_s: np.ndarray, poses: np.ndarray, query_s: np.ndarray, window_s: float = SPEED_WINDOW_S
                ) -> tuple[np.ndarray, np.ndarray]:
    """How fast the poses (``FlangeToBase``, mm) move at ``query_s`` (s): linear speed (mm/s) and angular speed
    (rad/s), from the poses half a ``window_s`` before and after (each clamped to the recording)."""
    t0 = np.clip(query_s - window_s / 2, time_s[0], time_s[-1])
    t1 = np.clip(query_s + window_s / 2, time_s[0], time_s[-1])
    dt = np.maximum(t1 - t0, 1e-9)
    start, _ = interpolate_poses(time_s, poses, t0, np.inf)
    end, _ = interpolate_poses(time_s, poses, t1, np.inf)
    linear = np.linalg.norm(end[:, :3, 3] - start[:, :3, 3], axis=1) / dt
    turn = rotation_vectors(np.swapaxes(start[:, :3, :3], 1, 2) @ end[:, :3, :3])
    return linear, np.linalg.norm(turn, axis=1) / dt


#: The robot's log is smoothed by local quadratics over 2k + 1 of its samples, k one of these (chosen by
#: cross-validation on the log itself, on at most ``SMOOTHING_SCORED`` of its samples).
SMOOTHING_HALF_WIDTHS = (2, 4, 8, 16)
SMOOTHING_SCORED = 1000


def _local_quadratic_rows(time_s: np.ndarray, rows: np.ndarray, half_width: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the samples ``rows`` and their 2k + 1 neighbours (``half_width`` k each side, clipped at the ends,
    where a sample has fewer): the neighbours' indices, the weights of the local quadratic (least squares in time
    on them) that give the sample's smoothed value, and the same without the sample itself (leave-one-out: the
    sample predicted from its neighbours alone); (len(rows), 2k + 1) each."""
    n = len(time_s)
    offsets = np.arange(-half_width, half_width + 1)
    unclipped = rows[:, None] + offsets[None, :]
    index = np.clip(unclipped, 0, n - 1)
    distinct = (unclipped >= 0) & (unclipped < n)
    dt = time_s[index] - time_s[rows][:, None]
    scale = np.maximum(np.max(np.abs(dt), axis=1, keepdims=True), 1e-9)
    design = np.stack([np.ones_like(dt), dt / scale, (dt / scale) ** 2], axis=2)
    weights = []
    for keep in (distinct, distinct & (offsets[None, :] != 0)):
        masked = design * keep[:, :, None]
        normal = np.swapaxes(masked, 1, 2) @ masked + 1e-12 * np.eye(3)
        # the fit's value at the sample (local time 0): the first row of inv(normal) @ design^T
        first_row = np.linalg.solve(normal, np.broadcast_to([[1.0], [0.0], [0.0]], (len(rows), 3, 1)))
        weights.append((masked @ first_row)[:, :, 0])
    return index, weights[0], weights[1]


def _local_values(poses: np.ndarray, index: np.ndarray, weights: np.ndarray, rows: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The weighted sums over each row's neighbours ``index`` of the rotation vectors relative to the row's own
    rotation (rad) and of the translations (mm)."""
    turns = rotation_vectors(np.swapaxes(poses[rows, :3, :3], 1, 2)[:, None] @ poses[index, :3, :3])
    return (weights[:, None] @ turns)[:, 0], (weights[:, None] @ poses[index, :3, 3])[:, 0]


def smooth_poses(time_s: np.ndarray, poses: np.ndarray, half_widths: tuple[int, ...] = SMOOTHING_HALF_WIDTHS
                 ) -> tuple[np.ndarray, tuple[int, int]]:
    """A densely sampled pose stream (e.g. the robot's ``FlangeToBase``, mm, at ``time_s`` s) with its white
    measurement noise smoothed out: at each sample, local quadratics in time through its 2k + 1 neighbours, of
    the rotation vectors relative to the sample's rotation and of the translation. For each of the two, ``k`` is
    the half width of ``half_widths`` with the smallest median leave-one-out error (each sample predicted from its
    neighbours): wide where the noise dominates, narrow where the motion curves faster than the samples come.
    Returns the smoothed poses and the two ``k`` (rotation, translation; 0: too few samples, left as they were)."""
    n = len(time_s)
    usable = [k for k in half_widths if 2 * k + 1 <= n]
    if not usable:
        return poses, (0, 0)
    scored = np.unique(np.linspace(0, n - 1, min(n, SMOOTHING_SCORED)).round().astype(int))
    errors = []
    for k in usable:
        index, _, loo = _local_quadratic_rows(time_s, scored, k)
        turn, position = _local_values(poses, index, loo, scored)
        errors.append((np.median(np.sum(turn ** 2, axis=1)),
                       np.median(np.sum((position - poses[scored, :3, 3]) ** 2, axis=1))))
    best = [usable[int(np.argmin(column))] for column in np.array(errors).T]
    rows = np.arange(n)
    out = np.array(poses, dtype=float)
    for channel, k in enumerate(best):
        index, smooth, _ = _local_quadratic_rows(time_s, rows, k)
        turn, position = _local_values(poses, index, smooth, rows)
        if channel == 0:
            out[:, :3, :3] = poses[:, :3, :3] @ rotation_matrices(turn)
        else:
            out[:, :3, 3] = position
    return out, (best[0], best[1])


def prepared_log(robot_time_s: np.ndarray, flange_to_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The robot's log as the hand-eye solver uses it: sorted by time (robot clock, s), each time once, the poses
    (``FlangeToBase``, mm) smoothed by :func:`smooth_poses`."""
    order = np.argsort(robot_time_s, kind="stable")
    robot_time_s, flange_to_base = np.asarray(robot_time_s, float)[order], np.asarray(flange_to_base, float)[order]
    distinct = np.concatenate([[True], np.diff(robot_time_s) > 0])
    robot_time_s, flange_to_base = robot_time_s[distinct], flange_to_base[distinct]
    return robot_time_s, smooth_poses(robot_time_s, flange_to_base)[0]
