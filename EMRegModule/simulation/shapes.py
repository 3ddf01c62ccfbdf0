"""Solid shapes for the CT phantom, as signed distance functions (SDF) in float32.

Every shape answers, for points given as three coordinate arrays ``x, y, z`` (mm, in the
frame the shape was built in, usually the fiducial frame's CAD frame "Frame"):

- ``sdf(x, y, z)``: signed distance, negative inside; accurate near the surface (it sets
  the partial-volume ramp of a voxel);
- ``bound(x, y, z)``: a conservative SDF, ``|bound| <= |true distance|`` with the same sign,
  used to skip bricks of voxels that are wholly inside or outside;
- ``inside(x, y, z)``: exact membership (used by supersampling of small objects);
- ``bounds``: axis-aligned box ``(lo, hi)`` that holds the solid.

Primitives are defined about their own origin; :class:`Posed` places one with a rigid
``LocalToFrame`` transform. CSG: :class:`Union`, :class:`Difference`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..marker_model import MarkerModel

F32 = np.float32


class Shape:
    """Base class: ``bound`` defaults to ``sdf``, ``inside`` to ``sdf <= 0``."""

    bounds: tuple[np.ndarray, np.ndarray]

    def sdf(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def bound(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return self.sdf(x, y, z)

    def inside(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return self.sdf(x, y, z) <= 0


def _box_bounds(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)


@dataclass
class Box(Shape):
    """Axis-aligned box centred at the origin with half extents ``half`` (mm)."""

    half: tuple[float, float, float]

    def __post_init__(self) -> None:
        h = np.asarray(self.half, dtype=float)
        self.bounds = _box_bounds(-h, h)

    def sdf(self, x, y, z):
        hx, hy, hz = (F32(v) for v in self.half)
        qx, qy, qz = np.abs(x) - hx, np.abs(y) - hy, np.abs(z) - hz
        outside = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
        return outside + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0)


def _cylinder_y(radial: np.ndarray, y: np.ndarray, radius: float, y0: float, y1: float) -> np.ndarray:
    d_r = radial - F32(radius)
    d_a = np.maximum(F32(y0) - y, y - F32(y1))
    outside = np.sqrt(np.maximum(d_r, 0) ** 2 + np.maximum(d_a, 0) ** 2)
    return outside + np.minimum(np.maximum(d_r, d_a), 0)


@dataclass
class CylinderY(Shape):
    """Cylinder of ``radius`` about the local +Y axis from ``y0`` to ``y1`` (mm)."""

    radius: float
    y0: float
    y1: float

    def __post_init__(self) -> None:
        r = self.radius
        self.bounds = _box_bounds([-r, self.y0, -r], [r, self.y1, r])

    def sdf(self, x, y, z):
        return _cylinder_y(np.sqrt(x * x + z * z), y, self.radius, self.y0, self.y1)


@dataclass
class InfiniteCylinderY(Shape):
    """Cylinder of ``radius`` about the local Y axis, unbounded along Y (clipped by ``extent``)."""

    radius: float
    extent: float = 1e4

    def __post_init__(self) -> None:
        r, e = self.radius, self.extent
        self.bounds = _box_bounds([-r, -e, -r], [r, e, r])

    def sdf(self, x, y, z):
        return np.sqrt(x * x + z * z) - F32(self.radius)


@dataclass
class CapsuleY(Shape):
    """Segment from (0, y0, 0) to (0, y1, 0) swept by a ball of ``radius`` (a rod with round ends)."""

    radius: float
    y0: float
    y1: float

    def __post_init__(self) -> None:
        r = self.radius
        self.bounds = _box_bounds([-r, self.y0 - r, -r], [r, self.y1 + r, r])

    def sdf(self, x, y, z):
        yc = np.clip(y, F32(self.y0), F32(self.y1))
        return np.sqrt(x * x + (y - yc) ** 2 + z * z) - F32(self.radius)


@dataclass
class Sphere(Shape):
    radius: float

    def __post_init__(self) -> None:
        r = self.radius
        self.bounds = _box_bounds([-r] * 3, [r] * 3)

    def sdf(self, x, y, z):
        return np.sqrt(x * x + y * y + z * z) - F32(self.radius)


@dataclass
class Ellipsoid(Shape):
    """Ellipsoid centred at the origin with semi-axes ``radii`` (mm).

    ``sdf`` is the usual first-order estimate ``k0 (k0 - 1) / k1`` (exact on the surface);
    ``bound`` is ``(k0 - 1) * min(radii)``, never larger than the true distance.
    """

    radii: tuple[float, float, float]

    def __post_init__(self) -> None:
        r = np.asarray(self.radii, dtype=float)
        self.bounds = _box_bounds(-r, r)

    def _k0(self, x, y, z):
        a, b, c = (F32(v) for v in self.radii)
        return np.sqrt((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2)

    def sdf(self, x, y, z):
        a, b, c = (F32(v) for v in self.radii)
        k0 = self._k0(x, y, z)
        k1 = np.sqrt((x / (a * a)) ** 2 + (y / (b * b)) ** 2 + (z / (c * c)) ** 2)
        return k0 * (k0 - 1) / np.maximum(k1, F32(1e-6))

    def bound(self, x, y, z):
        return (self._k0(x, y, z) - 1) * F32(min(self.radii))

    def inside(self, x, y, z):
        return self._k0(x, y, z) <= 1


@dataclass
class RibArc(Shape):
    """A tube of ``tube_radius`` along a circular arc of ``ring_radius`` in the local X-Z plane.

    The arc spans polar angles ``theta0..theta1`` (radians, ``atan2(z, x)``, theta1 > theta0,
    may pass pi) and ends in round caps.
    """

    ring_radius: float
    tube_radius: float
    theta0: float
    theta1: float

    def __post_init__(self) -> None:
        r = self.ring_radius + self.tube_radius
        self.bounds = _box_bounds([-r, -self.tube_radius, -r], [r, self.tube_radius, r])
        self._mid = 0.5 * (self.theta0 + self.theta1)
        self._half = 0.5 * (self.theta1 - self.theta0)

    def sdf(self, x, y, z):
        radial = np.sqrt(x * x + z * z)
        theta = np.arctan2(z, x)
        delta = np.mod(theta - F32(self._mid) + F32(np.pi), F32(2 * np.pi)) - F32(np.pi)  # wrapped to [-pi, pi)
        in_arc = np.abs(delta) <= self._half
        ring = np.sqrt((radial - F32(self.ring_radius)) ** 2 + y * y)
        ends = []
        for t in (self.theta0, self.theta1):
            ex, ez = F32(self.ring_radius * np.cos(t)), F32(self.ring_radius * np.sin(t))
            ends.append(np.sqrt((x - ex) ** 2 + y * y + (z - ez) ** 2))
        cap = np.minimum(ends[0], ends[1])
        return np.where(in_arc, ring, cap) - F32(self.tube_radius)


@dataclass
class MarkerSolid(Shape):
    """The PVC marker in its own frame (origin bottom-face centre, +Y to the pinhole), pinhole cut out."""

    model: MarkerModel

    def __post_init__(self) -> None:
        r = self.model.bottom_diameter_mm / 2
        self.bounds = _box_bounds([-r, 0.0, -r], [r, self.model.height_mm, r])

    def sdf(self, x, y, z):
        m = self.model
        radial = np.sqrt(x * x + z * z)
        bottom = _cylinder_y(radial, y, m.bottom_diameter_mm / 2, 0.0, m.bottom_height_mm)
        top = _cylinder_y(radial, y, m.top_diameter_mm / 2, m.bottom_height_mm - 1e-3, m.height_mm)
        hole = _cylinder_y(radial, y, m.pinhole_diameter_mm / 2, m.pinhole_bottom_mm, m.height_mm + 1.0)
        return np.maximum(np.minimum(bottom, top), -hole)

    def inside(self, x, y, z):
        m = self.model
        radial2 = x * x + z * z
        in_bottom = (y >= 0) & (y <= m.bottom_height_mm) & (radial2 <= F32((m.bottom_diameter_mm / 2) ** 2))
        in_top = (y > m.bottom_height_mm) & (y <= m.height_mm) & (radial2 <= F32((m.top_diameter_mm / 2) ** 2))
        in_hole = (y > m.pinhole_bottom_mm) & (radial2 < F32((m.pinhole_diameter_mm / 2) ** 2))
        return (in_bottom | in_top) & ~in_hole


@dataclass
class Posed(Shape):
    """A shape placed in the parent frame by ``local_to_parent`` (4x4 rigid)."""

    shape: Shape
    local_to_parent: np.ndarray

    def __post_init__(self) -> None:
        self.local_to_parent = np.asarray(self.local_to_parent, dtype=float)
        lo, hi = self.shape.bounds
        corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
        mapped = corners @ self.local_to_parent[:3, :3].T + self.local_to_parent[:3, 3]
        self.bounds = (mapped.min(axis=0), mapped.max(axis=0))
        self._rotation_t = self.local_to_parent[:3, :3].T.astype(F32)
        self._origin = self.local_to_parent[:3, 3].astype(F32)

    def _local(self, x, y, z):
        dx, dy, dz = x - self._origin[0], y - self._origin[1], z - self._origin[2]
        r = self._rotation_t
        return (r[0, 0] * dx + r[0, 1] * dy + r[0, 2] * dz,
                r[1, 0] * dx + r[1, 1] * dy + r[1, 2] * dz,
                r[2, 0] * dx + r[2, 1] * dy + r[2, 2] * dz)

    def sdf(self, x, y, z):
        return self.shape.sdf(*self._local(x, y, z))

    def bound(self, x, y, z):
        return self.shape.bound(*self._local(x, y, z))

    def inside(self, x, y, z):
        return self.shape.inside(*self._local(x, y, z))


@dataclass
class Union(Shape):
    parts: list[Shape] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.bounds = (np.min([p.bounds[0] for p in self.parts], axis=0),
                       np.max([p.bounds[1] for p in self.parts], axis=0))

    def sdf(self, x, y, z):
        return np.minimum.reduce([p.sdf(x, y, z) for p in self.parts])

    def bound(self, x, y, z):
        return np.minimum.reduce([p.bound(x, y, z) for p in self.parts])

    def inside(self, x, y, z):
        return np.logical_or.reduce([p.inside(x, y, z) for p in self.parts])


@dataclass
class Difference(Shape):
    """``base`` minus every shape of ``cuts``."""

    base: Shape
    cuts: list[Shape] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.bounds = self.base.bounds

    def sdf(self, x, y, z):
        d = self.base.sdf(x, y, z)
        for cut in self.cuts:
            d = np.maximum(d, -cut.sdf(x, y, z))
        return d

    def bound(self, x, y, z):
        d = self.base.bound(x, y, z)
        for cut in self.cuts:
            d = np.maximum(d, -cut.bound(x, y, z))
        return d

    def inside(self, x, y, z):
        inside = self.base.inside(x, y, z)
        for cut in self.cuts:
            inside &= ~cut.inside(x, y, z)
        return inside


def pose(rotation: np.ndarray | None = None, translation=None) -> np.ndarray:
    """A 4x4 rigid transform from a rotation (3x3) and a translation (mm)."""
    out = np.eye(4)
    if rotation is not None:
        out[:3, :3] = rotation
    if translation is not None:
        out[:3, 3] = translation
    return out
