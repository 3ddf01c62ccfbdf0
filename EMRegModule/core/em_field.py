"""The EM tracker's field as a dipole transmitter, and what a metal object's induced dipole does to positions.

The transmitter is three orthogonal unit coil dipoles at the Tracker origin: coil k makes the field
``F(x) e_k`` at x (Tracker frame, mm), ``F(x) = (3 u u^T - I) / |x|^3``, ``u = x / |x|`` (units with
mu0 / 4 pi = 1). A sensor with axes R measures the coupling ``S = R^T F(x)``; the tracker inverts the
free-space model, its position from the rotation-invariant ``S^T S = G(x) = F(x)^T F(x)``.

A metal object at ``o`` with polarisability ``A`` (3 x 3 symmetric, mm^3; a ferromagnetic rod is strongly
polarised along its axis, an eddy-current conductor negatively) is magnetised by each coil, adding
``dF(x) = F(x - o) A F(o)`` to what every sensor measures. To first order the reported position moves by
``dx`` with ``J(x) dx = F^T dF + dF^T F`` (J the Jacobian of vec G, solved in least squares); ``dx`` is
linear in ``A``. This is the classical dipole model of field distortion (a first-order one; the exact
inversion differs by a few per cent at a 5 mm error, 330 mm from the transmitter). Every formula is
covariant under rotations, so it holds in any frame whose origin is the transmitter.
"""

from __future__ import annotations

import numpy as np

#: Finite-difference step (mm) of the position Jacobian of the free-space coupling.
_STEP_MM = 0.05
#: The six symmetric unit matrices: xx, yy, zz, xy, xz, yz (a polarisability is their combination).
SYMMETRIC_BASIS = np.array([np.diag([1.0, 0, 0]), np.diag([0, 1.0, 0]), np.diag([0, 0, 1.0]),
                            [[0, 1.0, 0], [1.0, 0, 0], [0, 0, 0]], [[0, 0, 1.0], [0, 0, 0], [1.0, 0, 0]],
                            [[0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]])


def coil_field(points_mm: np.ndarray) -> np.ndarray:
    """``F(x)`` (K, 3, 3): the three unit transmitter coils' fields (columns) at points (K, 3) (Tracker, mm)."""
    x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    r = np.linalg.norm(x, axis=1)
    u = x / r[:, None]
    return (3.0 * u[:, :, None] * u[:, None, :] - np.eye(3)) / r[:, None, None] ** 3


def _invariant(points_mm: np.ndarray) -> np.ndarray:
    field = coil_field(points_mm)
    return np.swapaxes(field, -1, -2) @ field


def _inverse_jacobian(points_mm: np.ndarray) -> np.ndarray:
    """The least-squares inverse (K, 3, 9) of the Jacobian of vec G at points (K, 3)."""
    x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    jacobian = np.empty((len(x), 9, 3))
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = _STEP_MM
        jacobian[:, :, axis] = (_invariant(x + step) - _invariant(x - step)).reshape(-1, 9) / (2 * _STEP_MM)
    jt = np.swapaxes(jacobian, -1, -2)
    return np.linalg.solve(jt @ jacobian, jt)


def induced_coupling(points_mm: np.ndarray, object_mm: np.ndarray, polarisability: np.ndarray) -> np.ndarray:
    """``dF`` (K, 3, 3): the object's induced field per transmitter coil (columns) at points (K, 3)."""
    x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    o = np.asarray(object_mm, dtype=float).reshape(3)
    return coil_field(x - o) @ (np.asarray(polarisability, dtype=float) @ coil_field(o)[0])


def position_error(points_mm: np.ndarray, object_mm: np.ndarray, polarisability: np.ndarray) -> np.ndarray:
    """The reported position's first-order error (K, 3, mm) at true sensor positions (K, 3) near the object."""
    return position_error_basis(points_mm, object_mm, polarisability[None])[..., 0]


class FieldAtPoints:
    """The free-space field and the inverse of its position Jacobian at fixed sensor points (K, 3, Tracker
    frame, mm), kept for the errors of many candidate objects there."""

    def __init__(self, points_mm: np.ndarray) -> None:
        self.points_mm = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        self.field = coil_field(self.points_mm)
        self.inverse = _inverse_jacobian(self.points_mm)

    def error_basis(self, object_mm: np.ndarray, polarisabilities: np.ndarray = SYMMETRIC_BASIS) -> np.ndarray:
        """:func:`position_error_basis` at these points."""
        return position_error_basis(self.points_mm, object_mm, polarisabilities, self)


def position_error_basis(points_mm: np.ndarray, object_mm: np.ndarray,
                         polarisabilities: np.ndarray = SYMMETRIC_BASIS,
                         at: FieldAtPoints | None = None) -> np.ndarray:
    """First-order position errors (K, 3, P) at points (K, 3) of an object at ``object_mm`` for each of the
    polarisabilities (P, 3, 3) (default: the six symmetric unit ones, so that ``error = basis @ coefficients``);
    ``at``: the same points' :class:`FieldAtPoints`, to skip recomputing them."""
    x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    at = at or FieldAtPoints(x)
    o = np.asarray(object_mm, dtype=float).reshape(3)
    moments = np.asarray(polarisabilities, dtype=float) @ coil_field(o)[0]  # (P, 3, 3)
    d_field = np.einsum("kij,pjl->kpil", coil_field(x - o), moments)  # (K, P, 3, 3)
    d_invariant = np.einsum("kji,kpjl->kpil", at.field, d_field)
    d_invariant = d_invariant + np.swapaxes(d_invariant, -1, -2)
    return np.einsum("kin,kpn->kip", at.inverse, d_invariant.reshape(len(x), -1, 9))


def symmetric_coefficients(polarisability: np.ndarray) -> np.ndarray:
    """The six coefficients (xx, yy, zz, xy, xz, yz) of a symmetric 3 x 3 matrix in :data:`SYMMETRIC_BASIS`."""
    a = np.asarray(polarisability, dtype=float)
    return np.array([a[0, 0], a[1, 1], a[2, 2], a[0, 1], a[0, 2], a[1, 2]])
