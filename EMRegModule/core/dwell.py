"""Dwells: the periods when the probe is held still (in a pinhole, a board hole, at a target).

A dwell is found either from the recording's labels (a run of samples carrying the same
non-empty label) or, for a recording without labels, automatically: a period in which the
probe, expressed in the frame the caller chooses (normally the Reference frame, so that a
frame or transmitter moved between dwells changes nothing), stays within a small radius
for at least a minimum duration. Transitions, short stops and samples of bad quality are
ignored, and a few wild samples inside a dwell neither split it nor move its average.

Everything here is plain numpy over arrays of times (s) and positions (mm).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import EMRegError
from ..settings import DwellSettings

#: A still period's ends are trimmed to the samples within this many ``still_radius_mm`` of its median.
TRIM_FACTOR = 1.5
#: A labelled dwell whose samples spread (or drift) farther than this many ``still_radius_mm`` is a moving probe
#: (a probe held still, even by hand, stays well within it: 0.3 mm against 2 mm in a pinhole).
LABEL_SPREAD_FACTOR = 4.0


@dataclass
class Dwell:
    """One dwell: indices into the arrays it was found in (time order), a label, its time span (s).

    ``label`` is the recording's label, or empty for an automatically found dwell.
    """

    indices: np.ndarray
    label: str
    start_s: float
    end_s: float

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s

    def __len__(self) -> int:
        return len(self.indices)


@dataclass
class RobustMean:
    """A robust average of points: ``mean`` (3,), ``inliers`` (boolean mask), ``std_mm``.

    ``std_mm`` is the RMS 3D distance of the inliers from the mean (the dwell's spread).
    """

    mean: np.ndarray
    inliers: np.ndarray
    std_mm: float

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.inliers))


def robust_mean(points: np.ndarray, cutoff: float = 2.5, iterations: int = 4) -> RobustMean:
    """Mean of the points (N, 3, mm) after dropping wild ones: start from the coordinate-wise
    median, keep the points within ``cutoff`` times the median distance (about 3.8 sigma of
    isotropic jitter), average them, repeat. A minority of wild samples does not move it.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError("robust_mean needs at least one point")
    center = np.median(points, axis=0)
    inliers = np.ones(len(points), dtype=bool)
    for _ in range(iterations):
        distance = np.linalg.norm(points - center, axis=1)
        scale = max(float(np.median(distance)), 1e-3)
        new_inliers = distance <= cutoff * scale
        if np.count_nonzero(new_inliers) < max(1, len(points) // 2):
            new_inliers = distance <= np.median(distance)
        center = points[new_inliers].mean(axis=0)
        if np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    spread = float(np.sqrt(np.mean(np.sum((points[inliers] - center) ** 2, axis=1))))
    return RobustMean(center, inliers, spread)


def robust_mean_direction(vectors: np.ndarray, cutoff: float = 2.5) -> tuple[np.ndarray, float]:
    """Robust mean of unit vectors (N, 3): the unit mean direction and the RMS angle (degrees)
    of the inliers from it. Wild orientations (a minority) are dropped as in :func:`robust_mean`.
    """
    vectors = np.asarray(vectors, dtype=float).reshape(-1, 3)
    vectors = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    result = robust_mean(vectors, cutoff)
    direction = result.mean / np.linalg.norm(result.mean)
    cos = np.clip(vectors[result.inliers] @ direction, -1.0, 1.0)
    return direction, float(np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2))))


def good_quality_mask(quality: np.ndarray, max_quality: float | None = None) -> np.ndarray:
    """Samples whose tracker quality number is acceptable (0 = best; NaN = unknown = accepted).

    ``max_quality`` None: an automatic limit, far above the recording's typical values
    (median + 8 robust sigma, at least twice the median plus one), so only the clearly
    disturbed samples go.
    """
    quality = np.asarray(quality, dtype=float)
    known = np.isfinite(quality)
    if max_quality is None:
        if not np.any(known):
            return np.ones(len(quality), dtype=bool)
        median = float(np.median(quality[known]))
        mad = float(np.median(np.abs(quality[known] - median)))
        max_quality = max(median + 8 * 1.4826 * mad, 2 * median + 1.0)
    return ~known | (quality <= max_quality)


def _usable_samples(time_s: np.ndarray, position_mm: np.ndarray, quality: np.ndarray | None,
                    settings: DwellSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``time_s`` (N,) and ``position_mm`` (N, 3) as float arrays, and the mask of samples a dwell may use:
    finite time and position, and an acceptable quality number (:func:`good_quality_mask`)."""
    time_s = np.asarray(time_s, dtype=float)
    position_mm = np.asarray(position_mm, dtype=float).reshape(-1, 3)
    valid = np.all(np.isfinite(position_mm), axis=1) & np.isfinite(time_s)
    if quality is not None:
        valid &= good_quality_mask(quality, settings.max_quality)
    return time_s, position_mm, valid


def find_dwells(
    time_s: np.ndarray,
    position_mm: np.ndarray,
    labels: np.ndarray | None = None,
    quality: np.ndarray | None = None,
    settings: DwellSettings | None = None,
    source: str = "the recording",
    section: str = "calibration",
) -> list[Dwell]:
    """The dwells of one probe track, in time order.

    ``time_s`` (N,) sorted, ``position_mm`` (N, 3) in one frame (normally Reference),
    ``labels`` (N,) strings (empty while moving) or None, ``quality`` (N,) or None.
    When any label is present the dwells are the labelled runs; otherwise they are found
    automatically (:func:`still_periods`). Bad-quality samples are never part of a dwell. A labelled
    dwell in which the probe moves is refused (:func:`refuse_moving_labels`; ``source`` names the
    recording and ``section`` the settings table in the message).
    """
    settings = settings or DwellSettings()
    time_s, position_mm, valid = _usable_samples(time_s, position_mm, quality, settings)
    if labels is not None:
        labels = np.asarray(["" if v is None else str(v).strip() for v in labels], dtype=object)
        if any(labels[valid]):
            dwells = labelled_dwells(time_s, labels, valid, settings)
            refuse_moving_labels(dwells, position_mm, settings, source, section)
            return dwells
    return still_periods(time_s, position_mm, valid, settings)


def label_motion_mm(points: np.ndarray) -> tuple[float, float]:
    """How far a labelled dwell's probe moves (mm): the distance from the samples' median within which three
    quarters of them lie (a minority of wild samples does not count), and the drift (:func:`_drift`)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    spread = float(np.percentile(np.linalg.norm(points - np.median(points, axis=0), axis=1), 75))
    return spread, _drift(points)


def refuse_moving_labels(dwells: list[Dwell], position_mm: np.ndarray, settings: DwellSettings,
                         source: str = "the recording", section: str = "calibration") -> None:
    """Refuse (:class:`~EMRegModule.errors.EMRegError`) a labelled dwell in which the probe does not stay still:
    its samples spread, or drift, farther than :data:`LABEL_SPREAD_FACTOR` x ``still_radius_mm`` (a probe moving
    10 mm, or every row of a recording given one label): its average would be a plausible, wrong point.
    ``position_mm`` (N, 3) in the frame the dwells were found in."""
    limit = LABEL_SPREAD_FACTOR * settings.still_radius_mm
    for dwell in dwells:
        spread, drift = label_motion_mm(position_mm[dwell.indices])
        if max(spread, drift) > limit:
            raise EMRegError(
                f"{source}: the probe is not still during the dwell labelled {dwell.label!r} "
                f"({dwell.start_s:.2f}-{dwell.end_s:.2f} s, {len(dwell)} samples): three quarters of its samples "
                f"lie within {spread:.1f} mm of their median and it drifts {drift:.1f} mm, more than "
                f"{limit:g} mm ({LABEL_SPREAD_FACTOR:g} x [{section}] still_radius_mm); label only the samples where "
                "the probe is held still")


def labelled_dwells(time_s: np.ndarray, labels: np.ndarray, valid: np.ndarray,
                    settings: DwellSettings | None = None) -> list[Dwell]:
    """Runs of consecutive valid samples carrying the same non-empty label (bad samples inside
    a run are skipped, not splitting it); runs with fewer than ``min_samples`` are dropped."""
    settings = settings or DwellSettings()
    index = np.nonzero(valid & (labels != ""))[0]
    if len(index) == 0:
        return []
    # A run ends where the label changes or an unlabelled valid sample intervenes.
    valid_index = np.nonzero(valid)[0]
    position_in_valid = np.searchsorted(valid_index, index)
    breaks = (labels[index[1:]] != labels[index[:-1]]) | (np.diff(position_in_valid) > 1)
    starts = np.concatenate([[0], np.nonzero(breaks)[0] + 1])
    ends = np.concatenate([starts[1:], [len(index)]])
    dwells = []
    for s, e in zip(starts, ends, strict=True):
        members = index[s:e]
        if len(members) >= settings.min_samples:
            dwells.append(Dwell(members, str(labels[members[0]]), float(time_s[members[0]]),
                                float(time_s[members[-1]])))
    return dwells


def still_periods(time_s: np.ndarray, position_mm: np.ndarray, valid: np.ndarray | None = None,
                  settings: DwellSettings | None = None) -> list[Dwell]:
    """Periods when the probe stays still, found without labels (see :class:`DwellSettings`).

    Stillness of a sample: the median distance of the valid samples in a window around it
    from their coordinate-wise median (robust to wild samples). Still runs interrupted by
    a short gap at the same place are joined; runs shorter than ``min_duration_s`` dropped.
    """
    settings = settings or DwellSettings()
    time_s = np.asarray(time_s, dtype=float)
    valid = np.ones(len(time_s), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    index = np.nonzero(valid)[0]
    if len(index) < max(3, settings.min_samples):
        return []
    t = time_s[index]
    p = position_mm[index]
    dt = np.diff(t)
    step = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    k = int(np.clip(round(settings.window_s / step), 3, len(index)))
    windows = np.lib.stride_tricks.sliding_window_view(p, k, axis=0)  # (W, 3, k)
    centre = np.median(windows, axis=2)
    spread = np.median(np.linalg.norm(windows - centre[:, :, None], axis=1), axis=1)
    # Each window's verdict goes to its centre sample; the first and last half windows take
    # the verdict of the first and last full window.
    half = k // 2
    centred = np.concatenate([np.full(half, spread[0]), spread, np.full(len(index) - half - len(spread), spread[-1])])
    still = centred <= settings.still_radius_mm
    runs = _runs(still)
    periods: list[tuple[int, int]] = []  # [start, end) in valid-sample positions
    for s, e in runs:
        if periods:
            ps, pe = periods[-1]
            gap = t[s] - t[pe - 1]
            if gap <= settings.max_gap_s and np.linalg.norm(
                    np.median(p[ps:pe], axis=0) - np.median(p[s:e], axis=0)) <= max(2 * settings.still_radius_mm, 1.0):
                periods[-1] = (ps, e)
                continue
        periods.append((s, e))
    dwells = []
    for s, e in periods:
        # The window's verdict spills half a window into the slow ends of the approach and the
        # departure: trim the ends to the samples near the period's median before measuring it.
        near = np.flatnonzero(np.linalg.norm(p[s:e] - np.median(p[s:e], axis=0), axis=1)
                              <= TRIM_FACTOR * settings.still_radius_mm)
        if len(near) == 0:
            continue
        s, e = s + int(near[0]), s + int(near[-1]) + 1
        if e - s < settings.min_samples or t[e - 1] - t[s] < settings.min_duration_s:
            continue
        if _drift(p[s:e]) > settings.drift_limit_mm:
            continue
        members = index[s:e]
        dwells.append(Dwell(members, "", float(t[s]), float(t[e - 1])))
    return dwells


def _drift(points: np.ndarray) -> float:
    """Distance (mm) between the medians of the first and the last quarter of a still period:
    near zero for a probe held still (even hand-held), the distance travelled for slow motion."""
    quarter = max(1, len(points) // 4)
    return float(np.linalg.norm(np.median(points[:quarter], axis=0) - np.median(points[-quarter:], axis=0)))


def describe_still_periods(time_s: np.ndarray, position_mm: np.ndarray, quality: np.ndarray | None = None,
                           settings: DwellSettings | None = None, places: np.ndarray | None = None,
                           place_name: str = "target", section: str = "evaluation", limit: int = 5) -> str:
    """What a dwell search that found nothing did find, for the error message: the still periods
    of any length (durations, drift, distance to the nearest of ``places`` (K, 3) in the same
    frame) and which ``[section]`` setting would accept them.
    """
    settings = settings or DwellSettings()
    time_s, position_mm, valid = _usable_samples(time_s, position_mm, quality, settings)
    loose = replace(settings, min_duration_s=1e-9, min_samples=3, max_drift_mm=np.inf)
    periods = still_periods(time_s, position_mm, valid, loose)
    rule = (f"a dwell must last {settings.min_duration_s:g} s ([{section}] min_duration_s) with the probe within "
            f"{settings.still_radius_mm:g} mm ([{section}] still_radius_mm) and drifting less than "
            f"{settings.drift_limit_mm:g} mm")
    if not periods:
        return (f"the probe was never still ({int(np.count_nonzero(valid))} usable samples over "
                f"{float(np.ptp(time_s[valid])) if np.any(valid) else 0.0:.1f} s); {rule}; "
                f"raise [{section}] still_radius_mm if the probe was hand-held")
    periods = sorted(periods, key=lambda d: -d.duration_s)
    parts = []
    for dwell in periods[:limit]:
        points = position_mm[dwell.indices]
        text = f"{dwell.duration_s:.2f} s (drift {_drift(points):.1f} mm"
        if places is not None and len(places):
            distance = float(np.min(np.linalg.norm(np.asarray(places, dtype=float) - np.median(points, axis=0),
                                                   axis=1)))
            text += f", {distance:.1f} mm from the nearest {place_name}"
        parts.append(text + ")")
    more = f" and {len(periods) - limit} shorter" if len(periods) > limit else ""
    longest = periods[0].duration_s
    most = max(len(d) for d in periods)
    if longest < settings.min_duration_s:
        hint = f"lower [{section}] min_duration_s (e.g. to {max(0.05, np.floor(longest * 20) / 20 - 0.05):.2f})"
    elif most < settings.min_samples:
        hint = (f"but a dwell needs {settings.min_samples} samples ([{section}] min_samples) and the fullest has "
                f"{most}: lower [{section}] min_samples")
    else:
        hint = f"raise [{section}] still_radius_mm or max_drift_mm"
    return (f"{len(periods)} still period(s) found: {', '.join(parts)}{more}; {rule}; {hint}")




def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of the runs of True in a boolean array."""
    padded = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def group_by_place(centres: np.ndarray, radius_mm: float) -> np.ndarray:
    """Group ids (first-seen order, 0..G-1) for points (N, 3) closer than ``radius_mm`` to a
    group's first point (single pass in the given order: dwells are far apart or together)."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    group = np.full(len(centres), -1, dtype=int)
    anchors: list[np.ndarray] = []
    for i, c in enumerate(centres):
        if anchors:
            d = np.linalg.norm(np.asarray(anchors) - c, axis=1)
            j = int(np.argmin(d))
            if d[j] <= radius_mm:
                group[i] = j
                continue
        anchors.append(c)
        group[i] = len(anchors) - 1
    return group
