"""Simulated trakSTAR recordings: reference sensor (port 1) and probe (port 2) at 80 Hz.

A recording is built as a sequence of visits: the probe travels (withdraw along the hole
axis, a curved hand-held path, insertion) and dwells still in a pinhole, a board hole or
on a target. True poses are kept in a rigid "Body" (the fiducial frame, or the Reference
for the board) whose ``BodyToTracker`` can change between dwells (the frame is bumped).

Errors, in the Tracker frame, with the trakSTAR's character:

- per-dwell systematic error of the probe (~0.35 mm, ~0.25 deg; interpolated through
  transitions), a smaller constant one for the reference per static pose;
- per-sample jitter (~0.1 mm, ~0.1 deg), temporally correlated (AR(1)) as the tracker's
  filters make it;
- quality numbers mostly 0..3, and rare bad samples (quality 40..250) with a wild pose;
- labels on dwell rows (optional), empty while moving.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation, Slerp

from ..core.tracking import TrackingRecording
from ..core.transforms import axis_angle_to_rotation, random_rotation
from .distortion import FieldDistortion

RATE_HZ = 80.0
REFERENCE_PORT = 1
PROBE_PORT = 2


@dataclass
class NoiseModel:
    """Error magnitudes (mm, degrees; per axis standard deviations unless stated)."""

    probe_dwell_mm: float = 0.22
    probe_dwell_deg: float = 0.25
    probe_jitter_mm: float = 0.07
    probe_jitter_deg: float = 0.07
    reference_static_mm: float = 0.06
    reference_static_deg: float = 0.02
    reference_jitter_mm: float = 0.04
    reference_jitter_deg: float = 0.03
    correlation: float = 0.7  # AR(1) coefficient of the jitter, sample to sample
    bad_sample_rate: float = 0.002

    def scaled(self, factor: float) -> NoiseModel:
        """Every error magnitude times ``factor`` (correlation and bad-sample rate unchanged)."""
        values = {f.name: getattr(self, f.name) * factor for f in fields(self)
                  if f.name not in ("correlation", "bad_sample_rate")}
        return replace(self, **values)


@dataclass
class Visit:
    """One dwell: the probe pose in the Body (4x4), how long, and its label ('' = unlabelled)."""

    probe_to_body: np.ndarray
    duration_s: float
    label: str
    name: str  # the truth name (marker / hole / target), kept even when ``label`` is ''
    tremor_mm: float = 0.0  # hand-held wobble during the dwell (0 in a pinhole)
    #: a tool's tip in the probe frame (3,) and the cone (full angle, degrees) its shaft swings through about the
    #: still tip during the dwell (0: the tool rests); the tip stays where ``probe_to_body`` puts it
    tip_mm: np.ndarray | None = None
    pivot_swing_deg: float = 0.0


@dataclass
class DwellTruth:
    name: str
    label: str
    start_s: float
    end_s: float


@dataclass
class ReferenceSlip:
    """The reference sensor slips in its slot once during a recording: from the transition sample nearest to
    ``at_fraction`` of the recording on, the sensor sits at ``ReferenceAfterToReferenceBefore``
    (``reference_after_to_before``, 4x4, mm) in its former pose; :func:`simulate_session` sets ``time_s``."""

    at_fraction: float
    reference_after_to_before: np.ndarray
    time_s: float | None = None


@dataclass
class FrameBump:
    """The frame (with the reference sensor in its slot and the patient) is knocked once, between two samples,
    from the transition sample nearest to ``at_fraction`` of the recording on: it sits at ``BodyAfterToBodyBefore``
    (``body_after_to_before``, 4x4, mm) in its former pose. Nothing navigated changes (everything moved together);
    the reference jumps as in a slip. :func:`simulate_session` sets ``time_s``."""

    at_fraction: float
    body_after_to_before: np.ndarray
    time_s: float | None = None


@dataclass
class FieldOnset:
    """A metal object rolled in once during a recording: its effect starts at the transition sample nearest to
    ``at_fraction`` of the recording (and ramps up over the object's ``ramp_s``); :func:`simulate_session` sets
    ``time_s`` (s, the recording's clock) and the distortion's ``onset_s``."""

    at_fraction: float
    time_s: float | None = None


@dataclass
class _Track:
    time_s: list = field(default_factory=list)
    probe_to_body: list = field(default_factory=list)
    body_to_tracker: list = field(default_factory=list)
    dwell_index: list = field(default_factory=list)
    label: list = field(default_factory=list)


def probe_rotation_into(direction_in: np.ndarray, spin_rad: float, tilt_deg: float = 0.0,
                        rng: np.random.Generator | None = None) -> np.ndarray:
    """Probe axes (3x3, columns in the Body) with +X along ``direction_in`` (tip first, into the hole).

    ``spin_rad`` turns the probe about its own axis; ``tilt_deg`` (with ``rng``) tilts it
    by up to that angle in a random direction.
    """
    x = np.asarray(direction_in, dtype=float)
    x = x / np.linalg.norm(x)
    if tilt_deg > 0 and rng is not None:
        helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        perp = np.cross(x, helper)
        perp /= np.linalg.norm(perp)
        perp = axis_angle_to_rotation(x, rng.uniform(0, 2 * np.pi)) @ perp
        x = axis_angle_to_rotation(perp, np.radians(rng.uniform(0, tilt_deg))) @ x
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    y = axis_angle_to_rotation(x, spin_rad) @ y
    z = np.cross(x, y)
    return np.column_stack([x, y, z])


def _min_jerk(n: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _smooth_noise(rng: np.random.Generator, n: int, sigma: float, correlation: float = 0.97) -> np.ndarray:
    """(n, 3) smooth random wobble of standard deviation ``sigma`` (AR(1) with high correlation)."""
    if n == 0 or sigma <= 0:
        return np.zeros((n, 3))
    white = rng.normal(0.0, sigma * np.sqrt(1 - correlation**2), size=(n, 3))
    out = lfilter([1.0], [1.0, -correlation], white, axis=0)
    return out - np.linspace(out[0], out[-1], n) if n > 1 else out  # start and end on the path


def _travel(rng: np.random.Generator, start: np.ndarray, end: np.ndarray, out_start: np.ndarray,
            out_end: np.ndarray, centre: np.ndarray, lift_mm: float, hesitate: bool) -> list[np.ndarray]:
    """Probe poses (4x4 in the Body) from ``start`` to ``end``: withdraw, curved travel, insert."""
    p0, p1 = start[:3, 3], end[:3, 3]
    a, b = p0 + out_start * lift_mm, p1 + out_end * lift_mm
    distance = float(np.linalg.norm(b - a))
    n_out = int(RATE_HZ * rng.uniform(0.25, 0.45))
    n_in = int(RATE_HZ * rng.uniform(0.3, 0.5))
    n_travel = max(8, int(RATE_HZ * (0.5 + distance / rng.uniform(150.0, 250.0))))
    mid_dir = (a + b) / 2 - centre
    mid_dir = mid_dir / (np.linalg.norm(mid_dir) + 1e-9)
    bulge = rng.uniform(0.1, 0.3) * distance + rng.uniform(5.0, 20.0)
    s_out, s_in, s_tr = _min_jerk(n_out), _min_jerk(n_in), _min_jerk(n_travel)
    path = [p0 + (a - p0) * s for s in s_out]
    wobble = _smooth_noise(rng, n_travel, 0.8)
    travel = [a + (b - a) * s + mid_dir * bulge * np.sin(np.pi * s) + wobble[i] for i, s in enumerate(s_tr)]
    if hesitate:  # a short pause in mid-air, hand-held (not a dwell)
        k = n_travel // 2
        pause = int(RATE_HZ * rng.uniform(0.15, 0.3))
        held = travel[k] + _smooth_noise(rng, pause, 0.3)
        travel = travel[:k] + list(held) + travel[k:]
    path += travel
    path += [b + (p1 - b) * s for s in s_in]
    rotations = Rotation.from_matrix(np.stack([start[:3, :3], end[:3, :3]]))
    slerp = Slerp([0.0, 1.0], rotations)
    n_rot_travel = len(travel)
    phase = np.concatenate([np.zeros(n_out), _min_jerk(n_rot_travel), np.ones(n_in)])
    mats = slerp(np.clip(phase, 0, 1)).as_matrix()
    out = []
    for p, r in zip(path, mats, strict=True):
        t = np.eye(4)
        t[:3, :3] = r
        t[:3, 3] = p
        out.append(t)
    return out[1:-1]  # the dwells themselves hold the end poses


def pivot_poses(probe_to_body: np.ndarray, tip_mm: np.ndarray | None, swing_deg: float, n: int,
                rng: np.random.Generator | None = None, turns: float = 2.0) -> np.ndarray:
    """(n, 4, 4) sensor poses ``ProbeToBody`` of a tool pivoting about its still tip: the shaft tilts away from
    its start (``probe_to_body``) by up to half of ``swing_deg`` and back, going ``turns`` times round a cone
    about the start's shaft, starting at a random phase; the tip (``tip_mm``, probe frame) never moves. No tip
    or no swing: ``probe_to_body`` n times."""
    start = np.asarray(probe_to_body, dtype=float)
    if tip_mm is None or swing_deg <= 0 or n < 2:
        return np.repeat(start[None], n, axis=0)
    tip_mm = np.asarray(tip_mm, dtype=float)
    tip_body = start[:3, :3] @ tip_mm + start[:3, 3]
    shaft = start[:3, :3] @ tip_mm
    shaft /= np.linalg.norm(shaft)
    helper = np.array([0.0, 0.0, 1.0]) if abs(shaft[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(shaft, helper)
    u /= np.linalg.norm(u)
    v = np.cross(shaft, u)
    phase0 = 0.0 if rng is None else float(rng.uniform(0, 2 * np.pi))
    s = np.linspace(0.0, 1.0, n)
    tilt = np.radians(swing_deg / 2.0) * np.sin(np.pi * s) ** 0.5  # out quickly, round the cone, back
    phase = phase0 + 2 * np.pi * turns * s
    out = np.empty((n, 4, 4))
    for k in range(n):
        axis = np.cos(phase[k]) * u + np.sin(phase[k]) * v
        rotation = axis_angle_to_rotation(axis, float(tilt[k])) @ start[:3, :3]
        out[k] = np.eye(4)
        out[k, :3, :3] = rotation
        out[k, :3, 3] = tip_body - rotation @ tip_mm
    return out


def _interpolate_pose(a_to_b_start: np.ndarray, a_to_b_end: np.ndarray, n: int) -> list[np.ndarray]:
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a_to_b_start[:3, :3], a_to_b_end[:3, :3]])))
    s = _min_jerk(n)
    mats = slerp(s).as_matrix()
    out = []
    for k in range(n):
        t = np.eye(4)
        t[:3, :3] = mats[k]
        t[:3, 3] = a_to_b_start[:3, 3] + (a_to_b_end[:3, 3] - a_to_b_start[:3, 3]) * s[k]
        out.append(t)
    return out


def simulate_session(rng: np.random.Generator, visits: list[Visit], body_to_tracker: np.ndarray,
                     reference_to_body: np.ndarray, centre_body: np.ndarray, lift_mm: float = 25.0,
                     bump_before: dict[int, np.ndarray] | None = None, hesitation_rate: float = 0.0,
                     noise: NoiseModel | None = None, start_time_s: float = 0.0,
                     reference_slip: ReferenceSlip | None = None,
                     distortion: FieldDistortion | None = None, distortion_onset: FieldOnset | None = None,
                     frame_bump: FrameBump | None = None,
                     ) -> tuple[TrackingRecording, list[DwellTruth], list[np.ndarray]]:
    """A recording of the probe visiting ``visits`` in turn with the reference sensor recorded alongside.

    ``bump_before[i]``: the new ``BodyToTracker`` that takes effect during the transition
    into visit ``i`` (the frame was bumped). ``reference_slip``: the reference sensor slips in
    its slot once, between two samples while the probe moves (its ``time_s`` is set to the first
    sample after the slip). ``distortion``: a metal object distorting the field (both sensors, at
    its strength at each sample's time; :mod:`.distortion`); ``distortion_onset``: when it is rolled in (a
    transition sample, like the slip; its ``time_s`` is set); ``frame_bump``: the frame knocked at once (a
    transition sample; its ``time_s`` is set). Returns the recording (reported poses), the dwell periods, and the
    ``BodyToTracker`` of each visit (before a knock of ``frame_bump``).
    """
    noise = noise or NoiseModel()
    bump_before = bump_before or {}
    track = _Track()
    current_body = np.asarray(body_to_tracker, dtype=float)
    visit_body_to_tracker = []
    dwells: list[DwellTruth] = []

    def add(pose_body: np.ndarray, body: np.ndarray, dwell: int, label: str) -> None:
        track.time_s.append(start_time_s + len(track.time_s) / RATE_HZ)
        track.probe_to_body.append(pose_body)
        track.body_to_tracker.append(body)
        track.dwell_index.append(dwell)
        track.label.append(label)

    # start: the probe is already on its way from well away from the first hole (never held still
    # outside a hole, which an unlabelled recording would show as a dwell)
    first = visits[0].probe_to_body
    approach = first.copy()
    approach[:3, 3] = first[:3, 3] - first[:3, 0] * 120.0 + rng.normal(0, 30.0, 3)
    previous = approach
    for i, visit in enumerate(visits):
        out_prev = -previous[:3, 0]
        out_next = -visit.probe_to_body[:3, 0]
        path = _travel(rng, previous, visit.probe_to_body, out_prev, out_next, centre_body, lift_mm,
                       hesitate=bool(rng.random() < hesitation_rate))
        bumped = bump_before.get(i)
        bump_at = len(path) // 2
        for k, p in enumerate(path):
            if bumped is not None and k == bump_at:
                for b in _interpolate_pose(current_body, bumped, int(RATE_HZ * 0.25)):
                    add(p, b, -1, "")
                current_body = bumped
            add(p, current_body, -1, "")
        n = max(4, int(round(visit.duration_s * RATE_HZ)))
        start = len(track.time_s)
        tremor = _smooth_noise(rng, n, visit.tremor_mm, 0.95)
        swing = pivot_poses(visit.probe_to_body, visit.tip_mm, visit.pivot_swing_deg, n, rng)
        for k in range(n):
            p = swing[k].copy()
            p[:3, 3] += tremor[k]
            add(p, current_body, i, visit.label)
        dwells.append(DwellTruth(visit.name, visit.label, track.time_s[start], track.time_s[-1]))
        visit_body_to_tracker.append(current_body)
        previous = visit.probe_to_body
    leave = previous.copy()
    leave[:3, 3] = previous[:3, 3] - previous[:3, 0] * 100.0
    n_leave = int(RATE_HZ * 0.8)
    for k in range(1, n_leave + 1):  # pulled out and away at a steady speed, not coming to rest
        p = previous.copy()
        p[:3, 3] += (leave[:3, 3] - previous[:3, 3]) * k / n_leave
        add(p, current_body, -1, "")
    slip_index = None
    if reference_slip is not None:
        slip_index = _event_index(track, reference_slip.at_fraction)
        reference_slip.time_s = float(track.time_s[slip_index])
    if distortion is not None and distortion_onset is not None:
        distortion_onset.time_s = float(track.time_s[_event_index(track, distortion_onset.at_fraction)])
        distortion = replace(distortion, onset_s=distortion_onset.time_s)
    if frame_bump is not None:
        bump_index = _event_index(track, frame_bump.at_fraction)
        frame_bump.time_s = float(track.time_s[bump_index])
        track.body_to_tracker[bump_index:] = [b @ frame_bump.body_after_to_before
                                              for b in track.body_to_tracker[bump_index:]]
    recording = _report(rng, track, np.asarray(reference_to_body, dtype=float), noise, len(visits),
                        None if reference_slip is None else (slip_index, reference_slip.reference_after_to_before),
                        distortion)
    return recording, dwells, visit_body_to_tracker


def _event_index(track: _Track, at_fraction: float) -> int:
    """The sample, while the probe moves, nearest to ``at_fraction`` of the recording (an event's first sample)."""
    moving = np.flatnonzero(np.asarray(track.dwell_index) < 0)
    return int(moving[np.argmin(np.abs(moving - at_fraction * len(track.time_s)))])


#: Probe conventions the simulator can write (see :mod:`EMRegModule.core.probe_axis`).
PROBE_CONVENTIONS = ("+x_in", "+x_out", "none")


def apply_probe_convention(recording: TrackingRecording, convention: str,
                           probe_port: int = PROBE_PORT) -> TrackingRecording:
    """The recording as a probe of another convention reports it (the sensor centre unchanged).

    ``+x_in``: unchanged (+X into the hole, tip first); ``+x_out``: the sensor turned end for
    end in its holder (180 degrees about its Z axis: +X points out of the hole);
    ``none``: the probe rows carry a position only (no angles).
    """
    if convention not in PROBE_CONVENTIONS:
        raise ValueError(f"probe convention must be one of {PROBE_CONVENTIONS}, got {convention!r}")
    if convention == "+x_in":
        return recording
    rotation = recording.rotation.copy()
    probe = recording.sensor == probe_port
    if convention == "+x_out":
        rotation[probe] = rotation[probe] @ np.diag([-1.0, -1.0, 1.0])
    else:
        rotation[probe] = np.nan
    return TrackingRecording(recording.time_s, recording.sensor, recording.position_mm, rotation,
                             recording.quality, recording.label, recording.source, recording.orientation_format)


def _rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rotvec).as_matrix()


def _report(rng: np.random.Generator, track: _Track, reference_to_body: np.ndarray, noise: NoiseModel,
            n_visits: int, slip: tuple[int, np.ndarray] | None = None,
            distortion: FieldDistortion | None = None) -> TrackingRecording:
    """Apply the tracker's errors to the true poses (a slip of the reference first, then the field's
    distortion) and interleave reference and probe rows; ``slip``: (first sample,
    ``ReferenceAfterToReferenceBefore``) of a slip of the reference sensor in its slot."""
    n = len(track.time_s)
    time_s = np.asarray(track.time_s)
    probe_to_body = np.asarray(track.probe_to_body)
    body_to_tracker = np.asarray(track.body_to_tracker)
    dwell = np.asarray(track.dwell_index)
    probe_true = body_to_tracker @ probe_to_body
    reference_true = body_to_tracker @ reference_to_body
    if slip is not None:
        reference_true[slip[0]:] = reference_true[slip[0]:] @ slip[1]
    if distortion is not None:
        probe_true = distortion.distort(time_s, probe_true)
        reference_true = distortion.distort(time_s, reference_true)

    # probe: per-dwell systematic error, interpolated in time through the transitions
    sys_pos = rng.normal(0, noise.probe_dwell_mm, (n_visits, 3))
    sys_rot = rng.normal(0, np.radians(noise.probe_dwell_deg), (n_visits, 3))
    index = np.arange(n)
    dwell_rows = np.nonzero(dwell >= 0)[0]
    if len(dwell_rows):
        anchor = dwell[dwell_rows]
        probe_pos_err = np.stack([np.interp(index, dwell_rows, sys_pos[anchor, d]) for d in range(3)], axis=1)
        probe_rot_err = np.stack([np.interp(index, dwell_rows, sys_rot[anchor, d]) for d in range(3)], axis=1)
    else:
        probe_pos_err = np.zeros((n, 3))
        probe_rot_err = np.zeros((n, 3))
    probe_pos_err += _ar1(rng, n, noise.probe_jitter_mm, noise.correlation)
    probe_rot_err += _ar1(rng, n, np.radians(noise.probe_jitter_deg), noise.correlation)

    # reference: constant error per static pose, plus jitter
    changes = np.r_[0, np.nonzero(np.any(np.abs(np.diff(body_to_tracker, axis=0)) > 1e-12, axis=(1, 2)))[0] + 1]
    segment = np.searchsorted(changes, index, side="right") - 1
    ref_sys_pos = rng.normal(0, noise.reference_static_mm, (len(changes), 3))[segment]
    ref_sys_rot = rng.normal(0, np.radians(noise.reference_static_deg), (len(changes), 3))[segment]
    ref_pos_err = ref_sys_pos + _ar1(rng, n, noise.reference_jitter_mm, noise.correlation)
    ref_rot_err = ref_sys_rot + _ar1(rng, n, np.radians(noise.reference_jitter_deg), noise.correlation)

    probe = probe_true.copy()
    probe[:, :3, :3] = _rotvec_to_matrix(probe_rot_err) @ probe_true[:, :3, :3]
    probe[:, :3, 3] += probe_pos_err
    reference = reference_true.copy()
    reference[:, :3, :3] = _rotvec_to_matrix(ref_rot_err) @ reference_true[:, :3, :3]
    reference[:, :3, 3] += ref_pos_err

    probe_quality = _quality(rng, n)
    reference_quality = _quality(rng, n)
    _corrupt(rng, probe, probe_quality, noise.bad_sample_rate)
    _corrupt(rng, reference, reference_quality, noise.bad_sample_rate / 4)

    labels = np.asarray(track.label, dtype=object)
    rows_time = np.repeat(time_s, 2)
    sensors = np.tile([REFERENCE_PORT, PROBE_PORT], n)
    poses = np.empty((2 * n, 4, 4))
    poses[0::2] = reference
    poses[1::2] = probe
    quality = np.empty(2 * n)
    quality[0::2] = reference_quality
    quality[1::2] = probe_quality
    return TrackingRecording(rows_time, sensors, poses[:, :3, 3], poses[:, :3, :3], quality,
                             np.repeat(labels, 2), source="simulation")


def _ar1(rng: np.random.Generator, n: int, sigma: float, correlation: float) -> np.ndarray:
    white = rng.normal(0.0, sigma * np.sqrt(1 - correlation**2), size=(n, 3))
    zi = rng.normal(0.0, sigma, size=(1, 3)) * correlation
    out, _ = lfilter([1.0], [1.0, -correlation], white, axis=0, zi=zi)
    return out


def _quality(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.minimum(np.floor(np.abs(rng.normal(0, 1.3, n))), 3.0)


def _corrupt(rng: np.random.Generator, poses: np.ndarray, quality: np.ndarray, rate: float) -> None:
    """Rare bad samples: a wild pose reported with a high quality number."""
    bad = np.nonzero(rng.random(len(poses)) < rate)[0]
    for i in bad:
        direction = rng.normal(size=3)
        poses[i, :3, 3] += direction / np.linalg.norm(direction) * rng.uniform(5.0, 80.0)
        poses[i, :3, :3] = random_rotation(rng, 40.0) @ poses[i, :3, :3]
        quality[i] = float(rng.integers(40, 251))
