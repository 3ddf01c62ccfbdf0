"""Navigation: probe poses mapped into image space (paper Eq. 11-12).

``ProbeToImage = ReferenceToImage @ inv(ReferenceToTracker) @ ProbeToTracker`` for each
moment at which both sensors were sampled; vectorised over a whole recording, and as a
single-pose function for the live path (OpenIGTLink server).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .io.atomic import atomic_path
from .tracking import TrackingRecording, invert_rigid_batch, probe_in_reference

NAVIGATION_HEADER = "time_s,x_mm,y_mm,z_mm,label"


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
    ``label`` (N,) (the recording's labels) and ``quality`` (N,) (worst of both sensors)."""

    time_s: np.ndarray
    probe_to_image: np.ndarray
    label: np.ndarray
    quality: np.ndarray

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
                       reference_sensor: int = 1, probe_sensor: int = 2) -> NavigationResult:
    """Map every probe sample that has a reference sample at the same moment into image space.

    Vectorised: ``ProbeToReference`` per moment (paper Eq. 3-5), then ``ReferenceToImage`` on top.
    """
    samples = probe_in_reference(recording, reference_sensor, probe_sensor)
    mapped = np.matmul(np.asarray(reference_to_image, dtype=float), samples.probe_to_reference)
    return NavigationResult(samples.time_s, mapped, samples.label, samples.quality)


def format_navigation_csv(result: NavigationResult) -> str:
    """``time_s,x_mm,y_mm,z_mm,label`` text, one row per probe sample (positions in LPS mm)."""
    position = result.position_mm
    rows = zip(result.time_s.tolist(), position[:, 0].tolist(), position[:, 1].tolist(), position[:, 2].tolist(),
               result.label.tolist(), strict=True)
    lines = [NAVIGATION_HEADER]
    lines.extend(f"{t:.4f},{x:.4f},{y:.4f},{z:.4f},{_csv_label(label)}" for t, x, y, z, label in rows)
    return "\n".join(lines) + "\n"


def _csv_label(label: object) -> str:
    text = "" if label is None else str(label)
    if any(c in text for c in ',"\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def write_navigation_csv(result: NavigationResult, path: str | os.PathLike[str]) -> None:
    """Write ``navigation.csv`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(format_navigation_csv(result), encoding="utf-8")
