"""Rigid transforms, trakSTAR angles, rigid point fitting and registration error figures.

Conventions:

- A transform named ``AToB`` is a 4x4 homogeneous matrix mapping points given in frame A
  into frame B: ``p_B = AToB @ [p_A, 1]``.
- Lengths in millimetres, angles in degrees unless a name says ``_rad``.
- trakSTAR angles: ``R = Rz(azimuth) @ Ry(elevation) @ Rx(roll)`` maps sensor axes to
  tracker axes (seed paper Eq. 2, with its Ry/Rz typos corrected).
- Quaternions are ``(w, x, y, z)``, unit norm, the same rotation as the matrix.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import EMRegError

Array = NDArray[np.float64]

# LPS <-> RAS: negate x and y. The matrix is its own inverse.


def make_transform(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> Array:
    """Build a 4x4 homogeneous transform from a 3x3 rotation and a translation (mm)."""
    transform = np.eye(4)
    if rotation is not None:
        transform[:3, :3] = np.asarray(rotation, dtype=float)
    if translation is not None:
        transform[:3, 3] = np.asarray(translation, dtype=float)
    return transform


def invert_rigid(a_to_b: ArrayLike) -> Array:
    """Inverse of a rigid 4x4 transform (``AToB`` -> ``BToA``) without a general matrix inverse."""
    a_to_b = np.asarray(a_to_b, dtype=float)
    rotation = a_to_b[:3, :3]
    b_to_a = np.eye(4)
    b_to_a[:3, :3] = rotation.T
    b_to_a[:3, 3] = -rotation.T @ a_to_b[:3, 3]
    return b_to_a


def apply_transform(a_to_b: ArrayLike, points_a: ArrayLike) -> Array:
    """Map points (N x 3 or 3, frame A, mm) into frame B with a 4x4 transform."""
    a_to_b = np.asarray(a_to_b, dtype=float)
    points_a = np.asarray(points_a, dtype=float)
    return points_a @ a_to_b[:3, :3].T + a_to_b[:3, 3]


def apply_rotation(a_to_b: ArrayLike, vectors_a: ArrayLike) -> Array:
    """Rotate direction vectors (N x 3 or 3) from frame A into frame B (translation ignored)."""
    a_to_b = np.asarray(a_to_b, dtype=float)
    return np.asarray(vectors_a, dtype=float) @ a_to_b[:3, :3].T


#: The one tolerance of EMReg's rigidity checks (the largest of |R^T R - I|, |det R - 1| and the last row's distance
#: from 0 0 0 1): a matrix printed with four decimals (PLUS, hand-written files) passes, a scale or shear of 0.1 %
#: does not.
RIGID_TOLERANCE = 1e-3


def rigidity_error(transform: ArrayLike) -> float:
    """How far a 4x4 matrix is from a proper rigid transform: the largest of |R^T R - I| (element-wise),
    |det R - 1| and the last row's distance from 0 0 0 1 (infinite for another shape or a non-finite value)."""
    transform = np.asarray(transform, dtype=float)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        return float("inf")
    rotation = transform[:3, :3]
    return max(float(np.max(np.abs(rotation.T @ rotation - np.eye(3)))), abs(float(np.linalg.det(rotation)) - 1.0),
               float(np.max(np.abs(transform[3] - [0.0, 0.0, 0.0, 1.0]))))


def is_rigid(transform: ArrayLike, tolerance: float = RIGID_TOLERANCE) -> bool:
    """True when the 4x4 matrix is a proper rigid transform (orthonormal rotation, det +1, last row 0 0 0 1) within
    ``tolerance`` (:func:`rigidity_error`)."""
    return rigidity_error(transform) <= tolerance


def check_rigid(transform: ArrayLike, where: str) -> None:
    """Raise :class:`~EMRegModule.errors.EMRegError` naming ``where`` (the file and the transform) unless the 4x4
    ``transform`` is rigid within :data:`RIGID_TOLERANCE`."""
    error = rigidity_error(transform)
    if not error <= RIGID_TOLERANCE:
        matrix = np.asarray(transform, dtype=float)
        detail = (f"det R = {np.linalg.det(matrix[:3, :3]):.4g}, last row {matrix[3].tolist()}, "
                  if matrix.shape == (4, 4) and np.all(np.isfinite(matrix)) else "")
        raise EMRegError(f"{where} is not a rigid transform (off by {error:.2g}: {detail}tolerance "
                         f"{RIGID_TOLERANCE:g})")


# --- trakSTAR angles ----------------------------------------------------------------------


def angles_to_rotation(azimuth_deg: ArrayLike, elevation_deg: ArrayLike, roll_deg: ArrayLike) -> Array:
    """Rotation(s) ``SensorToTracker`` from trakSTAR azimuth/elevation/roll in degrees.

    ``R = Rz(azimuth) @ Ry(elevation) @ Rx(roll)``. Vectorised: inputs of shape (N,) give
    an (N, 3, 3) array, scalars a (3, 3) array.
    """
    az = np.radians(np.asarray(azimuth_deg, dtype=float))
    el = np.radians(np.asarray(elevation_deg, dtype=float))
    ro = np.radians(np.asarray(roll_deg, dtype=float))
    ca, sa = np.cos(az), np.sin(az)
    ce, se = np.cos(el), np.sin(el)
    cr, sr = np.cos(ro), np.sin(ro)
    rotation = np.empty(np.broadcast(az, el, ro).shape + (3, 3))
    rotation[..., 0, 0] = ca * ce
    rotation[..., 0, 1] = ca * se * sr - sa * cr
    rotation[..., 0, 2] = ca * se * cr + sa * sr
    rotation[..., 1, 0] = sa * ce
    rotation[..., 1, 1] = sa * se * sr + ca * cr
    rotation[..., 1, 2] = sa * se * cr - ca * sr
    rotation[..., 2, 0] = -se
    rotation[..., 2, 1] = ce * sr
    rotation[..., 2, 2] = ce * cr
    return rotation


def rotation_to_angles(rotation: ArrayLike) -> Array:
    """trakSTAR (azimuth, elevation, roll) in degrees from rotation(s) (..., 3, 3).

    Inverse of :func:`angles_to_rotation`; elevation is in [-90, 90], azimuth and roll in
    (-180, 180]. At gimbal lock (elevation = +-90) roll is set to 0.
    """
    rotation = np.asarray(rotation, dtype=float)
    elevation = np.arcsin(np.clip(-rotation[..., 2, 0], -1.0, 1.0))
    cos_el = np.sqrt(rotation[..., 0, 0] ** 2 + rotation[..., 1, 0] ** 2)
    locked = cos_el < 1e-9
    azimuth = np.where(
        locked,
        np.arctan2(-rotation[..., 0, 1], rotation[..., 1, 1]),
        np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0]),
    )
    roll = np.where(locked, 0.0, np.arctan2(rotation[..., 2, 1], rotation[..., 2, 2]))
    return np.degrees(np.stack([azimuth, elevation, roll], axis=-1))


# --- quaternions (w, x, y, z) ------------------------------------------------------------


def quaternion_to_rotation(quaternion_wxyz: ArrayLike) -> Array:
    """Rotation matrix (..., 3, 3) from unit quaternion(s) (..., 4) ordered (w, x, y, z)."""
    q = np.asarray(quaternion_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rotation = np.empty(q.shape[:-1] + (3, 3))
    rotation[..., 0, 0] = 1 - 2 * (y * y + z * z)
    rotation[..., 0, 1] = 2 * (x * y - z * w)
    rotation[..., 0, 2] = 2 * (x * z + y * w)
    rotation[..., 1, 0] = 2 * (x * y + z * w)
    rotation[..., 1, 1] = 1 - 2 * (x * x + z * z)
    rotation[..., 1, 2] = 2 * (y * z - x * w)
    rotation[..., 2, 0] = 2 * (x * z - y * w)
    rotation[..., 2, 1] = 2 * (y * z + x * w)
    rotation[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return rotation


def rotation_to_quaternion(rotation: ArrayLike) -> Array:
    """Unit quaternion(s) (w, x, y, z) with w >= 0 from rotation matrices (..., 3, 3)."""
    rotation = np.asarray(rotation, dtype=float)
    flat = rotation.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        # Shepperd's method: choose the largest diagonal term for numerical stability.
        trace = np.trace(m)
        candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
        k = int(np.argmax(candidates))
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + trace)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = q if q[0] >= 0 else -q
    return out.reshape(rotation.shape[:-2] + (4,))


# --- rigid fitting and errors ------------------------------------------------------------


def fit_rigid_batch(
    points_a: ArrayLike, points_b: ArrayLike, weights: ArrayLike | None = None
) -> tuple[Array, Array]:
    """Least-squares rigid fits (Arun / Umeyama, no scale) mapping paired points A onto B, batched.

    ``points_a`` and ``points_b``: (..., N, 3), frames A and B (mm), broadcast against each other;
    ``weights`` (..., N): non-negative per-pair weights (None: all equal). Returns rotations
    (..., 3, 3) and translations (..., 3) with ``p_B = R @ p_A + t``. Reflection-safe (the
    determinant of every rotation is +1). Inputs are not checked (see :func:`fit_rigid`); fewer
    than 3 non-collinear pairs give one of the many minimisers.
    """
    points_a, points_b = np.broadcast_arrays(np.asarray(points_a, dtype=float), np.asarray(points_b, dtype=float))
    if weights is None:
        centroid_a = points_a.mean(axis=-2)
        centroid_b = points_b.mean(axis=-2)
        weighted_b = points_b - centroid_b[..., None, :]
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), points_a.shape[:-1])
        w = w / w.sum(axis=-1, keepdims=True)
        centroid_a = np.einsum("...n,...ni->...i", w, points_a)
        centroid_b = np.einsum("...n,...ni->...i", w, points_b)
        weighted_b = (points_b - centroid_b[..., None, :]) * w[..., None]
    covariance = np.einsum("...ni,...nj->...ij", points_a - centroid_a[..., None, :], weighted_b)
    u, _, vt = np.linalg.svd(covariance)
    v = np.swapaxes(vt, -1, -2)
    u_t = np.swapaxes(u, -1, -2)
    sign = np.sign(np.linalg.det(v @ u_t))
    correction = np.ones(np.shape(sign) + (3,))
    correction[..., 2] = np.where(sign == 0, 1.0, sign)
    rotation = (v * correction[..., None, :]) @ u_t
    translation = centroid_b - np.einsum("...ij,...j->...i", rotation, centroid_a)
    return rotation, translation


def fit_rigid(
    points_a: ArrayLike, points_b: ArrayLike, weights: ArrayLike | None = None
) -> Array:
    """Least-squares rigid ``AToB`` (4x4) mapping paired points A (N, 3) onto B (N, 3), mm.

    One fit of :func:`fit_rigid_batch` with its inputs checked: reflection-safe, ``weights`` (N,)
    non-negative per-pair weights with a positive sum; needs at least 3 non-collinear pairs.
    """
    points_a = np.asarray(points_a, dtype=float)
    points_b = np.asarray(points_b, dtype=float)
    if points_a.shape != points_b.shape or points_a.ndim != 2 or points_a.shape[1] != 3:
        raise ValueError(f"fit_rigid needs two N x 3 arrays of equal shape, got {points_a.shape} and {points_b.shape}")
    if points_a.shape[0] < 3:
        raise ValueError(f"fit_rigid needs at least 3 point pairs, got {points_a.shape[0]}")
    if weights is not None:
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (len(points_a),) or np.any(weights < 0) or weights.sum() <= 0:
            raise ValueError("weights must be N non-negative numbers with a positive sum")
    rotation, translation = fit_rigid_batch(points_a, points_b, weights)
    return make_transform(rotation, translation)


def mean_rigid(a_to_b: ArrayLike) -> Array:
    """The mean (4x4) of rigid transforms (K, 4, 4): the mean translation, and the rotation nearest the mean
    rotation matrix (its polar part, determinant +1)."""
    poses = np.asarray(a_to_b, dtype=float).reshape(-1, 4, 4)
    u, _, vt = np.linalg.svd(poses[:, :3, :3].mean(axis=0))
    mean = np.eye(4)
    mean[:3, :3] = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    mean[:3, 3] = poses[:, :3, 3].mean(axis=0)
    return mean


def residuals(a_to_b: ArrayLike, points_a: ArrayLike, points_b: ArrayLike) -> Array:
    """Per-pair distances (mm) between ``AToB @ points_a`` and ``points_b``."""
    return np.linalg.norm(apply_transform(a_to_b, points_a) - np.asarray(points_b, dtype=float), axis=-1)


def fre(a_to_b: ArrayLike, points_a: ArrayLike, points_b: ArrayLike) -> float:
    """Fiducial registration error: RMS of the pair residuals in mm (paper Eq. 7)."""
    return float(np.sqrt(np.mean(residuals(a_to_b, points_a, points_b) ** 2)))


def rotation_angle_deg(a: ArrayLike, b: ArrayLike) -> Array:
    """Angle(s) in degrees of the rotation between rotation matrices ``a`` and ``b`` (..., 3, 3): that of
    ``a.T @ b``."""
    trace = np.einsum("...ji,...ji->...", np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def rotation_vectors(rotations: ArrayLike) -> Array:
    """Rotation vectors (..., 3; axis times angle in radians, angle in [0, pi]) of rotation matrices (..., 3, 3),
    vectorised: the axis from the skew part, the angle from it and the trace; near a half turn, where the skew
    part vanishes, the axis from the symmetric part ``a a^T = (R + R^T - 2 cos(angle) I) / (2 (1 - cos(angle)))``."""
    m = np.asarray(rotations, dtype=float)
    skew_part = 0.5 * np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                                m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    sine = np.linalg.norm(skew_part, axis=-1)
    cosine = np.clip(0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    angle = np.arctan2(sine, cosine)
    out = skew_part * np.where(sine > 1e-12, angle / np.maximum(sine, 1e-300), 1.0)[..., None]
    near = cosine < -0.9
    if np.any(near):
        r, c = m[near], cosine[near]
        outer = (r + np.swapaxes(r, -1, -2) - 2.0 * c[:, None, None] * np.eye(3)) / (2.0 * (1.0 - c))[:, None, None]
        column = np.argmax(np.diagonal(outer, axis1=-2, axis2=-1), axis=-1)
        axis = outer[np.arange(len(r)), :, column]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.sum(axis * skew_part[near], axis=-1) < 0.0, -1.0, 1.0)
        out[near] = axis * (sign * angle[near])[:, None]
    return out


def rotation_matrices(rotation_vectors_rad: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3; axis times angle in radians), vectorised
    (Rodrigues; the inverse of :func:`rotation_vectors`)."""
    v = np.asarray(rotation_vectors_rad, dtype=float)
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    small = angle < 1e-6
    # sin(a)/a and (1 - cos(a))/a^2, by their series where a is tiny
    a = np.where(small, 1.0, angle)
    first = np.where(small, 1.0 - angle ** 2 / 6.0, np.sin(a) / a)
    second = np.where(small, 0.5 - angle ** 2 / 24.0, (1.0 - np.cos(a)) / a ** 2)
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return np.eye(3) + first * k + second * (k @ k)


def angle_between_deg(u: ArrayLike, v: ArrayLike) -> Array:
    """Angle(s) in degrees between vectors (..., 3)."""
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    cos = np.sum(u * v, axis=-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def random_rotation(
    rng: np.random.Generator, max_angle_deg: float | None = None, min_angle_deg: float = 0.0
) -> Array:
    """A random rotation: uniform over SO(3), or about a random axis by an angle whose size lies
    between ``min_angle_deg`` and ``max_angle_deg`` (either sign)."""
    if max_angle_deg is None:
        q = rng.normal(size=4)
        return quaternion_to_rotation(q / np.linalg.norm(q))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    u = rng.uniform(-1.0, 1.0)
    angle = np.radians(np.sign(u) * (min_angle_deg + abs(u) * (max_angle_deg - min_angle_deg)))
    return axis_angle_to_rotation(axis, angle)


def axis_angle_to_rotation(axis: ArrayLike, angle_rad: float) -> Array:
    """Rotation matrix about a unit axis by an angle in radians (Rodrigues)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)


def rotation_from_y_axis(direction: ArrayLike) -> Array:
    """A rotation whose +Y column is the given direction (the other two axes chosen stably).

    Used for axisymmetric objects (markers) whose pose is defined up to a spin about +Y.
    """
    y = np.asarray(direction, dtype=float)
    y = y / np.linalg.norm(y)
    helper = np.array([1.0, 0.0, 0.0]) if abs(y[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    z = np.cross(helper, y)
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.column_stack([x, y, z])
