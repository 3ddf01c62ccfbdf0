"""A simulated stylus: a tracked tool with its tip offset from the sensor, pivoting in a divot.

:func:`simulate_pivot_recording` records the tool sensor (port 2) and the reference sensor (port 1) while the
tip rests in a divot fixed to the reference and the shaft swings in a cone about it (with the approach and the
departure around it), with the tracker errors of :class:`~EMRegModule.simulation.tracking.NoiseModel`; the
ground truth is the tip in the sensor's frame (``TipToProbe``'s translation) and the divot in the Reference
frame. The touches of a stylus registration pivot the same way (``Visit.pivot_swing_deg``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.tracking import TrackingRecording
from ..core.transforms import axis_angle_to_rotation, make_transform, random_rotation
from .tracking import NoiseModel, Visit, probe_rotation_into, simulate_session

#: The default simulated stylus: the tip 150 mm along the sensor's +X (a pointer with the sensor in its
#: handle), a little off the axis as a real one is.
DEFAULT_TIP_MM = (150.0, 1.5, -2.0)


def simulate_pivot_recording(seed: int = 0, tip_mm: Any = DEFAULT_TIP_MM, swing_deg: float = 30.0,
                             duration_s: float = 8.0, noise: NoiseModel | None = None
                             ) -> tuple[TrackingRecording, dict[str, Any]]:
    """A pivot calibration recording (positions mm, Tracker frame as a trakSTAR reports them) and its truth:
    ``{"tip_mm": [3], "TipToProbe": 4x4, "pivot_point_mm": [3] (Reference frame), "swing_deg": ..}``.

    ``swing_deg``: the cone's full angle (the shaft tilts up to half of it from its start each way)."""
    rng = np.random.default_rng(seed)
    tip_mm = np.asarray(tip_mm, dtype=float)
    reference_to_body = np.eye(4)  # the divot is fixed to the reference: the Body is the Reference
    body_to_tracker = make_transform(random_rotation(rng), rng.uniform(-50, 50, 3) + [0.0, 0.0, 250.0])
    divot_body = np.array([60.0, 20.0, -10.0])
    down = -np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0])  # the shaft points into the divot
    rotation = probe_rotation_into(down, float(rng.uniform(0, 2 * np.pi))) @ shaft_rotation(tip_mm)
    probe_to_body = make_transform(rotation, divot_body - rotation @ tip_mm)
    visit = Visit(probe_to_body, duration_s, "", "divot", tip_mm=tip_mm, pivot_swing_deg=swing_deg)
    recording, _, _ = simulate_session(rng, [visit], body_to_tracker, reference_to_body, divot_body,
                                       noise=noise or NoiseModel())
    truth = {"tip_mm": tip_mm.tolist(), "TipToProbe": make_transform(None, tip_mm).tolist(),
             "pivot_point_mm": divot_body.tolist(), "swing_deg": float(swing_deg)}
    return recording, truth


def shaft_rotation(tip_mm: Any) -> np.ndarray:
    """The rotation (3x3) that turns the tip's direction (sensor to tip, probe frame) onto +X: a probe pose
    whose +X runs along a path, times this, is the stylus pose whose shaft runs along it."""
    tip_mm = np.asarray(tip_mm, dtype=float)
    return _rotation_between(tip_mm / np.linalg.norm(tip_mm), np.array([1.0, 0.0, 0.0])).T


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation (3x3) taking unit vector ``a`` onto unit vector ``b`` (about their common normal)."""
    cross = np.cross(a, b)
    sine, cosine = float(np.linalg.norm(cross)), float(np.dot(a, b))
    if sine < 1e-12:
        return np.eye(3)
    return axis_angle_to_rotation(cross / sine, float(np.arctan2(sine, cosine)))
