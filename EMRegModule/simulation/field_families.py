"""Distorted fields of other families than EMReg's induced dipole, to validate the detector on (issue 37).

EMReg's detector (:mod:`EMRegModule.core.distortion`) was designed around the first-order induced dipole of
:mod:`EMRegModule.core.em_field`; a study that measures it only on that same dipole measures itself. The families
here are made differently, each a drop-in for :class:`~EMRegModule.simulation.distortion.FieldDistortion`
(``errors_at``, ``distort``, ``strength``, ``scaled``, ``distortion_mm``) so the session simulator distorts
both sensors with them:

- ``gp``: a random smooth displacement field (a Gaussian process with a squared-exponential kernel, drawn by
  random Fourier features), in the Tracker frame (mm). No physics: only smoothness.
- ``magpylib``: one real body in the transmitter's field, its field computed by ``magpylib`` (finite bodies,
  not dipoles): a soft-iron cuboid magnetised by each transmitter coil (an anisotropic susceptibility, strong
  along its long side), or a conductive ring in which each coil induces an eddy current (``I = -flux / L``,
  the flux integrated over the ring's disk). The sensor then measures, per coil, the transmitter's field plus
  the body's; the reported position is found as a tracker does, by solving the free-space dipole model for the
  position whose rotation-invariant coupling ``G = M^T M`` matches the measured one (Gauss-Newton, exact, not
  first order), and the reported orientation is the polar part of ``F(x') M^T`` (as the dipole simulator's).
- ``multi``: two or three bodies at once (cuboids, rings, and an exact induced dipole), plus a uniform field
  gradient across the working volume (a large distant steel mass), solved the same way.
- ``dipole``: the existing rod (:func:`~EMRegModule.simulation.distortion.place_object`).

Each is scaled so that the RMS over the pinholes of the non-rigid error
(:func:`~EMRegModule.simulation.distortion.nonrigid_errors`) is the size asked for.
Development families (the detector may be tuned on them): ``dipole``, ``gp``. Held out (never tuned on):
``magpylib``, ``multi`` (:data:`HELD_OUT`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.em_field import coil_field, induced_coupling
from ..core.transforms import apply_transform
from .distortion import DEFAULT_RAMP_S, TimedField, nonrigid_errors, place_object, polar_rotation

#: The families, development first.
FAMILIES = ("dipole", "gp", "magpylib", "multi")
#: Families never used to tune the detector: the study reports on them as held out.
DEVELOPMENT = ("dipole", "gp")
HELD_OUT = ("magpylib", "multi")
#: Gauss-Newton iterations of the tracker's free-space position solve.
SOLVE_ITERATIONS = 6
_STEP_MM = 0.05
#: Largest move (mm) of one Gauss-Newton step.
MAX_STEP_MM = 20.0


def _invariant(points_mm: np.ndarray) -> np.ndarray:
    f = coil_field(points_mm)
    return np.swapaxes(f, -1, -2) @ f


def solve_position(measured: np.ndarray, start_mm: np.ndarray) -> np.ndarray:
    """Positions (K, 3, Tracker mm) the free-space dipole model assigns to measured couplings (K, 3, 3; columns per
    coil, the units of :func:`EMRegModule.core.em_field.coil_field`), from ``start_mm`` (K, 3): ``G(x') = M^T M``
    solved by Gauss-Newton with a relative residual (vectorised over K)."""
    target = (np.swapaxes(measured, -1, -2) @ measured).reshape(-1, 9)
    scale = 1.0 / np.linalg.norm(target, axis=1)
    x = np.array(start_mm, dtype=float).reshape(-1, 3)
    for _ in range(SOLVE_ITERATIONS):
        residual = (_invariant(x).reshape(-1, 9) - target) * scale[:, None]
        jacobian = np.empty((len(x), 9, 3))
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = _STEP_MM
            jacobian[:, :, axis] = (_invariant(x + step) - _invariant(x - step)).reshape(-1, 9) \
                * (scale[:, None] / (2 * _STEP_MM))
        jt = np.swapaxes(jacobian, -1, -2)
        normal = jt @ jacobian
        damping = 1e-9 * np.trace(normal, axis1=-2, axis2=-1)[:, None, None] * np.eye(3)
        step = np.linalg.solve(normal + damping, (jt @ residual[..., None]))[..., 0]
        size = np.linalg.norm(step, axis=1, keepdims=True)
        x = x - step * np.minimum(1.0, MAX_STEP_MM / np.maximum(size, 1e-300))  # a trust region
    return x


# --- sources that add to what each transmitter coil makes at a sensor ------------------------------


@dataclass(frozen=True)
class SoftIronCuboid:
    """A soft-iron box at ``centre_mm`` (Tracker), sides ``dimension_mm`` along the columns of ``axes`` (3, 3),
    magnetised by each coil's field at its centre through the susceptibility ``susceptibility`` (3,, per side)."""

    centre_mm: np.ndarray
    axes: np.ndarray
    dimension_mm: np.ndarray
    susceptibility: np.ndarray

    def coupling(self, points_mm: np.ndarray) -> np.ndarray:
        """The body's field per coil (K, 3, 3, columns per coil) at points (K, 3)."""
        import magpylib

        applied = coil_field(self.centre_mm[None])[0]  # (3, 3): the coils' fields at the body
        chi = self.axes @ np.diag(self.susceptibility) @ self.axes.T
        orientation = Rotation.from_matrix(self.axes)
        out = np.empty((len(points_mm), 3, 3))
        for k in range(3):  # magpylib takes the polarisation in the body's own axes
            body = magpylib.magnet.Cuboid(polarization=self.axes.T @ (chi @ applied[:, k]),
                                          dimension=self.dimension_mm / 1000.0, position=self.centre_mm / 1000.0,
                                          orientation=orientation)
            out[:, :, k] = body.getB(np.asarray(points_mm) / 1000.0).reshape(-1, 3)
        return out


@dataclass(frozen=True)
class EddyRing:
    """A conductive ring (radius ``radius_mm``, normal ``normal``) at ``centre_mm`` (Tracker): each coil drives an
    eddy current ``-gain * flux`` through it (the flux of that coil's field over the ring's disk)."""

    centre_mm: np.ndarray
    normal: np.ndarray
    radius_mm: float
    gain: float = 1.0

    def _rotation(self) -> np.ndarray:
        n = self.normal / np.linalg.norm(self.normal)
        helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(n, helper)
        u /= np.linalg.norm(u)
        return np.column_stack([u, np.cross(n, u), n])

    def flux(self) -> np.ndarray:
        """Each coil's flux (3,) through the ring's disk (polar quadrature)."""
        rotation = self._rotation()
        radii = (np.arange(6) + 0.5) / 6 * self.radius_mm
        angles = np.arange(12) / 12 * 2 * np.pi
        rr, aa = np.meshgrid(radii, angles, indexing="ij")
        local = np.stack([rr * np.cos(aa), rr * np.sin(aa), np.zeros_like(rr)], axis=-1).reshape(-1, 3)
        area = (rr * (self.radius_mm / 6) * (2 * np.pi / 12)).reshape(-1)
        fields = coil_field(self.centre_mm + local @ rotation.T)  # (Q, 3, 3)
        return np.einsum("q,qik,i->k", area, fields, rotation[:, 2])

    def coupling(self, points_mm: np.ndarray) -> np.ndarray:
        """The ring's field per coil (K, 3, 3) at points (K, 3)."""
        import magpylib

        flux = self.flux()
        ring = magpylib.current.Circle(current=1.0, diameter=2 * self.radius_mm / 1000.0,
                                       position=self.centre_mm / 1000.0,
                                       orientation=Rotation.from_matrix(self._rotation()))
        unit = ring.getB(np.asarray(points_mm) / 1000.0).reshape(-1, 3)
        return -self.gain * unit[:, :, None] * flux[None, None, :]


@dataclass(frozen=True)
class ExactDipole:
    """EMReg's induced dipole (:func:`EMRegModule.core.em_field.induced_coupling`), solved exactly rather than to first
    order: one object among several of ``multi``."""

    object_mm: np.ndarray
    polarisability: np.ndarray

    def coupling(self, points_mm: np.ndarray) -> np.ndarray:
        return induced_coupling(points_mm, self.object_mm, self.polarisability)


@dataclass(frozen=True)
class Gradient:
    """A field gradient across the working volume (a large, distant mass): coil k's field gains
    ``|F(c) e_k| * gradients_per_mm[k] @ (x - c)`` (each gradient symmetric and traceless, as a field free of
    currents and sources has), ``c = centre_mm`` (Tracker, mm)."""

    centre_mm: np.ndarray
    gradients_per_mm: np.ndarray  # (3, 3, 3): per coil

    def coupling(self, points_mm: np.ndarray) -> np.ndarray:
        strength = np.linalg.norm(coil_field(self.centre_mm[None])[0], axis=0)  # (3,)
        offset = np.asarray(points_mm) - self.centre_mm
        return np.einsum("kij,nj->nik", self.gradients_per_mm, offset) * strength[None, None, :]


# --- the fields ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Timed(TimedField):
    """What every field here shares with :class:`~EMRegModule.simulation.distortion.FieldDistortion` (when it is
    there, how it moves the poses: :class:`~EMRegModule.simulation.distortion.TimedField`), and how strongly
    (``gain``)."""

    def distortion_mm(self, position_mm: np.ndarray) -> float:
        """The position error's size (mm) at full strength at ``position_mm`` (3,, Tracker)."""
        return float(np.linalg.norm(self.errors_at(np.asarray(position_mm, dtype=float).reshape(1, 3))[0][0]))

    def scaled(self, factor: float) -> Any:
        return replace(self, gain=self.gain * float(factor))


@dataclass(frozen=True)
class BodiesField(_Timed):
    """Bodies in the transmitter's field (``magpylib`` / ``multi``): their couplings, times ``gain``, added to the
    transmitter's, and the position solved with the free-space model as a tracker does (Tracker frame, mm)."""

    sources: tuple = ()
    gain: float = 1.0
    family: str = "magpylib"
    weights: tuple = ()  # per source (default: 1 each)
    onset_s: float = float("-inf")
    ramp_s: float = DEFAULT_RAMP_S

    def errors_at(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reported position's error (K, 3, mm) and rotation error (K, 3, 3) at true positions (K, 3)."""
        x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        weights = self.weights or (1.0,) * len(self.sources)
        measured = coil_field(x) + self.gain * sum(w * s.coupling(x) for w, s in zip(weights, self.sources,
                                                                                      strict=True))
        reported = solve_position(measured, x)
        return reported - x, polar_rotation(coil_field(reported) @ np.swapaxes(measured, -1, -2))

    def to_json(self) -> dict[str, Any]:
        return {"model": f"{self.family}: bodies' fields (magpylib) added to a dipole transmitter's, position solved "
                         "with the free-space model", "sources": [type(s).__name__ for s in self.sources],
                "gain": self.gain}


@dataclass(frozen=True)
class SmoothField(_Timed):
    """A random smooth displacement field (Tracker frame, mm): ``gain * sum_j a_j cos(w_j . x + b_j)``, random
    Fourier features of a squared-exponential Gaussian process; orientations untouched."""

    frequencies: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3) rad/mm
    phases: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (J,)
    amplitudes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3)
    gain: float = 1.0
    onset_s: float = float("-inf")
    ramp_s: float = DEFAULT_RAMP_S

    def errors_at(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(points_mm, dtype=float).reshape(-1, 3)
        error = self.gain * np.cos(x @ self.frequencies.T + self.phases) @ self.amplitudes
        return error, np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()

    def to_json(self) -> dict[str, Any]:
        return {"model": "gp: random smooth displacement field (random Fourier features)", "gain": self.gain}


# --- placing a field of a family beside a frame -----------------------------------------------


def _random_direction(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _outside(rng: np.random.Generator, centre: np.ndarray, radius: float, gap_mm: tuple[float, float]) -> np.ndarray:
    """A position ``gap_mm`` beyond a sphere around the points, at least 120 mm from the transmitter."""
    for _ in range(100):
        position = centre + _random_direction(rng) * (radius + rng.uniform(*gap_mm))
        if np.linalg.norm(position) > 120.0:
            return position
    return position


def _random_axes(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _body(rng: np.random.Generator, centre: np.ndarray, radius: float, kinds: tuple[str, ...]) -> Any:
    kind = kinds[int(rng.integers(len(kinds)))]
    position = _outside(rng, centre, radius, (30.0, 110.0))
    if kind == "cuboid":
        return SoftIronCuboid(position, _random_axes(rng), np.array([rng.uniform(60, 250), rng.uniform(10, 50),
                                                                       rng.uniform(5, 30)]),
                              np.array([1.0, rng.uniform(0.05, 0.3), rng.uniform(0.02, 0.1)]))
    if kind == "ring":
        return EddyRing(position, _random_direction(rng), float(rng.uniform(30, 120)))
    axis = _random_direction(rng)
    return ExactDipole(position, 1e5 * (np.outer(axis, axis) + 0.1 * (np.eye(3) - np.outer(axis, axis))))


def _gentle(source: Any, points_tracker: np.ndarray) -> float:
    """A gain that makes ``source``'s coupling at the points 0.1 % of the transmitter's (RMS): a safe start for
    :func:`scale_to` whatever the source's own units."""
    ratio = np.sqrt(np.mean(source.coupling(points_tracker) ** 2) / np.mean(coil_field(points_tracker) ** 2))
    return 1e-3 / max(float(ratio), 1e-300)


def scale_to(distortion: Any, points_body: np.ndarray, body_to_tracker: np.ndarray, reference_to_body: np.ndarray,
             nonrigid_rms_mm: float) -> Any:
    """``distortion`` (any family) rescaled (``scaled``) so that its non-rigid RMS at the points is
    ``nonrigid_rms_mm`` (secant steps: the exact solve is not linear in the strength)."""
    for _step in range(6):
        _, nonrigid = nonrigid_errors(distortion, points_body, body_to_tracker, reference_to_body)
        rms = float(np.sqrt(np.mean(np.sum(nonrigid**2, axis=1))))
        if not np.isfinite(rms) or rms <= 0 or abs(rms - nonrigid_rms_mm) < 1e-3 * max(nonrigid_rms_mm, 1e-3):
            break
        distortion = distortion.scaled(float(np.clip(nonrigid_rms_mm / rms, 0.2, 5.0)))
    return distortion


def place_field(family: str, rng: np.random.Generator, points_body: np.ndarray, body_to_tracker: np.ndarray,
                reference_to_body: np.ndarray, nonrigid_rms_mm: float) -> Any:
    """A distorted field of ``family`` (:data:`FAMILIES`) beside the points (K, 3, Body frame, mm) of a body at
    ``body_to_tracker``, scaled to ``nonrigid_rms_mm`` RMS non-rigid error at them (Reference frame, mm)."""
    if family == "dipole":
        return place_object(rng, points_body, body_to_tracker, reference_to_body, nonrigid_rms_mm)
    if family not in FAMILIES:
        raise ValueError(f"unknown field family {family!r}; families: {', '.join(FAMILIES)}")
    for _attempt in range(20):  # a body so placed that its size cannot be reached (or solved) is drawn again
        with np.errstate(all="ignore"):
            try:
                distortion = _draw(family, rng, points_body, body_to_tracker, reference_to_body, nonrigid_rms_mm)
            except np.linalg.LinAlgError:
                continue
            _, nonrigid = nonrigid_errors(distortion, points_body, body_to_tracker, reference_to_body)
        rms = float(np.sqrt(np.mean(np.sum(nonrigid**2, axis=1))))
        if np.isfinite(rms) and abs(rms - nonrigid_rms_mm) < 0.01 * nonrigid_rms_mm:
            return distortion
    raise RuntimeError(f"no {family} field of {nonrigid_rms_mm} mm could be placed")


def _draw(family: str, rng: np.random.Generator, points_body: np.ndarray, body_to_tracker: np.ndarray,
          reference_to_body: np.ndarray, nonrigid_rms_mm: float) -> Any:
    """One random field of ``family`` (not ``dipole``) scaled to ``nonrigid_rms_mm`` (see :func:`place_field`)."""
    points_tracker = apply_transform(body_to_tracker, np.asarray(points_body, dtype=float))
    centre = points_tracker.mean(axis=0)
    radius = float(np.max(np.linalg.norm(points_tracker - centre, axis=1)))
    if family == "gp":
        length = radius * rng.uniform(0.4, 1.2)
        count = 64
        distortion: Any = SmoothField(rng.normal(0.0, 1.0 / length, (count, 3)), rng.uniform(0, 2 * np.pi, count),
                                      rng.normal(size=(count, 3)) * np.sqrt(2.0 / count))
    elif family == "magpylib":
        body = _body(rng, centre, radius, ("cuboid", "ring"))
        distortion = BodiesField((body,), _gentle(body, points_tracker), "magpylib")
    elif family == "multi":
        sources = [_body(rng, centre, radius, ("cuboid", "ring", "dipole")) for _ in range(int(rng.integers(2, 4)))]
        gradients = rng.normal(size=(3, 3, 3))
        gradients = 0.5 * (gradients + np.swapaxes(gradients, -1, -2))
        gradients -= np.trace(gradients, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
        sources.append(Gradient(centre, gradients))
        # each source alone scaled to 1 mm, then weighted at random: no one of them rules by its units
        weights = [scale_to(BodiesField((source,), _gentle(source, points_tracker)), points_body, body_to_tracker,
                            reference_to_body, 1.0).gain * rng.uniform(0.3, 1.0) for source in sources]
        distortion = BodiesField(tuple(sources), 1.0, "multi", tuple(weights))
    return scale_to(distortion, points_body, body_to_tracker, reference_to_body, nonrigid_rms_mm)
