"""Navigation: probe poses mapped into image space (paper Eq. 11-12).

``ProbeToImage = ReferenceToImage @ inv(ReferenceToTracker) @ ProbeToTracker`` for each
moment at which both sensors were sampled; vectorised over a whole recording, and as a
single-pose function for the live path (OpenIGTLink server).

With a tool (``TipToProbe``, :mod:`EMRegModule.core.tool`) the navigated point is the tip:
``TipToImage = ProbeToImage @ TipToProbe``; ``navigation.csv`` then holds the tip's positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from .guidance import Guidance
from .tracking import SAME_MOMENT_S, TrackingRecording, invert_rigid_batch, sensor_pair


def probe_to_image(reference_to_image: np.ndarray, reference_to_tracker: np.ndarray,
                   probe_to_tracker: np.ndarray) -> np.ndarray:
    """``ProbeToImage`` (4x4, or (N, 4, 4) for stacks) from one moment's sensor poses (paper Eq. 12).

    ``reference_to_image``: the registration (Reference -> CT LPS, mm); ``reference_to_tracker``
    and ``probe_to_tracker``: the two sensors' poses as the tracker reports them, (4, 4) or (N, 4, 4).
    """
    reference_to_image = np.asarray(reference_to_image, dtype=float)
    tracker_to_reference = invert_rigid_batch(np.asarray(reference_to_tracker, dtype=float))
    return reference_to_image @ (tracker_to_reference @ np.asarray(probe_to_tracker, dtype=float))


@dataclass
class NavigationResult:
    """Probe samples in image space: ``time_s`` (N,), ``probe_to_image`` (N, 4, 4),
    ``label`` (N,) (the recording's labels), ``quality`` (N,) (worst of both sensors) and ``status`` (N,)
    (``OK`` / ``INVALID``, set by :func:`EMRegModule.core.checkpoints.check_navigation`; None: not judged, OK);
    ``guidance``: the guidance numbers against a plan (:mod:`EMRegModule.core.guidance`), None without one."""

    time_s: np.ndarray
    probe_to_image: np.ndarray
    label: np.ndarray
    quality: np.ndarray
    status: np.ndarray | None = None
    guidance: Guidance | None = None

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def position_mm(self) -> np.ndarray:
        """Probe sensor centre in image space (N, 3), LPS mm."""
        return self.probe_to_image[:, :3, 3]

    @property
    def direction(self) -> np.ndarray:
        """Probe +X (long axis, cable to tip) in image space (N, 3)."""
        return self.probe_to_image[:, :3, 0]


def navigate_recording(recording: TrackingRecording, reference_to_image: np.ndarray,
                       reference_sensor: int = DEFAULT_REFERENCE_PORT, probe_sensor: int = DEFAULT_PROBE_PORT,
                       tip_to_probe: np.ndarray | None = None) -> NavigationResult:
    """Map every probe sample that has a reference sample at the same moment into image space.

    ``tip_to_probe`` (4x4, mm): a tool's tip; the result then holds ``TipToImage`` (the tip navigated).

    Vectorised Eq. 12 in 3x3 blocks (no 4x4 stacks are built or inverted): with
    ``TrackerToImage = ReferenceToImage @ inv(ReferenceToTracker)`` per moment,
    ``R = R_ri @ R_ref^T @ R_probe`` and ``p = R_ri @ R_ref^T @ (p_probe - p_ref) + t_ri``.
    Moments are paired as in :func:`EMRegModule.core.tracking.probe_in_reference`.
    """
    reference_to_image = np.asarray(reference_to_image, dtype=float)
    reference, probe, ref_idx, probe_idx = sensor_pair(recording, reference_sensor, probe_sensor)
    tracker_to_image = reference_to_image[:3, :3] @ np.swapaxes(reference.rotation[ref_idx], 1, 2)
    mapped = np.zeros((len(probe_idx), 4, 4))
    mapped[:, :3, :3] = tracker_to_image @ probe.rotation[probe_idx]
    offset = probe.position_mm[probe_idx] - reference.position_mm[ref_idx]
    mapped[:, :3, 3] = np.einsum("nij,nj->ni", tracker_to_image, offset) + reference_to_image[:3, 3]
    mapped[:, 3, 3] = 1.0
    if tip_to_probe is not None:
        mapped = mapped @ np.asarray(tip_to_probe, dtype=float)
    quality = np.fmax(reference.quality[ref_idx], probe.quality[probe_idx])
    return NavigationResult(probe.time_s[probe_idx], mapped, probe.label[probe_idx], quality)


def unpaired_probe_note(recording: TrackingRecording, result: NavigationResult,
                        probe_sensor: int = DEFAULT_PROBE_PORT) -> str | None:
    """One line when some probe samples of ``recording`` found no reference sample at the same moment (within
    ``SAME_MOMENT_S``) and so are not in ``result`` (e.g. a probe sampled faster than the reference), else None."""
    probe_rows = int(np.count_nonzero(recording.sensor == probe_sensor))
    dropped = probe_rows - len(result)
    if dropped <= 0:
        return None
    return (f"{recording.source}: {dropped} of {probe_rows} probe samples (port {probe_sensor}) have no reference "
            f"sample within {SAME_MOMENT_S * 1000:g} ms of their time: not mapped (navigation.csv holds "
            f"{len(result)} rows)")


