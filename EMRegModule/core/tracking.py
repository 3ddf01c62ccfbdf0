"""Tracking samples: one trakSTAR recording in memory, and its frame arithmetic.

A :class:`TrackingRecording` holds rows of sensor poses in the Tracker frame (the
transmitter, paper S_w) exactly as the tracker reports them: ``SensorToTracker``.
Probe samples are expressed in the Reference frame (the Model 800 sensor fixed in the
fiducial frame, paper S_p) with paper Eq. 3-5: ``ProbeToReference = inv(ReferenceToTracker)
@ ProbeToTracker`` at the same moment, so a frame or transmitter that moves between
dwells changes nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import EMRegError
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from .transforms import invert_rigid

#: Reference and probe rows of one moment share ``time_s`` within this tolerance (spec).
SAME_MOMENT_S = 1e-3

#: Time stamps are decimal text read into binary floating point: two stamps written exactly 1 ms apart can read
#: a little more than ``SAME_MOMENT_S`` apart (0.42 and 0.421: 1.0000000000000009 ms; near epoch times of
#: 1.7e9 s, up to 2.4e-7 s more). Same-moment comparisons allow this much beyond ``SAME_MOMENT_S``.
TIME_STAMP_SLACK_S = 1e-6

#: The largest difference (s) of two time stamps of one moment, as compared: ``SAME_MOMENT_S`` plus the slack.
SAME_MOMENT_LIMIT_S = SAME_MOMENT_S + TIME_STAMP_SLACK_S

#: A recording with nothing recorded for longer than this (s) is split there into segments (with a warning).
MAX_GAP_S = 2.0

#: More clock resets than this in one recording are not resets: its rows are out of time order (a file sorted by
#: another column, or shuffled), and they are read by their time stamps instead (with a warning).
MAX_CLOCK_RESETS = 10

#: A sensor with at least this many samples whose median step between samples exceeds ``MAX_GAP_S`` is not
#: sampled in seconds (a tracker samples tens of times a second): ``time_s`` holds milliseconds (or finer).
MIN_SAMPLES_FOR_RATE = 20

#: Consecutive segments are this far apart (s) on a recording's timeline (more than any dwell gap).
SEGMENT_SEPARATION_S = 2.0

#: The probe must move at least this far (mm, spread about its median) relative to the reference over a
#: recording; a probe that never moves relative to the reference is a port mistake (or a second sensor on
#: the frame).
MIN_PROBE_SPREAD_MM = 2.0

#: Ports look swapped when the "reference" spreads in the Tracker frame more than this factor times the
#: "probe" and by more than ``SWAP_MIN_SPREAD_MM``.
SWAP_SPREAD_FACTOR = 3.0
SWAP_MIN_SPREAD_MM = 10.0

#: Every sensor position of a recording within this distance (mm) of the tracker's origin means the file is in
#: metres: a sensor cannot sit inside the transmitter (it is tens of millimetres or more away).
METRES_LIKE_MM = 5.0


@dataclass
class TrackingRecording:
    """Sensor samples (rows) of a tracking recording, all poses ``SensorToTracker``.

    Attributes: ``time_s`` (N,), ``sensor`` (N,) port numbers 1..4, ``position_mm`` (N, 3),
    ``rotation`` (N, 3, 3) sensor axes in Tracker axes, ``quality`` (N,) NaN when unknown
    (0 = best), ``label`` (N,) strings, empty while the probe moves.
    """

    time_s: np.ndarray
    sensor: np.ndarray
    position_mm: np.ndarray
    rotation: np.ndarray
    quality: np.ndarray
    label: np.ndarray
    source: str = "recording"
    orientation_format: str = field(default="angles")  # "angles" or "quaternion" (as read / to write)
    #: (N,) time segment of each row (0, 1, ...): a time reset or a long gap starts a new one
    segment: np.ndarray | None = None
    #: what reading found and kept (time resets, gaps), one line each
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        n = len(self.time_s)
        self.segment = np.zeros(n, dtype=int) if self.segment is None else np.asarray(self.segment, dtype=int)
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.sensor = np.asarray(self.sensor, dtype=int)
        self.position_mm = np.asarray(self.position_mm, dtype=float).reshape(n, 3)
        self.rotation = np.asarray(self.rotation, dtype=float).reshape(n, 3, 3)
        self.quality = np.asarray(self.quality, dtype=float).reshape(n)
        self.label = np.asarray(self.label, dtype=object).reshape(n)

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sensors(self) -> list[int]:
        """Sorted port numbers present in the recording."""
        return sorted(int(s) for s in np.unique(self.sensor))

    def select(self, mask: np.ndarray) -> TrackingRecording:
        """The rows where ``mask`` (boolean or index array) holds."""
        return TrackingRecording(
            self.time_s[mask], self.sensor[mask], self.position_mm[mask], self.rotation[mask],
            self.quality[mask], self.label[mask], self.source, self.orientation_format, self.segment[mask],
            list(self.warnings),
        )

    @property
    def timeline_s(self) -> np.ndarray:
        """Times (s) made increasing across segments: segment k is moved to start
        ``SEGMENT_SEPARATION_S`` after segment k-1 ends when it would not (a time reset); within a
        segment the times are the recorded ones shifted by one constant."""
        if len(self) == 0 or not np.any(self.segment):
            return self.time_s
        timeline = self.time_s.astype(float).copy()
        end = None
        for k in np.unique(self.segment):
            rows = self.segment == k
            start = float(np.min(self.time_s[rows]))
            if end is not None and start < end + SEGMENT_SEPARATION_S:
                timeline[rows] += end + SEGMENT_SEPARATION_S - start
            end = float(np.max(timeline[rows]))
        return timeline

    def for_sensor(self, port: int, role: str = "sensor") -> TrackingRecording:
        """Rows of one sensor port, in time order; :class:`EMRegError` if the port has none."""
        mask = self.sensor == port
        if not np.any(mask):
            raise EMRegError(
                f"{self.source}: no samples from the {role} sensor on port {port} "
                f"(ports present: {self.sensors}); set the port with --{role}-sensor or in case.toml [sensors]"
            )
        rows = self.select(mask)
        order = np.argsort(rows.timeline_s, kind="stable")
        return rows.select(order)

    def transforms(self) -> np.ndarray:
        """``SensorToTracker`` 4x4 matrices (N, 4, 4)."""
        out = np.zeros((len(self), 4, 4))
        out[:, :3, :3] = self.rotation
        out[:, :3, 3] = self.position_mm
        out[:, 3, 3] = 1.0
        return out


@dataclass
class ProbeInReference:
    """Probe samples expressed in the Reference frame, one per probe sample with a reference partner.

    ``probe_to_reference`` (N, 4, 4); ``time_s``, ``quality`` (worst of the two sensors),
    ``label`` (the probe row's label) and ``reference_to_tracker`` (N, 4, 4) alongside.
    """

    time_s: np.ndarray
    probe_to_reference: np.ndarray
    reference_to_tracker: np.ndarray
    quality: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def position_mm(self) -> np.ndarray:
        """Probe sensor origin in the Reference frame (N, 3)."""
        return self.probe_to_reference[:, :3, 3]

    @property
    def direction(self) -> np.ndarray:
        """Probe sensor +X axis in the Reference frame (N, 3) (the Model 90's long axis)."""
        return self.probe_to_reference[:, :3, 0]


def match_moments(
    reference: TrackingRecording, probe: TrackingRecording, tolerance_s: float = SAME_MOMENT_S
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (reference_index, probe_index) of rows taken at the same moment.

    Both inputs are time-sorted single-sensor recordings. Each probe row is paired with the
    nearest reference row when they are within ``tolerance_s`` (plus ``TIME_STAMP_SLACK_S``, the round-off of
    decimal time stamps); other probe rows are dropped.
    """
    if len(reference) == 0 or len(probe) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    reference_time, probe_time = reference.timeline_s, probe.timeline_s
    right = np.searchsorted(reference_time, probe_time)
    right = np.clip(right, 0, len(reference) - 1)
    left = np.clip(right - 1, 0, len(reference) - 1)
    pick_left = np.abs(reference_time[left] - probe_time) <= np.abs(reference_time[right] - probe_time)
    nearest = np.where(pick_left, left, right)
    same_moment = np.abs(reference_time[nearest] - probe_time) <= tolerance_s + TIME_STAMP_SLACK_S
    ok = same_moment & (reference.segment[nearest] == probe.segment)
    return nearest[ok], np.nonzero(ok)[0]


def probe_in_reference(
    recording: TrackingRecording, reference_port: int = DEFAULT_REFERENCE_PORT, probe_port: int = DEFAULT_PROBE_PORT,
    check_ports: bool = True,
) -> ProbeInReference:
    """Express every probe sample in the Reference frame at its own moment (paper Eq. 3-5).

    ``ProbeToReference = inv(ReferenceToTracker) @ ProbeToTracker``. Raises
    :class:`EMRegError` when a sensor is missing or no moment has both sensors, and for the port
    mistakes of :func:`sensor_pair` (unless ``check_ports`` is false: a synthetic recording whose
    probe is rigidly fixed to the reference).
    """
    reference, probe, ref_idx, probe_idx = sensor_pair(recording, reference_port, probe_port, check_ports)
    reference_to_tracker = reference.transforms()[ref_idx]
    if not np.all(np.isfinite(reference_to_tracker)):
        raise EMRegError(f"{recording.source}: the reference sensor (port {reference_port}) has samples without "
                         "an orientation; every sample is expressed in the Reference frame, which needs "
                         "the reference sensor's full pose")
    probe_to_tracker = probe.transforms()[probe_idx]
    tracker_to_reference = invert_rigid_batch(reference_to_tracker)
    probe_to_reference = tracker_to_reference @ probe_to_tracker
    quality = np.fmax(reference.quality[ref_idx], probe.quality[probe_idx])
    return ProbeInReference(
        probe.timeline_s[probe_idx], probe_to_reference, reference_to_tracker, quality, probe.label[probe_idx]
    )


def sensor_pair(recording: TrackingRecording, reference_port: int, probe_port: int, check_roles: bool = True
                ) -> tuple[TrackingRecording, TrackingRecording, np.ndarray, np.ndarray]:
    """The reference and probe rows (time-sorted) and their same-moment index pairs, with the ports checked.

    Refused with :class:`EMRegError` (one line, exit 2): the same port for both, a port absent from
    the recording, no common moment, a probe that never moves relative to the reference
    (``MIN_PROBE_SPREAD_MM``), and a "reference" that moves far more than the "probe" in the
    Tracker frame (swapped ports, ``SWAP_SPREAD_FACTOR``).
    """
    if int(reference_port) == int(probe_port):
        raise EMRegError(f"{recording.source}: the reference and the probe sensor are both port {reference_port}; "
                         "give two different ports (--reference-sensor / --probe-sensor or case.toml [sensors])")
    reference = recording.for_sensor(reference_port, "reference")
    probe = recording.for_sensor(probe_port, "probe")
    ref_idx, probe_idx = match_moments(reference, probe)
    if len(probe_idx) == 0:
        raise EMRegError(
            f"{recording.source}: no probe sample has a reference sample at the same time (within 1 ms)"
        )
    if check_roles:
        _check_roles(recording.source, reference, probe, ref_idx, probe_idx, reference_port, probe_port)
    return reference, probe, ref_idx, probe_idx


def _spread_mm(points: np.ndarray) -> float:
    """95th percentile distance (mm) of points from their median: how far a sensor travels, robustly."""
    if len(points) == 0:
        return 0.0
    return float(np.percentile(np.linalg.norm(points - np.median(points, axis=0), axis=1), 95))


def role_spreads(reference_position_mm: np.ndarray, reference_rotation: np.ndarray,
                 probe_position_mm: np.ndarray) -> tuple[float, float, float]:
    """How far each sensor travels (mm, 95th percentile distance from the median) at moments paired by time:
    the probe in the Reference frame, the reference in the Tracker frame, the probe in the Tracker frame.

    ``reference_position_mm`` (N, 3) and ``reference_rotation`` (N, 3, 3): ``ReferenceToTracker``;
    ``probe_position_mm`` (N, 3): the probe's origin in the Tracker frame at the same moments."""
    rotation_t = np.swapaxes(np.asarray(reference_rotation, dtype=float), 1, 2)
    reference_position_mm = np.asarray(reference_position_mm, dtype=float)
    probe_position_mm = np.asarray(probe_position_mm, dtype=float)
    relative = np.einsum("nij,nj->ni", rotation_t, probe_position_mm - reference_position_mm)
    return _spread_mm(relative), _spread_mm(reference_position_mm), _spread_mm(probe_position_mm)


def role_problem(spreads: tuple[float, float, float], reference_port: int, probe_port: int) -> tuple[str, str] | None:
    """The port mistake the spreads of :func:`role_spreads` show, as ``(kind, one-line message)``, or None.

    ``"still"``: the probe never moves relative to the reference (``MIN_PROBE_SPREAD_MM``): a second sensor on
    the frame, or the same sensor twice. ``"swapped"``: the "reference" moves far more than the "probe" in the
    Tracker frame (``SWAP_SPREAD_FACTOR``, ``SWAP_MIN_SPREAD_MM``). Offline recordings and live navigation
    judge with this one rule."""
    relative_spread, reference_spread, probe_spread = spreads
    if relative_spread < MIN_PROBE_SPREAD_MM:
        return "still", (
            f"the probe (port {probe_port}) never moves relative to the reference (port {reference_port}): "
            f"spread {relative_spread:.2f} mm < {MIN_PROBE_SPREAD_MM:g} mm; check the sensor ports")
    if reference_spread > SWAP_MIN_SPREAD_MM and reference_spread > SWAP_SPREAD_FACTOR * probe_spread:
        return "swapped", (
            f"the reference sensor (port {reference_port}) moves {reference_spread:.0f} mm in the tracker "
            f"frame, the probe (port {probe_port}) only {probe_spread:.0f} mm: the ports look swapped; check "
            "--reference-sensor / --probe-sensor or case.toml [sensors]")
    return None


def _check_roles(source: str, reference: TrackingRecording, probe: TrackingRecording, ref_idx: np.ndarray,
                 probe_idx: np.ndarray, reference_port: int, probe_port: int) -> None:
    spreads = role_spreads(reference.position_mm[ref_idx], reference.rotation[ref_idx], probe.position_mm[probe_idx])
    problem = role_problem(spreads, reference_port, probe_port)
    extent = float(max(np.max(np.abs(reference.position_mm)), np.max(np.abs(probe.position_mm))))
    if problem is not None and problem[0] == "still" and extent < METRES_LIKE_MM:  # not a port mistake: the unit
        raise EMRegError(
            f"{source}: every position lies within {extent:.3g} of the tracker's origin: the recording looks like "
            "metres, and EMReg reads millimetres (a sensor sits tens of millimetres or more from the transmitter); "
            "scale the positions by 1000"
        )
    if problem is not None:
        raise EMRegError(f"{source}: {problem[1]}")


def split_time_segments(time_s: np.ndarray, sensor: np.ndarray, source: str = "recording",
                        first_line: int = 2, where: Callable[[int], str] | None = None
                        ) -> tuple[np.ndarray, list[str]]:
    """Segments of a recording in file order, and the warnings that say where and why it was split.

    The one rule for every recording format (tracking CSV, PLUS / Slicer sequence file): a new
    segment starts where a sensor's time goes back (a clock reset: the rows after it are kept, not
    merged with the earlier ones by time) and where nothing was recorded for more than
    ``MAX_GAP_S``. Within a segment each sensor's time must increase; a repeated or decreasing time
    that is not a reset of the whole recording is an :class:`EMRegError` naming the place. A sensor
    whose time goes back more than ``MAX_CLOCK_RESETS`` times is no clock being reset: the rows are
    out of order (sorted by another column, shuffled), so they are taken in the order of their times
    (a warning says so) and only a time seen twice for one sensor is refused.
    ``where(row)`` names a row's place in its file (default ``line {row + first_line}``; a sequence
    file says ``frame N``). Time stamps that are not seconds (a sensor's median step longer than
    ``MAX_GAP_S``: milliseconds) are refused with one line.
    """
    time_s = np.asarray(time_s, dtype=float)
    sensor = np.asarray(sensor, dtype=int)
    if where is None:
        def where(row: int) -> str:
            return f"line {row + first_line}"
    n = len(time_s)
    segment = np.zeros(n, dtype=int)
    warnings: list[str] = []
    if n == 0:
        return segment, warnings
    _check_seconds(time_s, sensor, source)
    order = np.lexsort((np.arange(n), sensor))  # by sensor, file order within
    same = sensor[order][1:] == sensor[order][:-1]
    backs = int(np.count_nonzero(same & (np.diff(time_s[order]) < 0)))
    in_time_order = backs > MAX_CLOCK_RESETS  # not a clock: rows out of order, read by their time stamps
    if in_time_order:
        warnings.append(f"{source}: the rows are not in time order (a sensor's time goes back {backs} times, more "
                        f"than {MAX_CLOCK_RESETS} clock resets): read in the order of time_s")
    elif backs:
        current, last = 0, {}
        for i, (t, s) in enumerate(zip(time_s.tolist(), sensor.tolist(), strict=True)):
            if s in last and t < last[s]:
                current += 1
                warnings.append(f"{source}: time goes back from {last[s]:.3f} s to {t:.3f} s at {where(i)} "
                                "(a clock reset): the rows after it are a separate time segment")
                last = {}
            last[s] = t
            segment[i] = current
    # long gaps (nothing from any sensor) split a segment too
    for k in range(int(segment.max()) + 1):
        rows = np.nonzero(segment == k)[0]
        times = np.unique(time_s[rows])
        gaps = np.nonzero(np.diff(times) > MAX_GAP_S)[0]
        if len(gaps) == 0:
            continue
        for g in gaps:
            warnings.append(f"{source}: nothing recorded for {times[g + 1] - times[g]:.1f} s after {times[g]:.3f} s "
                            f"(more than {MAX_GAP_S:g} s): the rows after it are a separate time segment")
        segment[rows] = segment[rows] * (n + 1) + np.searchsorted(times[gaps], time_s[rows], side="left")
    if warnings:
        segment = np.unique(segment, return_inverse=True)[1].reshape(n)
        # keep the segments in file order of first appearance (time order for rows out of order)
        visit = np.argsort(time_s, kind="stable") if in_time_order else np.arange(n)
        first = {int(segment[i]): k for k, i in reversed(list(enumerate(visit.tolist())))}
        rank = {v: r for r, v in enumerate(sorted(first, key=first.get))}
        segment = np.array([rank[int(v)] for v in segment.tolist()], dtype=int)
    # within a segment, each sensor's time must increase (in file order; rows out of order: no time twice)
    order = np.lexsort((time_s if in_time_order else np.arange(n), segment, sensor))
    same = (sensor[order][1:] == sensor[order][:-1]) & (segment[order][1:] == segment[order][:-1])
    bad = np.nonzero(same & (np.diff(time_s[order]) <= 0))[0]
    if len(bad):
        row = int(order[bad[0] + 1])
        raise EMRegError(f"{source}: {where(row)}: time {time_s[row]:.4f} s of sensor {sensor[row]} "
                         "does not increase (each sensor's time must increase within a recording)")
    return segment, warnings


def _check_seconds(time_s: np.ndarray, sensor: np.ndarray, source: str) -> None:
    """Refuse time stamps that are not seconds: a sensor sampled (median step) less often than every
    ``MAX_GAP_S`` over ``MIN_SAMPLES_FOR_RATE`` samples or more (every step would be a pause)."""
    for port in np.unique(sensor):
        times = np.unique(time_s[sensor == port])
        if len(times) < MIN_SAMPLES_FOR_RATE:
            continue
        step = float(np.median(np.diff(times)))
        if step > MAX_GAP_S:
            raise EMRegError(
                f"{source}: the samples of sensor {int(port)} are {step:.4g} apart in time (median): the time "
                f"stamps look like milliseconds, and EMReg reads seconds (a tracker samples tens of times a "
                "second); divide the times by 1000")


def invert_rigid_batch(a_to_b: np.ndarray) -> np.ndarray:
    """Inverse of a stack of rigid transforms (N, 4, 4), vectorised."""
    a_to_b = np.asarray(a_to_b, dtype=float)
    if a_to_b.ndim == 2:
        return invert_rigid(a_to_b)
    rotation_t = np.transpose(a_to_b[:, :3, :3], (0, 2, 1))
    b_to_a = np.zeros_like(a_to_b)
    b_to_a[:, :3, :3] = rotation_t
    b_to_a[:, :3, 3] = -np.einsum("nij,nj->ni", rotation_t, a_to_b[:, :3, 3])
    b_to_a[:, 3, 3] = 1.0
    return b_to_a
