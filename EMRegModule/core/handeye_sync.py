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
from scipy.spatial.transform import Rotation
from scipy.stats import rankdata

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
    relative = Rotation.from_matrix(np.swapaxes(rotations[first], 1, 2) @ rotations[second])
    dt = time_s[second] - time_s[first]
    speed = np.linalg.norm(relative.as_rotvec(), axis=1) / dt
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


def interpolate_poses(time_s: np.ndarray, poses: np.ndarray, query_s: np.ndarray, max_gap_s: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4; e.g. ``FlangeToBase``, mm) at the instants ``query_s`` (same clock, s): rotation by
    spherical interpolation, translation linear, between the two samples around each instant. Returns the poses
    and a mask of the instants that have samples on both sides at most ``max_gap_s`` apart (identity elsewhere)."""
    query_s = np.asarray(query_s, dtype=float)
    before = np.clip(np.searchsorted(time_s, query_s, side="right") - 1, 0, len(time_s) - 2)
    after = before + 1
    span = time_s[after] - time_s[before]
    valid = (query_s >= time_s[0]) & (query_s <= time_s[-1]) & (span <= max_gap_s)
    fraction = np.clip((query_s - time_s[before]) / np.maximum(span, 1e-12), 0.0, 1.0)
    step = Rotation.from_matrix(np.swapaxes(poses[before, :3, :3], 1, 2) @ poses[after, :3, :3]).as_rotvec()
    out = np.tile(np.eye(4), (len(query_s), 1, 1))
    out[:, :3, :3] = poses[before, :3, :3] @ Rotation.from_rotvec(step * fraction[:, None]).as_matrix()
    out[:, :3, 3] = poses[before, :3, 3] + (poses[after, :3, 3] - poses[before, :3, 3]) * fraction[:, None]
    out[~valid] = np.eye(4)
    return out, valid


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
    turn = Rotation.from_matrix(np.swapaxes(start[:, :3, :3], 1, 2) @ end[:, :3, :3]).as_rotvec()
    return linear, np.linalg.norm(turn, axis=1) / dt
