"""The candidate fields of the distortion test, as columns of displacement per amplitude (Reference frame, mm).

Each candidate is a field linear in its amplitudes: ``columns(points)`` is (K, 3, P), the displacement at K points
per unit of each of its P amplitudes. An induced dipole near the frame (:mod:`EMRegModule.core.em_field`, seen from
the transmitter through each pinhole's pose), single Gaussian bumps, polynomial fields, and the smoothest modes of a
Gaussian process on the pinholes. They carry no test: :mod:`.scan` projects them beyond the rigid fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..em_field import FieldAtPoints


def gaussian_kernel(points_a: np.ndarray, points_b: np.ndarray, length_mm: np.ndarray | float) -> np.ndarray:
    """Gaussian bump values exp(-|a - b|^2 / (2 L^2)), (len(a), len(b)); ``length_mm`` per b or one."""
    squared = np.sum((points_a[:, None, :] - points_b[None, :, :]) ** 2, axis=-1)
    return np.exp(-squared / (2.0 * np.asarray(length_mm, dtype=float) ** 2))


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit directions (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    angle = np.pi * (1.0 + np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(angle), r * np.sin(angle), z])


@dataclass(frozen=True)
class Dipole:
    """An induced dipole at ``object_mm`` (Tracker frame); pinholes seen from the transmitter through each one's
    ``TrackerToReference`` (the frame may have moved between dwells). Amplitudes: the six symmetric
    polarisability coefficients (mm^3, :data:`EMRegModule.core.em_field.SYMMETRIC_BASIS`)."""

    object_mm: np.ndarray
    tracker_to_reference: np.ndarray  # (4, 4): for points other than the pinholes (the calibration's mean pose)

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 6) in the Reference frame at points (K, 3), each with its pose (K, 4, 4) or the mean
        (``seen``: those points as the transmitter sees them, kept)."""
        seen = seen or Seen(points_reference, np.broadcast_to(
            self.tracker_to_reference if tracker_to_reference is None else tracker_to_reference,
            (len(points_reference), 4, 4)))
        return seen.rotation @ seen.field.error_basis(self.object_mm)


class Seen:
    """Points of the Reference frame as the transmitter sees them: their poses' rotations (K, 3, 3) and the
    free-space field there (:class:`EMRegModule.core.em_field.FieldAtPoints`)."""

    def __init__(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray) -> None:
        self.rotation = tracker_to_reference[:, :3, :3]
        origin = tracker_to_reference[:, :3, 3]
        self.points_tracker = np.einsum("kji,kj->ki", self.rotation, np.asarray(points_reference) - origin)
        self.field = FieldAtPoints(self.points_tracker)


@dataclass(frozen=True)
class Bumps:
    """Gaussian bumps at ``centres_mm`` (B, 3, Reference) of widths ``lengths_mm`` (B,); amplitudes: a
    displacement (mm, 3) per bump."""

    centres_mm: np.ndarray
    lengths_mm: np.ndarray

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3B) at points (K, 3) of the Reference frame."""
        kernel = gaussian_kernel(np.asarray(points_reference, dtype=float), self.centres_mm, self.lengths_mm)
        return np.einsum("kb,cd->kcbd", kernel, np.eye(3)).reshape(len(kernel), 3, -1)


@dataclass(frozen=True)
class Polynomial:
    """A displacement field polynomial in position (Reference frame): every monomial of
    ``(x - centre_mm) / scale_mm`` up to ``degree``, times each axis; amplitudes: mm per monomial and axis."""

    centre_mm: np.ndarray
    scale_mm: float
    degree: int

    def exponents(self) -> np.ndarray:
        return np.array([(i, j, k) for total in range(self.degree + 1) for i in range(total + 1)
                         for j in range(total + 1 - i) for k in (total - i - j,)])

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3M) at points (K, 3) of the Reference frame (M monomials)."""
        u = (np.asarray(points_reference, dtype=float).reshape(-1, 3) - self.centre_mm) / self.scale_mm
        monomials = np.prod(u[:, None, :] ** self.exponents()[None], axis=-1)  # (K, M)
        return np.einsum("km,cd->kcmd", monomials, np.eye(3)).reshape(len(u), 3, -1)


@dataclass(frozen=True)
class Modes:
    """The smoothest fields a Gaussian process of length ``length_mm`` puts on the pinholes ``centres_mm`` (B, 3):
    the kernel's leading eigenvectors there, extended to any point by the kernel (Nystrom), ``weights`` (B, M);
    amplitudes: a displacement (mm, 3) per mode."""

    centres_mm: np.ndarray
    length_mm: float
    weights: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, length_mm: float, modes: int) -> Modes:
        values, vectors = np.linalg.eigh(gaussian_kernel(points, points, length_mm))
        order = np.argsort(values)[::-1][:modes]
        return cls(points, float(length_mm), vectors[:, order] / np.maximum(values[order], 1e-12))

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3M) at points (K, 3) of the Reference frame."""
        values = gaussian_kernel(np.asarray(points_reference, dtype=float).reshape(-1, 3), self.centres_mm,
                         self.length_mm) @ self.weights  # (K, M)
        return np.einsum("km,cd->kcmd", values, np.eye(3)).reshape(len(values), 3, -1)
