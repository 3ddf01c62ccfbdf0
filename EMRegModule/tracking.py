"""Tracking samples: one trakSTAR recording in memory, and its frame arithmetic.

A :class:`TrackingRecording` holds rows of sensor poses in the Tracker frame (the
transmitter, paper S_w) exactly as the tracker reports them: ``SensorToTracker``.
Probe samples are expressed in the Reference frame (the Model 800 sensor fixed in the
fiducial frame, paper S_p) with paper Eq. 3-5: ``ProbeToReference = inv(ReferenceToTracker)
@ ProbeToTracker`` at the same moment, so a frame or transmitter that moves between
dwells changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import EMRegError
from .transforms import invert_rigid

#: Reference and probe rows of one moment share ``time_s`` within this tolerance (spec).
SAME_MOMENT_S = 1e-3


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
    notes: list[str] = field(default_factory=list)  # what reading dropped (e.g. frames with an INVALID status)

    def __post_init__(self) -> None:
        n = len(self.time_s)
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
            self.quality[mask], self.label[mask], self.source, self.orientation_format, list(self.notes),
        )

    def for_sensor(self, port: int, role: str = "sensor") -> TrackingRecording:
        """Rows of one sensor port, in time order; :class:`EMRegError` if the port has none."""
        mask = self.sensor == port
        if not np.any(mask):
            raise EMRegError(
                f"{self.source}: no samples from the {role} sensor on port {port} "
                f"(ports present: {self.sensors}); set the port with --{role}-sensor or in case.toml [sensors]"
            )
        rows = self.select(mask)
        order = np.argsort(rows.time_s, kind="stable")
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
    nearest reference row when they are within ``tolerance_s``; other probe rows are dropped.
    """
    if len(reference) == 0 or len(probe) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    right = np.searchsorted(reference.time_s, probe.time_s)
    right = np.clip(right, 0, len(reference) - 1)
    left = np.clip(right - 1, 0, len(reference) - 1)
    pick_left = np.abs(reference.time_s[left] - probe.time_s) <= np.abs(reference.time_s[right] - probe.time_s)
    nearest = np.where(pick_left, left, right)
    ok = np.abs(reference.time_s[nearest] - probe.time_s) <= tolerance_s
    return nearest[ok], np.nonzero(ok)[0]


def probe_in_reference(
    recording: TrackingRecording, reference_port: int = 1, probe_port: int = 2
) -> ProbeInReference:
    """Express every probe sample in the Reference frame at its own moment (paper Eq. 3-5).

    ``ProbeToReference = inv(ReferenceToTracker) @ ProbeToTracker``. Raises
    :class:`EMRegError` when a sensor is missing or no moment has both sensors.
    """
    reference = recording.for_sensor(reference_port, "reference")
    probe = recording.for_sensor(probe_port, "probe")
    ref_idx, probe_idx = match_moments(reference, probe)
    if len(probe_idx) == 0:
        raise EMRegError(
            f"{recording.source}: no probe sample has a reference sample at the same time (within 1 ms)"
        )
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
        probe.time_s[probe_idx], probe_to_reference, reference_to_tracker, quality, probe.label[probe_idx]
    )


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
