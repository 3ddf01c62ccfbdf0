"""A metal object near the frame distorting the EM field, for simulated recordings (ground truth).

The physics is :mod:`EMRegModule.core.em_field` (a dipole transmitter; the object an induced dipole; first
order): a steel rod of a C-arm, an instrument tray or a table rail moves the reported positions of the
sensors near it and turns their reported axes. Published sizes: near a steel rod the Aurora's position
error reaches 4 mm (Hummel et al. 2005); the trakSTAR behaves alike. The reported orientation is
``Q R`` with ``Q`` the rotation (polar) part of ``F(x + dx) (F + dF)^T``: the same rotation error for
every sensor orientation at that place.

The object may be rolled in during a recording: its strength ramps from 0 to 1 between
``onset_s`` and ``onset_s + ramp_s`` (recording time, s), so the real error is known at every moment
(:meth:`FieldDistortion.errors_at` times :meth:`FieldDistortion.strength`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.em_field import coil_field, induced_coupling, position_error
from ..core.transforms import apply_transform, fit_rigid, invert_rigid

#: Time (s) over which an object rolled in reaches its full effect.
DEFAULT_RAMP_S = 2.0


def polar_rotation(matrices: np.ndarray) -> np.ndarray:
    """The rotation part (K, 3, 3) of near-rotation-times-positive matrices (polar decomposition)."""
    u, _, vt = np.linalg.svd(matrices)
    sign = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= sign[..., None]
    return u @ vt


class TimedField:
    """What every simulated field distortion shares: when it is there and how it moves the poses a tracker reports.

    A subclass has ``onset_s`` / ``ramp_s`` (it arrives at ``onset_s``, recording time in s, and reaches full effect
    ``ramp_s`` later; ``onset_s = -inf``: there all along) and ``errors_at(points_mm)``: at full strength, the
    reported position's error (K, 3, mm) and the rotation error ``Q`` (K, 3, 3; reported sensor axes = ``Q @``
    true axes) at true sensor positions (K, 3), Tracker frame."""

    def strength(self, time_s: np.ndarray | float) -> np.ndarray:
        """The field's effect (0..1) at recording times ``time_s`` (s)."""
        t = np.asarray(time_s, dtype=float)
        if not np.isfinite(self.onset_s):
            return np.ones_like(t)
        if self.ramp_s <= 0:
            return (t >= self.onset_s).astype(float)
        s = np.clip((t - self.onset_s) / self.ramp_s, 0.0, 1.0)
        return s * s * (3.0 - 2.0 * s)  # smooth start and stop

    def distort(self, time_s: np.ndarray, poses_tracker: np.ndarray) -> np.ndarray:
        """Sensor poses (K, 4, 4, Tracker) as the tracker reports them at ``time_s`` (K,): true poses moved by the
        field's errors at its strength then (the rotation error scaled along its axis)."""
        poses = np.array(poses_tracker, dtype=float, copy=True)
        strength = self.strength(time_s)
        active = strength > 0
        if not np.any(active):
            return poses
        position_error, rotation_error = self.errors_at(poses[active, :3, 3])
        s = strength[active]
        poses[active, :3, 3] += s[:, None] * position_error
        poses[active, :3, :3] = scaled_rotation(rotation_error, s) @ poses[active, :3, :3]
        return poses


@dataclass(frozen=True)
class FieldDistortion(TimedField):
    """A metal object in the transmitter's field (Tracker frame, mm) and when it is there.

    ``object_mm`` (3,): its position; ``polarisability`` (3, 3, mm^3): its induced moment per unit
    field; ``onset_s`` / ``ramp_s``: it arrives at ``onset_s`` (recording time) and reaches full
    effect ``ramp_s`` later (``onset_s = -inf``: there all along).
    """

    object_mm: np.ndarray
    polarisability: np.ndarray
    onset_s: float = float("-inf")
    ramp_s: float = DEFAULT_RAMP_S

    def errors_at(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """At full strength: the reported position's error (K, 3, mm) and the rotation error ``Q`` (K, 3, 3)
        (reported sensor axes = ``Q @`` true axes) at true sensor positions (K, 3) (Tracker frame)."""
        x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        error = position_error(x, self.object_mm, self.polarisability)
        measured = coil_field(x) + induced_coupling(x, self.object_mm, self.polarisability)
        return error, polar_rotation(coil_field(x + error) @ np.swapaxes(measured, -1, -2))

    def distortion_mm(self, position_mm: np.ndarray) -> float:
        """The size (mm) of the position error at full strength at a sensor at ``position_mm`` (3,, Tracker frame):
        the :class:`~EMRegModule.devices.simulator.tracker_flags.DistortionModel` the live simulators' flags (trakSTAR
        METAL byte, Aurora RMS error) are made from, so the flags follow the same object that moves the poses."""
        error = position_error(np.asarray(position_mm, dtype=float).reshape(1, 3), self.object_mm, self.polarisability)
        return float(np.linalg.norm(error[0]))

    def scaled(self, factor: float) -> FieldDistortion:
        """The same object, ``factor`` times as strongly polarised (errors scale with it, to first order)."""
        return replace(self, polarisability=np.asarray(self.polarisability, dtype=float) * float(factor))

    def to_json(self) -> dict[str, Any]:
        return {"model": "induced magnetic dipole in a dipole transmitter's field, first order",
                "object_tracker_mm": [float(v) for v in self.object_mm],
                "polarisability_mm3": np.asarray(self.polarisability, dtype=float).tolist(),
                "onset_s": float(self.onset_s) if np.isfinite(self.onset_s) else None,
                "ramp_s": float(self.ramp_s)}

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> FieldDistortion:
        onset = document.get("onset_s")
        return cls(np.asarray(document["object_tracker_mm"], dtype=float),
                   np.asarray(document["polarisability_mm3"], dtype=float),
                   float("-inf") if onset is None else float(onset), float(document.get("ramp_s", DEFAULT_RAMP_S)))


def scaled_rotation(rotations: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Rotations (K, 3, 3) turned by ``fraction`` (K,) of their angle about their own axis."""
    rotvec = Rotation.from_matrix(rotations).as_rotvec() * np.asarray(fraction, dtype=float)[:, None]
    return Rotation.from_rotvec(rotvec).as_matrix()


# --- placing an object near a frame ----------------------------------------------------------


def nonrigid_errors(distortion: FieldDistortion, points_body: np.ndarray, body_to_tracker: np.ndarray,
                    reference_to_body: np.ndarray, at_body: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What the object does to sensor points fixed to a body (K, 3, Body frame, mm) seen from the reference sensor.

    Returns (raw, nonrigid), both (K, 3) in the Reference frame (mm) at full strength: ``raw`` the
    error of each point as measured (probe and reference both distorted), ``nonrigid`` what is left
    of it after the best rigid fit of the distorted points onto the true ones (what no registration
    can remove, the residual a calibration shows beside noise). With ``at_body`` (L, 3): the same two
    at those points instead, the rigid fit still made on ``points_body`` (the error a registration
    from distorted pinholes leaves at a target probed in the same field).
    """
    reference_to_tracker = np.asarray(body_to_tracker, dtype=float) @ np.asarray(reference_to_body, dtype=float)
    reported_reference = distortion.distort(np.zeros(1), reference_to_tracker[None])[0]

    def measure(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points_tracker = apply_transform(body_to_tracker, points)
        probe_error, _ = distortion.errors_at(points_tracker)
        return (apply_transform(invert_rigid(reported_reference), points_tracker + probe_error),
                apply_transform(invert_rigid(reference_to_tracker), points_tracker))

    measured, true = measure(np.asarray(points_body, dtype=float).reshape(-1, 3))
    measured_to_true = fit_rigid(measured, true)
    if at_body is not None:
        measured, true = measure(np.asarray(at_body, dtype=float).reshape(-1, 3))
    return measured - true, apply_transform(measured_to_true, measured) - true


def place_object(rng: np.random.Generator, points_body: np.ndarray, body_to_tracker: np.ndarray,
                 reference_to_body: np.ndarray, nonrigid_rms_mm: float, onset_s: float = float("-inf"),
                 ramp_s: float = DEFAULT_RAMP_S, gap_mm: tuple[float, float] = (40.0, 120.0)) -> FieldDistortion:
    """A steel rod beside the points (a frame's pinholes, K >= 3, Body frame) scaled to ``nonrigid_rms_mm``.

    The rod lies ``gap_mm`` beyond the points' farthest extent in a random direction (at least 120 mm
    from the transmitter), its axis random; its polarisability is strong along the axis (10 x across).
    Its strength is chosen so that the RMS over the points of the non-rigid error
    (:func:`nonrigid_errors`) is ``nonrigid_rms_mm``.
    """
    points_tracker = apply_transform(body_to_tracker, np.asarray(points_body, dtype=float))
    centre = points_tracker.mean(axis=0)
    radius = float(np.max(np.linalg.norm(points_tracker - centre, axis=1)))
    for _attempt in range(100):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        position = centre + direction * (radius + rng.uniform(*gap_mm))
        if np.linalg.norm(position) > 120.0:
            break
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    polarisability = 1e5 * (np.outer(axis, axis) + 0.1 * (np.eye(3) - np.outer(axis, axis)))
    distortion = FieldDistortion(position, polarisability, onset_s, ramp_s)
    for _step in range(3):  # first order: linear in the strength; refine for the rigid fit's small nonlinearity
        _, nonrigid = nonrigid_errors(distortion, points_body, body_to_tracker, reference_to_body)
        rms = float(np.sqrt(np.mean(np.sum(nonrigid**2, axis=1))))
        if rms <= 0 or abs(rms - nonrigid_rms_mm) < 1e-4 * max(nonrigid_rms_mm, 1e-3):
            break
        distortion = distortion.scaled(nonrigid_rms_mm / rms)
    return distortion


def truth_at_points(distortion: FieldDistortion, labels: list[str], points_body: np.ndarray,
                    body_to_tracker: np.ndarray, reference_to_body: np.ndarray) -> dict[str, Any]:
    """The ground truth of a distortion at labelled points (Reference frame, mm, full strength) for ``truth.json``:
    each point's raw and non-rigid error (:func:`nonrigid_errors`), their RMS and largest sizes."""
    raw, nonrigid = nonrigid_errors(distortion, points_body, body_to_tracker, reference_to_body)
    raw_norm, nonrigid_norm = np.linalg.norm(raw, axis=1), np.linalg.norm(nonrigid, axis=1)
    return {"rms_nonrigid_mm": float(np.sqrt(np.mean(nonrigid_norm**2))), "max_nonrigid_mm": float(nonrigid_norm.max()),
            "max_raw_mm": float(raw_norm.max()),
            "points": [{"label": label, "raw_mm": [float(v) for v in r], "nonrigid_mm": [float(v) for v in n]}
                       for label, r, n in zip(labels, raw, nonrigid, strict=True)]}
