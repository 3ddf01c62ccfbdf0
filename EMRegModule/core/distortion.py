"""Field distortion seen at registration: residuals that are spatially coherent, beyond what noise explains.

The CT is geometrically true; the EM measurements are not once metal distorts the field. After the
rigid fit (with l), the residual of each calibration point is its tracking noise plus the non-rigid
part of the distortion, a smooth field (neighbouring pinholes displaced alike). Noise is independent
from pinhole to pinhole; a distortion is not. Everything here is in the **Reference frame** (mm): the
field is the displacement of an EM measurement from where it should be, less the rigid motion the
registration absorbs of it.

**Model.** The residual vector ``r`` (3N) is ``P (f + e)``: ``P`` removes what the rigid fit (rotation,
translation, and l when solved) absorbs; ``e`` is noise of unknown size, independent per point (the probe's
per-dwell error and the CT's localisation); ``f`` is a smooth field of *unknown family*. The detector was designed
around EMReg's induced dipole and measured only on it; on fields of other shapes it missed (issue 37). So the
candidates are now of several kinds, the dipole one among them:

- an induced dipole (:mod:`EMRegModule.core.em_field`) at positions around the frame, linear in its six
  polarisability coefficients (only when the calibration kept where the transmitter was, ``TrackerToReference``);
- single smooth Gaussian bumps (3 amplitudes each) at and outside the pinholes, widths a fraction of the frame;
- generic smooth fields of no physics: polynomial displacement fields of degree 1-3 in position, and the smoothest
  modes of Gaussian processes of several lengths on the pinholes (extended elsewhere by the kernel).

**Test.** Each candidate's share of ``|r|^2`` is turned into its own tail probability under isotropic noise (the
share a rank-P subspace takes of an isotropic vector in the m residual dimensions is Beta(P/2, (m-P)/2)), so that
candidates of 3 and of 50 columns compete on one scale; the statistic is the smallest of these. Its distribution
under noise alone does not depend on the noise's size (only the geometry enters): it is drawn by Monte Carlo once
per geometry (deterministic seed), which accounts exactly for having tried every candidate, and the p-value is
compared with ``[registration] distortion_false_alarm``. No noise level is used at all, so a distortion cannot hide
inside a noise estimate made from its own residuals. (A permutation null, the residual vectors shuffled among the
pinholes, is available as :data:`NULL`; the Gaussian one is the default, exact for isotropic noise.)

**Noise from independent evidence.** The share test divides by the residuals' own sum of squares, the signal
included, and loses power as the noise grows. When the probe's per-dwell error is known from evidence other than
the residuals (:class:`NoisePrior`: the within-dwell spread of the calibration samples times the tracker's ratio,
``[registration] dwell_error_ratio``), a second statistic compares each candidate's explained sum of squares with
that noise (its chi-square tail), the smallest over the candidates; the reported p-value is that of the smaller of
the two tests' p-values against the same over the Monte Carlo null draws of both (the false-alarm rate stays
``alpha``, where twice the smaller, Bonferroni, would cost power), the known-noise one
counted only when the share test leans the same way (:data:`SHARE_SUPPORT`): a noise level set
too small (a tracker of another ratio, a tool whose tip error the dwells do not show) would make any residual look
coherent, and the largest candidate fit it. The noise level grows
with the tracker's real noise, while a field's coherent residual stays. The same prior checks the FRE
(:attr:`DistortionEstimate.fle_ratio`): in the Fitzpatrick model the residual sum of squares is ``(3N - P) FLE^2``,
so an FRE above what the prior explains (beside any fitted field) means an error the model does not know of; the
prediction then takes the larger FLE the residuals show, says it is not to be trusted, and above
``[registration] max_fle_ratio`` the registration is refused.

**One bad pair or a field.** A probe not fully inserted moves one point; a field moves several neighbours. The
evidence is put down to one bad pair only when all three hold: the largest residual is an outlier by itself (its
share of the sum of squares beyond what noise gives in this geometry, :data:`OUTLIER_LEVEL`), the other pinholes
alone are not even weakly significant (:data:`WITHOUT_LARGEST_LEVEL`), and the field they pick does not predict
the largest residual (:data:`PREDICTED_SHARE`). A strong test is no longer overruled merely because dropping its
largest residual leaves a p-value a little above the false-alarm rate (issue 37, cases C and E).

Why not a chi-square against the error model's FLE: with one dwell per pinhole the FLE is estimated from
these same residuals (a dwell's spread shows the tracker's jitter, not its per-dwell error, which is
several times larger), so the ratio is one by construction; a noise level known beforehand would make
the test only as good as that guess.

**Estimate.** When detected, the best candidate (a dipole's position refined by Nelder-Mead) is fitted by
least squares: its non-rigid field at the pinholes gives ``rms_mm`` / ``max_mm``; its field and the
covariance of its amplitudes give the distortion's mean square at any point probed in the same field
(:meth:`DistortionEstimate.mean_square_at`, the error model's distortion term), plus what the fitted family
misses where it was not fitted, measured by its own leave-one-out errors at the pinholes beyond their noise (a
field of another family than the fitted one is predicted with that miss, not as if its family were known), and
the noise that remains beside it replaces the probe's per-dwell error of the error model.
:meth:`DistortionEstimate.prediction_trust` says, for ``registration.json``, why the prediction may not be
trusted: a distortion measured, one suspected (p below :data:`SUSPECT_LEVEL`), or no test possible.

**What a clean result means.** "Nothing detected" speaks only for fields the test could have seen.
:func:`detectable_rms` measures, per session, the smallest field (RMS of its non-rigid part at the pinholes) the
test finds in :data:`POWER_LEVEL` of random smooth fields at this session's noise and pinholes; it is written to
``registration.json`` (``detectable_rms_mm``), and above ``[registration] max_undetectable_distortion_mm`` the
registration warns and :meth:`DistortionEstimate.prediction_trust` says the prediction cannot be trusted (refused
with ``refuse_undetectable_distortion``): with that much tracking noise, or that few pinholes, no distortion found
does not mean no distortion.

**Validation.** ``emreg study trust`` measures detection, false alarms and predicted / measured TRE on field
families the detector was not designed around (:mod:`EMRegModule.simulation.field_families`: magpylib bodies
solved as a tracker does, several bodies with a field gradient), beside the development ones (the induced dipole,
random smooth Gaussian-process fields) the constants here were chosen on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .em_field import FieldAtPoints
from .error_model import fiducial_jacobian
from .transforms import mean_rigid

#: Bump widths tried, as fractions of the RMS distance of the pinholes from their centroid.
LENGTH_FRACTIONS = (0.3, 0.5, 0.8)
#: Bump centres: the pinholes, and the pinholes pushed out from the centroid by this factor (an object outside).
OUTWARD = 1.35
#: Candidate objects: directions from the pinholes' centre, and gaps (mm) beyond their farthest one.
OBJECT_DIRECTIONS = 64
OBJECT_GAPS_MM = (15.0, 50.0, 100.0, 180.0, 300.0)
#: Candidate objects nearer than this to the transmitter (mm) are not tried.
MIN_TRANSMITTER_DISTANCE_MM = 80.0
#: Monte Carlo draws of the null distribution (p-values resolved to 1 / 2001, ample for a false-alarm rate of 0.002).
NULL_DRAWS = 2000
#: Relative size below which a candidate's column direction counts as absent (its rank, its fit).
RANK_TOLERANCE = 1e-9
#: Fewest residual degrees of freedom a test needs (below: not tested).
MIN_DOF = 6
#: Share of the largest residual's square the field fitted to the other pinholes must predict, when those alone are
#: not significant (simulated, 12 each: a bad pair at most 0.14, a rod's field 0.44-0.96).
PREDICTED_SHARE = 0.5
#: The other pinholes alone carry the evidence when their own test's p-value is at most this.
WITHOUT_LARGEST_LEVEL = 0.05
#: A calibration point left unpaired within this fraction of the pinholes' RMS distance from their centroid of the
#: largest residual's pinhole (the widest bump the test tries) is a neighbour moved too: not one bad pair.
NEIGHBOUR_FRACTION = LENGTH_FRACTIONS[-1]
#: A bad pair's residual lies along its pinhole's axis (a probe not fully inserted): at least this share of its square.
AXIAL_SHARE = 0.7
#: Below this p-value a distortion not detected is still named as a reason not to trust the prediction.
SUSPECT_LEVEL = 0.05
#: The known-noise test counts only when the share test's p-value is at most this (chosen on the development
#: fields: it keeps most of the known-noise test's gain, and a pivoting stylus's calibration, whose dwells do not show
#: its tip error, no longer looks distorted).
SHARE_SUPPORT = 0.2
#: The largest residual is a bad pair's candidate only when its share of the sum of squares has a p-value below this.
OUTLIER_LEVEL = 0.01
#: Generic smooth candidates: polynomial degrees, Gaussian-process lengths (fractions of the pinholes' RMS distance
#: from their centroid) and numbers of their smoothest modes.
POLYNOMIAL_DEGREES = (1, 2, 3)
GP_LENGTH_FRACTIONS = (0.5, 1.0, 2.0)
GP_MODES = (4, 8)
#: The null distribution: "gaussian" (isotropic noise drawn) or "permutation" (the residual vectors shuffled).
NULL = "gaussian"
#: The detectable size: the non-rigid RMS at the pinholes the test finds in this share of random smooth fields
#: (:func:`detectable_rms`), drawn (:data:`POWER_DRAWS` of them, Gaussian processes of :data:`POWER_LENGTH_FRACTIONS`
#: of the pinholes' RMS distance from their centroid) with this session's noise and geometry.
POWER_LEVEL = 0.9
POWER_DRAWS = 300
POWER_LENGTH_FRACTIONS = (0.5, 1.0, 2.0)
#: Bisection steps of each draw's smallest detected size (the size resolved to 2^-steps of its bracket).
POWER_STEPS = 10
#: Doublings of a draw's size, from 4 x the noise, before it counts as never found (2^10: a field 4000 x the noise).
POWER_WIDENINGS = 10


@dataclass(frozen=True)
class NoisePrior:
    """The probe's per-dwell localisation error known apart from the residuals tested: ``sigma_mm`` per axis (mm),
    and ``source``, where it comes from (words for ``registration.json`` and the report)."""

    sigma_mm: float
    source: str


def size_words(size_mm: float) -> str:
    """A detectable size in words: "up to 1.20 mm", or "any size" when infinite."""
    return f"up to {size_mm:.2f} mm" if np.isfinite(size_mm) else "any size"


def _kernel(points_a: np.ndarray, points_b: np.ndarray, length_mm: np.ndarray | float) -> np.ndarray:
    """Gaussian bump values exp(-|a - b|^2 / (2 L^2)), (len(a), len(b)); ``length_mm`` per b or one."""
    squared = np.sum((points_a[:, None, :] - points_b[None, :, :]) ** 2, axis=-1)
    return np.exp(-squared / (2.0 * np.asarray(length_mm, dtype=float) ** 2))


def _rigid_jacobian(points: np.ndarray, axes: np.ndarray | None) -> np.ndarray:
    """The stacked rigid-fit Jacobian (3N, P) at the pinholes (rotation about their centroid, translation, l)."""
    return fiducial_jacobian(points, points.mean(axis=0), axes).reshape(3 * len(points), -1)


def _complement(jacobian: np.ndarray) -> np.ndarray:
    """An orthonormal basis (3N, m) of what the rigid fit leaves: residuals live there."""
    u, s, _ = np.linalg.svd(jacobian, full_matrices=True)
    return u[:, int(np.sum(s > s[0] * 1e-10)):]


def _fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit directions (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    angle = np.pi * (1.0 + np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(angle), r * np.sin(angle), z])


# --- the two field models: an induced dipole, or smooth bumps ---------------------------------


@dataclass(frozen=True)
class _Dipole:
    """An induced dipole at ``object_mm`` (Tracker frame); pinholes seen from the transmitter through each one's
    ``TrackerToReference`` (the frame may have moved between dwells). Amplitudes: the six symmetric
    polarisability coefficients (mm^3, :data:`EMRegModule.core.em_field.SYMMETRIC_BASIS`)."""

    object_mm: np.ndarray
    tracker_to_reference: np.ndarray  # (4, 4): for points other than the pinholes (the calibration's mean pose)

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: _Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 6) in the Reference frame at points (K, 3), each with its pose (K, 4, 4) or the mean
        (``seen``: those points as the transmitter sees them, kept)."""
        seen = seen or _Seen(points_reference, np.broadcast_to(
            self.tracker_to_reference if tracker_to_reference is None else tracker_to_reference,
            (len(points_reference), 4, 4)))
        return seen.rotation @ seen.field.error_basis(self.object_mm)


class _Seen:
    """Points of the Reference frame as the transmitter sees them: their poses' rotations (K, 3, 3) and the
    free-space field there (:class:`EMRegModule.core.em_field.FieldAtPoints`)."""

    def __init__(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray) -> None:
        self.rotation = tracker_to_reference[:, :3, :3]
        origin = tracker_to_reference[:, :3, 3]
        self.points_tracker = np.einsum("kji,kj->ki", self.rotation, np.asarray(points_reference) - origin)
        self.field = FieldAtPoints(self.points_tracker)


@dataclass(frozen=True)
class _Bumps:
    """Gaussian bumps at ``centres_mm`` (B, 3, Reference) of widths ``lengths_mm`` (B,); amplitudes: a
    displacement (mm, 3) per bump."""

    centres_mm: np.ndarray
    lengths_mm: np.ndarray

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: _Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3B) at points (K, 3) of the Reference frame."""
        kernel = _kernel(np.asarray(points_reference, dtype=float), self.centres_mm, self.lengths_mm)
        return np.einsum("kb,cd->kcbd", kernel, np.eye(3)).reshape(len(kernel), 3, -1)


@dataclass(frozen=True)
class _Polynomial:
    """A displacement field polynomial in position (Reference frame): every monomial of
    ``(x - centre_mm) / scale_mm`` up to ``degree``, times each axis; amplitudes: mm per monomial and axis."""

    centre_mm: np.ndarray
    scale_mm: float
    degree: int

    def exponents(self) -> np.ndarray:
        return np.array([(i, j, k) for total in range(self.degree + 1) for i in range(total + 1)
                         for j in range(total + 1 - i) for k in (total - i - j,)])

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: _Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3M) at points (K, 3) of the Reference frame (M monomials)."""
        u = (np.asarray(points_reference, dtype=float).reshape(-1, 3) - self.centre_mm) / self.scale_mm
        monomials = np.prod(u[:, None, :] ** self.exponents()[None], axis=-1)  # (K, M)
        return np.einsum("km,cd->kcmd", monomials, np.eye(3)).reshape(len(u), 3, -1)


@dataclass(frozen=True)
class _Modes:
    """The smoothest fields a Gaussian process of length ``length_mm`` puts on the pinholes ``centres_mm`` (B, 3):
    the kernel's leading eigenvectors there, extended to any point by the kernel (Nystrom), ``weights`` (B, M);
    amplitudes: a displacement (mm, 3) per mode."""

    centres_mm: np.ndarray
    length_mm: float
    weights: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, length_mm: float, modes: int) -> _Modes:
        values, vectors = np.linalg.eigh(_kernel(points, points, length_mm))
        order = np.argsort(values)[::-1][:modes]
        return cls(points, float(length_mm), vectors[:, order] / np.maximum(values[order], 1e-12))

    def columns(self, points_reference: np.ndarray, tracker_to_reference: np.ndarray | None = None,
                seen: _Seen | None = None) -> np.ndarray:
        """Field columns (K, 3, 3M) at points (K, 3) of the Reference frame."""
        values = _kernel(np.asarray(points_reference, dtype=float).reshape(-1, 3), self.centres_mm,
                         self.length_mm) @ self.weights  # (K, M)
        return np.einsum("km,cd->kcmd", values, np.eye(3)).reshape(len(values), 3, -1)


def _stack(columns: np.ndarray) -> np.ndarray:
    """(N, 3, P) -> (3N, P), rows point-major (as the rigid Jacobian)."""
    return columns.reshape(-1, columns.shape[-1])


class _Group:
    """Candidate fields of one kind and column count, and each one's orthonormal column basis in the residual
    basis Q (C, m, P) with its rank (C,)."""

    def __init__(self, candidates: list, bases: np.ndarray, ranks: np.ndarray) -> None:
        self.candidates, self.bases, self.ranks = candidates, bases, ranks
        n_candidates, m, n_columns = bases.shape
        self.flat = np.ascontiguousarray(np.transpose(bases, (1, 0, 2)).reshape(m, n_candidates * n_columns))

    def fractions(self, z: np.ndarray) -> np.ndarray:
        """The share of |z|^2 each candidate explains (..., C), z (..., m)."""
        n_candidates, _, n_columns = self.bases.shape
        projections = (z @ self.flat).reshape(z.shape[:-1] + (n_candidates, n_columns))
        return np.sum(projections**2, axis=-1) / np.sum(z**2, axis=-1)[..., None]


def _share_p_values(fractions: np.ndarray, ranks: np.ndarray, dof: int) -> np.ndarray:
    """P(a share >= ``fractions``) for a rank-P subspace of a dof-dimensional isotropic vector: the Beta(P/2,
    (dof - P)/2) tail, so that candidates of different sizes compete on one scale."""
    from scipy.special import betainc

    a = np.asarray(ranks, dtype=float) / 2.0
    b = (dof - np.asarray(ranks, dtype=float)) / 2.0
    return betainc(b, a, np.clip(1.0 - fractions, 0.0, 1.0))


@dataclass
class _Scan:
    """Candidate fields in the residual basis Q (3N, m): induced dipoles around the frame (with the transmitter's
    poses), single Gaussian bumps, and generic smooth fields (polynomials, a Gaussian process's smoothest modes)."""

    basis: np.ndarray
    groups: list
    seen: _Seen | None = None

    @classmethod
    def of(cls, points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None) -> _Scan:
        basis = _complement(_rigid_jacobian(points, axes))
        seen = None if poses is None else _Seen(points, poses)
        kinds = [_bump_candidates(points)] + [[c] for c in _generic_candidates(points)]
        if seen is not None:
            kinds.insert(0, _dipole_candidates(seen, poses))
        groups = []
        for candidates in kinds:
            if not candidates:
                continue
            design = np.stack([basis.T @ _stack(c.columns(points, poses, seen)) for c in candidates])
            q, r = np.linalg.qr(design)  # (C, m, P)
            diagonal = np.abs(np.diagonal(r, axis1=-2, axis2=-1))
            keep = diagonal > RANK_TOLERANCE * diagonal.max(axis=-1, keepdims=True)  # drop dependent columns
            ranks = keep.sum(axis=-1)
            if ranks.max() > basis.shape[1] - MIN_DOF:
                continue
            q = q * keep[:, None, :]
            for rank in np.unique(ranks):  # one rank per group: its share's tail is monotone in the share
                chosen = np.nonzero(ranks == rank)[0]
                groups.append(_Group([candidates[i] for i in chosen], q[chosen], ranks[chosen]))
        return cls(basis, groups, seen)

    @property
    def dof(self) -> int:
        return int(self.basis.shape[1])

    @property
    def candidates(self) -> list:
        return [c for g in self.groups for c in g.candidates]

    def rank_of(self, index: int) -> int:
        """The rank candidate ``index`` (of :attr:`candidates`) was tested with."""
        for group in self.groups:
            if index < len(group.candidates):
                return int(group.ranks[index])
            index -= len(group.candidates)
        raise IndexError(index)

    def best(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For z (..., m): the smallest candidate p-value of the share test (:func:`_share_p_values`, no noise
        level), the share of |z|^2 that candidate explains, and its index in :attr:`candidates` (each (...,))."""
        return self.best_both(z)[0]

    def best_both(self, z: np.ndarray, sigma_mm: float | None = None) -> list[tuple[np.ndarray, np.ndarray,
                                                                                     np.ndarray]]:
        """:meth:`best` of the share test, and with ``sigma_mm`` (the noise per axis known) also of the known-noise
        test: the sum of squares each candidate explains against that noise, a chi-square of its rank's degrees of
        freedom (the candidates' fractions computed once for both)."""
        from scipy.special import gammaincc

        z = np.asarray(z, dtype=float)
        total = np.sum(z**2, axis=-1)
        fractions, indices, offset = [], [], 0
        p_values: list[list[np.ndarray]] = [[], []]
        for group in self.groups:
            f = group.fractions(z)
            best = np.argmax(f, axis=-1)
            fractions.append(np.take_along_axis(f, best[..., None], -1)[..., 0])
            indices.append(best + offset)
            p_values[0].append(_share_p_values(fractions[-1], group.ranks[0], self.dof))
            if sigma_mm is not None:
                p_values[1].append(gammaincc(group.ranks[0] / 2.0, fractions[-1] * total / (2.0 * sigma_mm**2)))
            offset += len(group.candidates)
        f_all, i_all = np.stack(fractions, -1), np.stack(indices, -1)
        out = []
        for p in p_values[:1 if sigma_mm is None else 2]:
            p_all = np.stack(p, -1)
            index = np.argmin(p_all, axis=-1)[..., None]
            out.append((np.take_along_axis(p_all, index, -1)[..., 0], np.take_along_axis(f_all, index, -1)[..., 0],
                        np.take_along_axis(i_all, index, -1)[..., 0]))
        return out


def _generic_candidates(points: np.ndarray) -> list:
    """Smooth fields of no physical family (Reference frame): polynomials of :data:`POLYNOMIAL_DEGREES` and the
    :data:`GP_MODES` smoothest modes of Gaussian processes :data:`GP_LENGTH_FRACTIONS` of the frame's size long."""
    centroid = points.mean(axis=0)
    radius = max(float(np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1)))), 1.0)
    fields: list = [_Polynomial(centroid, radius, degree) for degree in POLYNOMIAL_DEGREES]
    fields += [_Modes.of(points, radius * fraction, modes) for fraction in GP_LENGTH_FRACTIONS for modes in GP_MODES
               if modes < len(points)]
    return fields


def _dipole_candidates(seen: _Seen, poses: np.ndarray) -> list[_Dipole]:
    """Objects around the pinholes (Tracker frame): :data:`OBJECT_DIRECTIONS` x :data:`OBJECT_GAPS_MM`."""
    points_tracker = seen.points_tracker
    centre = points_tracker.mean(axis=0)
    radius = float(np.max(np.linalg.norm(points_tracker - centre, axis=1)))
    mean = mean_rigid(poses)
    candidates = []
    for gap in OBJECT_GAPS_MM:
        for direction in _fibonacci_sphere(OBJECT_DIRECTIONS):
            position = centre + direction * (radius + gap)
            if np.linalg.norm(position) >= MIN_TRANSMITTER_DISTANCE_MM:
                candidates.append(_Dipole(position, mean))
    return candidates


def _bump_candidates(points: np.ndarray) -> list[_Bumps]:
    """Single bumps at the pinholes and pushed out from them, of :data:`LENGTH_FRACTIONS` widths."""
    centroid = points.mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1))))
    places = np.concatenate([points, centroid + OUTWARD * (points - centroid)])
    return [_Bumps(place[None], np.array([max(radius * f, 1.0)])) for place in places for f in LENGTH_FRACTIONS]


@dataclass
class DistortionEstimate:
    """The distortion test and the non-rigid field fitted at registration (Reference frame, mm).

    ``labels`` / ``image_markers``: the paired pinholes; ``points_mm`` (N, 3): their calibration points;
    ``residuals_mm`` (N, 3): measured point minus the registered CT pinhole; ``statistic``: the largest
    share of the residuals' sum of squares one candidate field explains; ``p_value``: its Monte Carlo
    p-value under noise alone; ``alpha``: the false-alarm rate it is compared with. The fitted field:
    ``model`` (a dipole or bumps; None: noise alone) with ``amplitudes`` (P,) and their covariance
    (P, P); ``rigid_per_amplitude`` (6, P): the rigid motion (rotation rad, translation mm, about the
    pinholes' centroid) the registration absorbs of each amplitude's field; ``at_pinholes_mm`` (N, 3):
    the non-rigid field at the pinholes; ``noise_sigma_mm`` (per axis) and ``noise_dof``: the noise beside it.
    """

    labels: list[str]
    points_mm: np.ndarray
    residuals_mm: np.ndarray
    statistic: float
    p_value: float
    alpha: float
    noise_sigma_mm: float
    noise_dof: float = float("inf")
    model: Any = None
    amplitudes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    amplitude_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    rigid_per_amplitude: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))
    at_pinholes_mm: np.ndarray | None = None
    tested: bool = True
    image_markers: list[str] = field(default_factory=list)
    note: str = ""
    #: One bad pair (a probe not fully inserted) is not a field: the pinhole of the largest residual (``left_out``)
    #: must be explained by the others too, either because they alone are significant (their p-value) or because
    #: the field they fit predicts at least :data:`PREDICTED_SHARE` of its residual's square (NaN: not computed).
    p_value_without_largest: float = float("nan")
    largest_predicted_share: float = float("nan")
    left_out: str = ""
    #: The evidence was put down to one bad pair at ``left_out`` (:func:`_several_points`): not a distortion.
    one_bad_pair: bool = False
    #: Calibration points the pairing left out that joined the test (near a CT pinhole no pair took): they add
    #: evidence; the field and the noise are measured on the pairs (``labels``) alone.
    tested_unpaired: list[str] = field(default_factory=list)
    #: The probe's per-dwell error known apart from the residuals (:class:`NoisePrior`; NaN: none) and its source.
    noise_prior_sigma_mm: float = float("nan")
    noise_prior_source: str = ""
    #: The smallest field (RMS of its non-rigid part at the pinholes, mm) this test finds in :data:`POWER_LEVEL` of
    #: random smooth fields at this session's noise and geometry (:func:`detectable_rms`; NaN: not tested).
    detectable_rms_mm: float = float("nan")
    #: The largest field the test may be unable to see before the prediction is not to be trusted (mm,
    #: ``[registration] max_undetectable_distortion_mm``; NaN: not checked).
    undetectable_limit_mm: float = float("nan")
    #: The fitted field's leave-one-out errors at the pinholes (:func:`_leave_one_out`): their mean square (mm^2, 3D)
    #: and the mean of ``tr((I - H_ii)^-1)``, what noise of unit variance per axis gives them (:attr:`extension_ms`).
    loo_ms: float = 0.0
    loo_noise_factor: float = 0.0

    @property
    def extension_ms(self) -> float:
        """What the fitted family misses where it was not fitted (mm^2, 3D, per point): the leave-one-out errors'
        mean square beyond what the noise gives them, the noise being the tracker's own known apart from the residuals
        when smaller than the noise beside the fit (which a misfit inflates, and would hide), else the latter. Added
        to the distortion predicted anywhere: a field of another family than the fitted one."""
        sigma = self.noise_sigma_mm
        if self.noise_prior_sigma_mm > 0:
            sigma = min(sigma, self.noise_prior_sigma_mm)
        return float(max(self.loo_ms - sigma**2 * self.loo_noise_factor, 0.0))

    @property
    def fle_ratio(self) -> float:
        """The per-dwell error the residuals show (beside the fitted field when one was detected) over the one known
        apart from them (NaN without a prior): near 1 when the FRE is what the tracker's noise explains."""
        if not (self.noise_prior_sigma_mm > 0):
            return float("nan")
        return float(self.noise_sigma_mm / self.noise_prior_sigma_mm)

    def fle_p_value(self) -> float:
        """The chance of residuals at least this much larger than the prior explains (chi-square on the noise's
        degrees of freedom; NaN without a prior)."""
        from scipy.special import gammaincc

        ratio = self.fle_ratio
        if not np.isfinite(ratio) or not np.isfinite(self.noise_dof):
            return float("nan")
        return float(gammaincc(self.noise_dof / 2.0, self.noise_dof * ratio**2 / 2.0))

    @property
    def fle_consistent(self) -> bool:
        """False when the residuals are larger than the prior explains at :data:`SUSPECT_LEVEL` (True without one)."""
        p = self.fle_p_value()
        return not (np.isfinite(p) and p <= SUSPECT_LEVEL)

    @property
    def detected(self) -> bool:
        return self.tested and self.p_value <= self.alpha and not self.one_bad_pair

    # --- the fitted field -------------------------------------------------------------------

    def _operator(self, points: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """``G(x) @ columns`` (K, 3, C) for amplitude columns (P, C): the model's field at x minus the rigid
        motion the registration absorbed of it."""
        raw = self.model.columns(points) @ columns
        motion = fiducial_jacobian(points, np.asarray(self.points_mm, dtype=float).mean(axis=0))
        return raw - motion @ (self.rigid_per_amplitude @ columns)

    def field_at(self, points_reference: np.ndarray) -> np.ndarray:
        """The fitted non-rigid displacement (K, 3, mm) at points (K, 3) of the Reference frame, probed with the
        frame where it was calibrated."""
        points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
        if self.model is None:
            return np.zeros_like(points)
        return self._operator(points, np.asarray(self.amplitudes, dtype=float).reshape(-1, 1))[..., 0]

    def mean_square_at(self, points_reference: np.ndarray) -> np.ndarray:
        """Expected squared distortion error (K,) (mm^2) at points (K, 3) of the Reference frame probed in the same
        field: the fitted field squared less its variance (navigation is not corrected by the fitted field, so the
        error holds the true field, whose square the fitted one's overstates by that variance on average; never
        below 0), plus what the fitted family itself misses where it was not fitted (:attr:`extension_ms`, from its
        leave-one-out errors at the pinholes: a field of another family than the fitted one); 0 everywhere when no
        distortion was detected. (Until issue 37's second round it was the fitted square plus the variance, and never
        less than the mean square measured at the pinholes: that overshot by 1.2-1.4x at targets inside the frame,
        where the rigid fit leaves the least of a field.)"""
        points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
        if not self.detected or self.model is None:
            return np.zeros(len(points))
        values, vectors = np.linalg.eigh(np.asarray(self.amplitude_covariance, dtype=float))
        columns = np.concatenate([np.asarray(self.amplitudes, dtype=float).reshape(-1, 1),
                                  vectors * np.sqrt(np.clip(values, 0.0, None))], axis=1)
        fitted, variance = np.empty(len(points)), np.empty(len(points))
        for start in range(0, len(points), 16384):
            chunk = np.sum(self._operator(points[start:start + 16384], columns) ** 2, axis=1)  # (k, columns)
            fitted[start:start + len(chunk)] = chunk[:, 0]
            variance[start:start + len(chunk)] = np.sum(chunk[:, 1:], axis=1)
        return np.clip(fitted - variance, 0.0, None) + self.extension_ms

    def measured_ms(self) -> float:
        """The non-rigid field's mean square over the pinholes (mm^2) with its uncertainty (the fitted field's
        variance there): the distortion measured at registration; 0 when none was detected."""
        if not self.detected or self.model is None:
            return 0.0
        values, vectors = np.linalg.eigh(np.asarray(self.amplitude_covariance, dtype=float))
        columns = np.concatenate([np.asarray(self.amplitudes, dtype=float).reshape(-1, 1),
                                  vectors * np.sqrt(np.clip(values, 0.0, None))], axis=1)
        return float(np.mean(np.sum(self._operator(np.asarray(self.points_mm, dtype=float), columns) ** 2,
                                    axis=(1, 2))))

    def prediction_trust(self) -> dict[str, Any]:
        """The ``registration.json`` ``prediction_trust`` block: whether the predicted TRE rests on a model the
        registration's own residuals agree with, and the reasons it may not (words for the user)."""
        reasons = []
        if not self.tested:
            why = self.note or "too few pinholes"
            reasons.append(f"the residuals could not be tested for field distortion ({why})")
        elif self.detected:
            reasons.append(f"field distortion measured at the pinholes ({self.rms_mm:.2f} mm RMS, up to "
                           f"{self.largest()[0]:.2f} mm near {self.where()}): the prediction adds the fitted field "
                           "and what its family misses between the pinholes, but how the field extends beyond them is "
                           "not known")
        elif self.p_value <= SUSPECT_LEVEL:
            why = (f"; the evidence was put down to one bad pair at {self.left_out}" if self.one_bad_pair else "")
            reasons.append(f"the residuals are more coherent than noise (p = {self.p_value:.2g}) without reaching the "
                           f"false-alarm rate of the distortion test ({self.alpha:g}){why}: a field distortion may be "
                           "hiding in the tracking error the prediction assumes")
        if self.tested and not self.detected and self.detectable_rms_mm > self.undetectable_limit_mm:
            reasons.append(f"with this tracking noise and these {len(self.labels) + len(self.tested_unpaired)} "
                           "pinholes, the distortion test could "
                           f"miss a field of {size_words(self.detectable_rms_mm)} RMS at the pinholes (above "
                           f"{self.undetectable_limit_mm:g} mm): no distortion found does not mean none is there, "
                           "and the prediction does not include one")
        if self.tested and not self.fle_consistent:
            reasons.append(f"the calibration residuals show a per-dwell error {self.fle_ratio:.1f} times what the "
                           f"tracker's own noise explains ({self.noise_prior_source}): the predicted TRE takes the "
                           "larger error the residuals show, but its cause (a probe not seated, a bent probe, an "
                           "unmodelled distortion) is not known")
        return {"trusted": not reasons, "reasons": reasons,
                "distortion_ms_mm2": round(self.measured_ms(), 6)}

    # --- summary and files ------------------------------------------------------------------

    def pinhole_field(self) -> np.ndarray:
        """The fitted non-rigid field at the pinholes (N, 3, mm)."""
        if self.at_pinholes_mm is None:
            return np.zeros_like(np.asarray(self.points_mm, dtype=float))
        return np.asarray(self.at_pinholes_mm, dtype=float)

    @property
    def rms_mm(self) -> float:
        sizes = np.linalg.norm(self.pinhole_field(), axis=1)
        return float(np.sqrt(np.mean(sizes**2))) if len(sizes) else 0.0

    def largest(self) -> tuple[float, int]:
        """The largest fitted field size at a pinhole (mm) and that pinhole's index (-1 without pinholes)."""
        sizes = np.linalg.norm(self.pinhole_field(), axis=1)
        return (float(sizes.max()), int(np.argmax(sizes))) if len(sizes) else (0.0, -1)

    def where(self) -> str:
        """The pinhole where the field is largest, named by calibration point (and CT marker)."""
        _, k = self.largest()
        if k < 0:
            return "-"
        marker = f" (CT marker {self.image_markers[k]})" if k < len(self.image_markers) else ""
        return f"{self.labels[k]}{marker}"

    def to_json(self) -> dict[str, Any]:
        """The ``registration.json`` ``distortion`` block."""
        largest, k = self.largest()

        def rounded(values: Any, digits: int = 6) -> list:
            return np.round(np.asarray(values, dtype=float), digits).tolist()

        model: dict[str, Any] | None = None
        if isinstance(self.model, _Dipole):
            model = {"kind": "dipole", "object_tracker_mm": rounded(self.model.object_mm),
                     "TrackerToReference": rounded(self.model.tracker_to_reference, 9),
                     "amplitudes": "polarisability (mm^3): xx, yy, zz, xy, xz, yz in the Tracker frame",
                     "formula": "d(x) = T_R @ dx(inv(T) x): the first-order position error of an induced dipole "
                                "(EMRegModule.core.em_field.position_error), T = TrackerToReference"}
        elif isinstance(self.model, _Bumps):
            model = {"kind": "bumps", "centres_mm": rounded(self.model.centres_mm),
                     "length_scales_mm": rounded(self.model.lengths_mm),
                     "amplitudes": "displacement (mm) x, y, z per bump",
                     "formula": "d(x) = sum_b exp(-|x - c_b|^2 / (2 L_b^2)) a_b"}
        elif isinstance(self.model, _Polynomial):
            model = {"kind": "polynomial", "centre_mm": rounded(self.model.centre_mm), "scale_mm": self.model.scale_mm,
                     "degree": self.model.degree, "exponents": self.model.exponents().tolist(),
                     "amplitudes": "displacement (mm) x, y, z per monomial",
                     "formula": "d(x) = sum_m prod(((x - centre) / scale) ** exponents_m) a_m"}
        elif isinstance(self.model, _Modes):
            model = {"kind": "modes", "centres_mm": rounded(self.model.centres_mm), "length_mm": self.model.length_mm,
                     "weights": rounded(self.model.weights, 12),
                     "amplitudes": "displacement (mm) x, y, z per mode",
                     "formula": "d(x) = sum_m (exp(-|x - c|^2 / (2 L^2)) @ weights)_m a_m"}
        return {
            "detected": self.detected, "rms_mm": round(self.rms_mm, 4), "max_mm": round(largest, 4),
            "max_at": self.labels[k] if k >= 0 else None, "tested": self.tested,
            "test": "share of the rigid fit's residual sum of squares the best candidate field explains (an induced "
                    "dipole near the frame, smooth bumps, polynomial fields, a Gaussian process's smoothest modes; "
                    "chosen by its tail probability), against the Monte Carlo distribution of the smallest tail "
                    "probability under independent noise" + ("; and the sum of squares it explains against the "
                                                              "noise_prior (chi-square), the smaller p-value's own"
                                                              if self.noise_prior_sigma_mm > 0 else ""),
            "statistic": round(float(self.statistic), 6), "p_value": round(float(self.p_value), 6),
            "alpha": float(self.alpha), **({"note": self.note} if self.note else {}),
            "p_value_without_largest": None if not np.isfinite(self.p_value_without_largest)
            else round(float(self.p_value_without_largest), 6),
            "largest_predicted_share": None if not np.isfinite(self.largest_predicted_share)
            else round(float(self.largest_predicted_share), 4),
            "left_out": self.left_out or None, "one_bad_pair": self.one_bad_pair,
            "tested_unpaired": list(self.tested_unpaired),
            "noise_sigma_mm": round(float(self.noise_sigma_mm), 5),
            **({"extension_ms_mm2": round(float(self.extension_ms), 6), "loo_ms_mm2": round(float(self.loo_ms), 6),
                "loo_noise_factor": round(float(self.loo_noise_factor), 6)} if self.detected else {}),
            **({"detectable_rms_mm": round(float(self.detectable_rms_mm), 4)
                if np.isfinite(self.detectable_rms_mm) else None,
                "detectable": f"the non-rigid RMS at the pinholes this test finds in {POWER_LEVEL:.0%} of random "
                              "smooth fields at this session's noise and pinholes (smaller fields may go unseen; "
                              "null: no size, the test misses too many smooth fields at any size)",
                **({"undetectable_limit_mm": float(self.undetectable_limit_mm)}
                   if np.isfinite(self.undetectable_limit_mm) else {})}
               if not np.isnan(self.detectable_rms_mm) else {}),
            "noise_dof": round(float(self.noise_dof), 3) if np.isfinite(self.noise_dof) else None,
            **({"noise_prior": {"sigma_mm": round(float(self.noise_prior_sigma_mm), 5),
                                "source": self.noise_prior_source, "fle_ratio": round(self.fle_ratio, 4),
                                "fle_p_value": round(self.fle_p_value(), 6)
                                if np.isfinite(self.fle_p_value()) else None}}
               if self.noise_prior_sigma_mm > 0 else {}),
            "field": {
                "frame": "Reference", "units": "mm",
                "description": "the EM measurement's displacement at x beyond the rigid motion the registration "
                               "absorbs: model(x) @ amplitudes - (omega x (x - centroid) + t), (omega, t) = "
                               "rigid_per_amplitude @ amplitudes",
                "model": model, "amplitudes": rounded(self.amplitudes, 9),
                "amplitude_covariance": rounded(self.amplitude_covariance, 12),
                "rigid_per_amplitude": rounded(self.rigid_per_amplitude, 15),
                "centroid_mm": rounded(np.asarray(self.points_mm, dtype=float).mean(axis=0)),
                "pinholes_mm": rounded(self.points_mm),
                "residuals_mm": rounded(self.residuals_mm),
                "at_pinholes_mm": rounded(self.pinhole_field()),
            },
            "labels": list(self.labels), "image_markers": list(self.image_markers),
        }

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> DistortionEstimate:
        """Inverse of :meth:`to_json`."""
        block = document["field"]
        stored = block.get("model")
        model: Any = None
        if stored and stored.get("kind") == "dipole":
            model = _Dipole(np.asarray(stored["object_tracker_mm"], dtype=float).reshape(3),
                            np.asarray(stored["TrackerToReference"], dtype=float).reshape(4, 4))
        elif stored and stored.get("kind") == "bumps":
            model = _Bumps(np.asarray(stored["centres_mm"], dtype=float).reshape(-1, 3),
                           np.asarray(stored["length_scales_mm"], dtype=float).reshape(-1))
        elif stored and stored.get("kind") == "polynomial":
            model = _Polynomial(np.asarray(stored["centre_mm"], dtype=float).reshape(3), float(stored["scale_mm"]),
                                int(stored["degree"]))
        elif stored and stored.get("kind") == "modes":
            centres = np.asarray(stored["centres_mm"], dtype=float).reshape(-1, 3)
            model = _Modes(centres, float(stored["length_mm"]),
                           np.asarray(stored["weights"], dtype=float).reshape(len(centres), -1))
        amplitudes = np.asarray(block.get("amplitudes", []), dtype=float).reshape(-1)
        n = len(amplitudes)
        return cls(labels=[str(v) for v in document.get("labels", [])],
                   points_mm=np.asarray(block["pinholes_mm"], dtype=float).reshape(-1, 3),
                   residuals_mm=np.asarray(block["residuals_mm"], dtype=float).reshape(-1, 3),
                   statistic=float(document["statistic"]), p_value=float(document["p_value"]),
                   alpha=float(document["alpha"]), noise_sigma_mm=float(document["noise_sigma_mm"]),
                   noise_dof=float("inf") if document.get("noise_dof") is None else float(document["noise_dof"]),
                   model=model, amplitudes=amplitudes,
                   amplitude_covariance=np.asarray(block.get("amplitude_covariance", []), dtype=float).reshape(n, n),
                   rigid_per_amplitude=np.asarray(block.get("rigid_per_amplitude", []), dtype=float).reshape(6, n),
                   at_pinholes_mm=np.asarray(block["at_pinholes_mm"], dtype=float).reshape(-1, 3),
                   tested=bool(document.get("tested", True)),
                   image_markers=[str(v) for v in document.get("image_markers", [])],
                   note=str(document.get("note", "")),
                   noise_prior_sigma_mm=float((document.get("noise_prior") or {}).get("sigma_mm", float("nan"))),
                   noise_prior_source=str((document.get("noise_prior") or {}).get("source", "")),
                   p_value_without_largest=float("nan") if document.get("p_value_without_largest") is None
                   else float(document["p_value_without_largest"]),
                   largest_predicted_share=float("nan") if document.get("largest_predicted_share") is None
                   else float(document["largest_predicted_share"]),
                   left_out=str(document.get("left_out") or ""),
                   one_bad_pair=bool(document["one_bad_pair"]) if "one_bad_pair" in document
                   else _older_bad_pair(document),
                   detectable_rms_mm=float("nan") if "detectable_rms_mm" not in document
                   else float("inf") if document["detectable_rms_mm"] is None else float(document["detectable_rms_mm"]),
                   undetectable_limit_mm=float(document.get("undetectable_limit_mm", float("nan"))),
                   tested_unpaired=[str(v) for v in document.get("tested_unpaired", [])],
                   loo_ms=float(document.get("loo_ms_mm2", 0.0)),
                   loo_noise_factor=float(document.get("loo_noise_factor", 0.0)))


def _older_bad_pair(document: Mapping[str, Any]) -> bool:
    """Whether a ``distortion`` block written before ``one_bad_pair`` was (issue 37, second round) put its evidence
    down to one bad pair: then the others' p-value above ``alpha`` and a predicted share below
    :data:`PREDICTED_SHARE` said so."""
    p_without, share = document.get("p_value_without_largest"), document.get("largest_predicted_share")
    return p_without is not None and share is not None and float(p_without) > float(document["alpha"]) \
        and float(share) < PREDICTED_SHARE


def null_statistics(scan: _Scan, draws: int = NULL_DRAWS, seed: int = 0,
                    residuals: np.ndarray | None = None, known_noise: bool = False) -> np.ndarray:
    """The test statistic (the smallest candidate p-value) under noise alone (draws,) for this geometry
    (deterministic: seeded). Without ``residuals``: isotropic Gaussian noise (exact for it, whatever its size);
    with ``residuals`` (N, 3): those vectors shuffled among the pinholes (a permutation null). ``known_noise``: the
    statistics of the share and of the known-noise tests of the same draws (draws, 2) (:meth:`_Scan.best_both`, the
    noise drawn of unit size)."""
    rng = np.random.default_rng(seed)
    if residuals is None:
        z = rng.standard_normal((draws, scan.dof))
    else:
        order = np.argsort(rng.random((draws, len(residuals))), axis=1)
        z = np.asarray(residuals, dtype=float)[order].reshape(draws, -1) @ scan.basis
    out = np.empty((draws, 2 if known_noise else 1))
    for start in range(0, draws, 250):
        for k, (smallest, _, _) in enumerate(scan.best_both(z[start:start + 250], 1.0 if known_noise else None)):
            out[start:start + 250, k] = smallest
    return out if known_noise else out[:, 0]


def _p_value(scan: _Scan, statistic: float, residuals: np.ndarray | None = None,
             null: np.ndarray | None = None) -> float:
    """The Monte Carlo p-value of a statistic (a smallest candidate p-value: small is significant) against
    ``null`` (draws,) or the share test's :func:`null_statistics`."""
    if null is None:
        null = null_statistics(scan, residuals=None if NULL == "gaussian" else residuals)
    return float((1 + np.count_nonzero(null <= statistic * (1 + 1e-9))) / (len(null) + 1))


def _refine(scan: _Scan, model: Any, points: np.ndarray, poses: np.ndarray | None, z: np.ndarray) -> Any:
    """A dipole's position refined from the best candidate (least remaining sum of squares); others as chosen."""
    if not isinstance(model, _Dipole):
        return model
    from scipy.optimize import minimize

    def remaining(position: np.ndarray) -> float:
        if np.linalg.norm(position) < MIN_TRANSMITTER_DISTANCE_MM:
            return float(z @ z)
        design = scan.basis.T @ _stack(_Dipole(position, model.tracker_to_reference).columns(points, poses, scan.seen))
        q, _ = np.linalg.qr(design)
        return float(z @ z - np.sum((q.T @ z) ** 2))

    result = minimize(remaining, model.object_mm, method="Nelder-Mead",
                      options={"xatol": 1.0, "fatol": 1e-6 * float(z @ z), "maxfev": 300,
                               "initial_simplex": model.object_mm + np.vstack([np.zeros(3), 25.0 * np.eye(3)])})
    return _Dipole(np.asarray(result.x, dtype=float), model.tracker_to_reference) \
        if result.fun < remaining(model.object_mm) else model


def _projected(points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None,
               residuals: np.ndarray) -> tuple[_Scan, np.ndarray] | None:
    """The candidates' scan of these pinholes and the residuals projected beyond the rigid fit, ``z`` (None: too few
    degrees of freedom to test, or nothing left beyond the fit)."""
    scan = _Scan.of(points, axes, poses)
    if not scan.groups or scan.dof < MIN_DOF + 3:
        return None
    z = scan.basis.T @ residuals.reshape(-1)
    return (scan, z) if np.any(z) else None


def _arrays(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
            tracker_to_reference: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                              np.ndarray | None]:
    """The inputs of :func:`estimate_distortion` / :func:`fit_field` as float arrays: points and residuals (N, 3),
    axes (N, 3) or None, the transmitter's poses (N, 4, 4) or None."""
    points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
    residuals = np.asarray(residuals_reference, dtype=float).reshape(-1, 3)
    axes = None if axes_reference is None else np.asarray(axes_reference, dtype=float).reshape(-1, 3)
    poses = None if tracker_to_reference is None else np.asarray(tracker_to_reference, dtype=float).reshape(-1, 4, 4)
    return points, residuals, axes, poses


def _test(points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None, residuals: np.ndarray,
          noise: NoisePrior | None = None, support: float = SHARE_SUPPORT
          ) -> tuple[_Scan, np.ndarray, float, float, int, np.ndarray] | None:
    """The scan, z, statistic's share, p-value, best candidate and the null draws of residuals (None: too few to
    test). With a ``noise`` prior: the share test and the known-noise test both, the smaller p-value's own and its
    candidate (the known-noise one only when the share test's p-value is at most ``support``); the null draws are
    then (draws, 2), else (draws,)."""
    projected = _projected(points, axes, poses, residuals)
    if projected is None:
        return None
    scan, z = projected
    if noise is None or not noise.sigma_mm > 0 or NULL != "gaussian":
        smallest, share, best = scan.best(z)
        null = null_statistics(scan, residuals=None if NULL == "gaussian" else residuals)
        return scan, z, float(share), _p_value(scan, float(smallest), null=null), int(best), null
    null = null_statistics(scan, known_noise=True)
    (smallest, share, best), (known, known_share, known_best) = scan.best_both(z, noise.sigma_mm)
    p_value, p_known = _p_value(scan, float(smallest), null=null[:, 0]), _p_value(scan, float(known), null=null[:, 1])
    if p_known < p_value and p_value <= support:  # a noise level too small makes any residual look coherent
        share, best = known_share, known_best
    return scan, z, float(share), _combined_p_value(null, p_value, p_known, support), int(best), null


def detectable_rms(scan: _Scan, points: np.ndarray, null: np.ndarray, alpha: float, noise_sigma_mm: float,
                   prior_sigma_mm: float | None = None, support: float = SHARE_SUPPORT,
                   max_fre_mm: float = float("inf")) -> float:
    """The smallest non-rigid field (RMS at the pinholes, mm) the test finds in :data:`POWER_LEVEL` of random smooth
    fields with this session's pinholes ``points`` (N, 3, Reference) and noise (``noise_sigma_mm`` per axis; the
    test's own known noise ``prior_sigma_mm``, None: the share test alone, ``null`` then (draws,) else (draws, 2)). A
    field whose residuals' RMS exceeds ``max_fre_mm`` counts as caught: the registration refuses such an FRE.

    No family is assumed: the fields are Gaussian processes of several lengths (:data:`POWER_LENGTH_FRACTIONS`),
    their non-rigid part scaled to each size, drawn with noise of the session's size (deterministic seed). Each
    draw's smallest detected size is found by bisection on the same draw (the test's verdict grows with the size),
    and the :data:`POWER_LEVEL` quantile of those is the answer. The one-bad-pair check is left out: it overrules
    single points, not smooth fields. The answer is the size of field this session could miss: a registration
    that found nothing says nothing about fields smaller than it. Infinite when more than 1 - :data:`POWER_LEVEL` of
    the fields are missed at every size (the share test alone judges a field's shape, not its size: one that no
    candidate follows is never found, however large)."""
    rng = np.random.default_rng(7)
    n = len(points)
    centroid = points.mean(axis=0)
    radius = max(float(np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1)))), 1.0)
    factors = [np.linalg.cholesky(_kernel(points, points, radius * fraction) + 1e-9 * np.eye(n))
               for fraction in POWER_LENGTH_FRACTIONS]
    directions = np.empty((POWER_DRAWS, scan.dof))
    for k in range(POWER_DRAWS):
        field_z = scan.basis.T @ (factors[k % len(factors)] @ rng.standard_normal((n, 3))).reshape(-1)
        directions[k] = field_z / max(float(np.linalg.norm(field_z)), 1e-300)
    noise_z = noise_sigma_mm * rng.standard_normal((POWER_DRAWS, scan.dof))
    known = prior_sigma_mm is not None and prior_sigma_mm > 0 and np.ndim(null) == 2
    share_null = np.sort(null[:, 0] if known else null)
    if known:
        known_null = np.sort(null[:, 1])
        combined_null = _combined_null(null, support)

    def found(size_mm: np.ndarray) -> np.ndarray:
        z = directions * (np.sqrt(n) * size_mm)[:, None] + noise_z
        refused = np.sum(z**2, axis=1) > n * max_fre_mm**2
        if not known:
            p = (1 + np.searchsorted(share_null, scan.best(z)[0] * (1 + 1e-9), side="right")) / (len(share_null) + 1)
            return (p <= alpha) | refused
        (share, _, _), (coherent, _, _) = scan.best_both(z, prior_sigma_mm)
        p_share = (1 + np.searchsorted(share_null, share * (1 + 1e-9), side="right")) / (len(share_null) + 1)
        p_known = (1 + np.searchsorted(known_null, coherent * (1 + 1e-9), side="right")) / (len(known_null) + 1)
        observed = np.where(p_share <= support, np.minimum(p_share, p_known), p_share)
        p = (1 + np.searchsorted(combined_null, observed * (1 + 1e-9), side="right")) / (len(combined_null) + 1)
        return (p <= alpha) | refused

    low = np.zeros(POWER_DRAWS)
    high = np.full(POWER_DRAWS, 4.0 * max(noise_sigma_mm, 0.01))
    missed = ~found(high)
    for _ in range(POWER_WIDENINGS):  # widen until each draw is found, or the field dwarfs the noise
        if not missed.any():
            break
        high[missed] *= 2.0
        missed[missed] = ~found(high)[missed]
    for _ in range(POWER_STEPS):
        middle = 0.5 * (low + high)
        hit = found(middle)
        high, low = np.where(hit, middle, high), np.where(hit, low, middle)
    # a draw the test misses at every size (without a noise level the share test sees shape, not size) is never found
    return float(np.quantile(np.where(missed, np.inf, high), POWER_LEVEL, method="higher"))


def _combined_null(null: np.ndarray, support: float) -> np.ndarray:
    """The two tests' combined statistic over the null draws (draws, 2), sorted: per draw, the smaller of its share
    and known-noise p-values within the draws (the latter only where the former is at most ``support``)."""
    def p_values(column: np.ndarray) -> np.ndarray:
        return (1 + np.searchsorted(np.sort(column), column * (1 + 1e-9), side="right")) / (len(column) + 1)

    share, known = p_values(null[:, 0]), p_values(null[:, 1])
    return np.sort(np.where(share <= support, np.minimum(share, known), share))


def _combined_p_value(null: np.ndarray, p_share: float, p_known: float, support: float) -> float:
    """The p-value of the two tests together: the smaller of the share test's and the known-noise test's
    (the latter only where the former is at most ``support``), against the same statistic over the null draws
    (draws, 2) of both (exact for the pair, where twice the smaller, Bonferroni, would halve the power)."""
    draws = _combined_null(null, support)
    observed = min(p_share, p_known) if p_share <= support else p_share
    return float((1 + np.count_nonzero(draws <= observed * (1 + 1e-9))) / (len(draws) + 1))


def estimate_distortion(points_reference: np.ndarray, residuals_reference: np.ndarray,
                        axes_reference: np.ndarray | None, alpha: float, labels: Sequence[str] = (),
                        image_markers: Sequence[str] = (), tracker_to_reference: np.ndarray | None = None,
                        noise: NoisePrior | None = None, max_fre_mm: float = float("inf"),
                        unpaired_reference: np.ndarray | None = None,
                        fitted_count: int | None = None) -> DistortionEstimate:
    """Test the rigid fit's residuals for field distortion and fit it (see the module docstring).

    ``points_reference`` (N, 3): the paired calibration points (Reference, mm); ``residuals_reference``
    (N, 3): measured point minus the registered CT pinhole, in the Reference frame (mm);
    ``axes_reference`` (N, 3): the markers' axes in the Reference frame when l was solved (None: fixed);
    ``alpha``: the false-alarm rate (``[registration] distortion_false_alarm``);
    ``tracker_to_reference`` (N, 4, 4): the transmitter's pose at each point's dwells (None: unknown, no
    dipole candidates; the generic smooth fields and bumps still are); ``noise``: the probe's per-dwell error known
    apart from these residuals (None: the share test alone, and no FRE check); ``max_fre_mm``: the FRE above which
    the registration is refused (``[registration] max_fre_mm``: a field that large is caught, not missed, in
    :func:`detectable_rms`); ``unpaired_reference`` (K, 3): the calibration points the pairing left out (a
    neighbour of the largest residual among them means a field moved several pinholes, not one bad pair);
    ``fitted_count``: how many of the points (the first) are pairs the registration used (None: all); the others
    are unpaired points near a free CT pinhole, which join the test but not the field's fit or the noise.
    """
    estimate = _estimate(points_reference, residuals_reference, axes_reference, alpha, labels, image_markers,
                         tracker_to_reference, noise, max_fre_mm, unpaired_reference, fitted_count)
    if noise is None or not estimate.tested or not noise.sigma_mm > 0:
        return estimate
    return replace(estimate, noise_prior_sigma_mm=float(noise.sigma_mm), noise_prior_source=noise.source)


def _estimate(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
              alpha: float, labels: Sequence[str], image_markers: Sequence[str],
              tracker_to_reference: np.ndarray | None, noise: NoisePrior | None,
              max_fre_mm: float = float("inf"), unpaired_reference: np.ndarray | None = None,
              fitted_count: int | None = None) -> DistortionEstimate:
    """:func:`estimate_distortion` before the noise prior is recorded."""
    points, residuals, axes, poses = _arrays(points_reference, residuals_reference, axes_reference,
                                             tracker_to_reference)
    labels = list(labels) or [f"P{k + 1:02d}" for k in range(len(points))]
    image_markers = list(image_markers)
    n = len(points) if fitted_count is None else min(int(fitted_count), len(points))
    # the pairs: the field and the noise are measured on them; the points after them only add evidence to the test
    pair_points, pair_residuals = points[:n], residuals[:n]
    pair_axes, pair_poses = (None if axes is None else axes[:n]), (None if poses is None else poses[:n])
    joined = labels[n:]
    rms = float(np.sqrt(np.mean(pair_residuals**2))) if n else 0.0
    note = "" if poses is not None else ("the calibration does not say where the transmitter was (an older "
                                         "frame_calibration.json): no induced-dipole candidates, generic smooth "
                                         "fields only")
    untested = DistortionEstimate(labels[:n], pair_points, pair_residuals, 0.0, 1.0, alpha, rms, tested=False,
                                  image_markers=image_markers[:n], note="too few pinholes to test")
    if n < 4:
        return untested
    tested = _test(points, axes, poses, residuals, noise)
    if tested is None:
        return untested if not len(residuals) or np.any(residuals) else replace(untested, note="")
    scan, z, statistic, p_value, best, null = tested
    pair_test = tested if n == len(points) else _test(pair_points, pair_axes, pair_poses, pair_residuals, noise)
    prior = None if noise is None else noise.sigma_mm

    def finished(estimate: DistortionEstimate) -> DistortionEstimate:
        return replace(estimate, tested_unpaired=joined,
                       detectable_rms_mm=detectable_rms(scan, points, null, alpha, estimate.noise_sigma_mm, prior,
                                                        max_fre_mm=max_fre_mm))

    noise_scan, noise_z = (scan, z) if pair_test is None else pair_test[:2]
    noise_alone = (float(np.sqrt(noise_z @ noise_z / noise_scan.dof)), float(noise_scan.dof))
    if p_value > alpha:
        return finished(DistortionEstimate(labels[:n], pair_points, pair_residuals, statistic, p_value, alpha,
                                           *noise_alone, image_markers=image_markers[:n], note=note))
    largest = int(np.argmax(np.sum(residuals**2, axis=1)))
    keep = np.arange(len(points)) != largest
    p_without, share = float("nan"), float("nan")
    rest = _test(points[keep], None if axes is None else axes[keep], None if poses is None else poses[keep],
                 residuals[keep], noise, support=1.0) if len(points) > 4 else None
    if rest is not None:
        p_without = rest[3]
        share = _predicted_share(rest[0].candidates[rest[4]], points, poses, axes, residuals, largest)
    axial = 1.0 if axes is None else float((residuals[largest] @ axes[largest]) ** 2
                                           / max(residuals[largest] @ residuals[largest], 1e-300))
    if not _several_points(p_without, share, _outlier_p_value(scan, residuals), axial,
                           _unpaired_near(points, largest, unpaired_reference)):
        return finished(DistortionEstimate(labels[:n], pair_points, pair_residuals, statistic, p_value, alpha,
                                           *noise_alone, image_markers=image_markers[:n], note=note,
                                           p_value_without_largest=p_without, largest_predicted_share=share,
                                           left_out=labels[largest], one_bad_pair=True))
    if pair_test is None:  # too few pairs to fit a field on them alone: on every point tested
        return finished(_fitted(scan, z, best, points, residuals, axes, poses, labels, image_markers, statistic,
                                p_value, alpha, note, p_without, share, labels[largest]))
    return finished(_fitted(pair_test[0], pair_test[1], pair_test[4], pair_points, pair_residuals, pair_axes,
                            pair_poses, labels[:n], image_markers[:n], statistic, p_value, alpha, note, p_without,
                            share, labels[largest]))


def _fitted(scan: _Scan, z: np.ndarray, best: int, points: np.ndarray, residuals: np.ndarray,
            axes: np.ndarray | None, poses: np.ndarray | None, labels: list[str], image_markers: Sequence[str],
            statistic: float, p_value: float, alpha: float, note: str, p_without: float = float("nan"),
            share: float = float("nan"), left_out: str = "") -> DistortionEstimate:
    """The estimate with candidate ``best`` fitted by least squares (a dipole's position refined first)."""
    model = _refine(scan, scan.candidates[best], points, poses, z)
    at_pinholes = model.columns(points, poses, scan.seen)  # (N, 3, P)
    design = scan.basis.T @ _stack(at_pinholes)
    # no more directions than the scan tested the candidate with (its rank there): a candidate of more columns than
    # residual dimensions must not fit the noise away (a 60-column cubic polynomial spans all 41 of 28 pinholes)
    u, singular, vt = np.linalg.svd(design, full_matrices=False)
    rank = min(scan.rank_of(best), int(np.count_nonzero(singular > RANK_TOLERANCE * singular[0])))
    inverse = vt[:rank].T @ (u[:, :rank] / singular[:rank]).T
    amplitudes = inverse @ z
    remaining = z - design @ amplitudes
    dof = scan.dof - rank - (3 if isinstance(model, _Dipole) else 0)
    variance = float(remaining @ remaining) / max(dof, 1)
    covariance = variance * inverse @ inverse.T
    rigid = np.linalg.pinv(_rigid_jacobian(points, axes))[:6] @ _stack(at_pinholes)
    centroid = points.mean(axis=0)
    nonrigid = at_pinholes @ amplitudes - fiducial_jacobian(points, centroid) @ (rigid @ amplitudes)
    return DistortionEstimate(labels, points, residuals, statistic, p_value, alpha, float(np.sqrt(variance)),
                              float(max(dof, 1)), model, amplitudes, covariance, rigid, nonrigid,
                              image_markers=list(image_markers), note=note, p_value_without_largest=p_without,
                              largest_predicted_share=share, left_out=left_out,
                              **_leave_one_out(scan.basis, scan.basis @ u[:, :rank], remaining))


def _leave_one_out(basis: np.ndarray, field_basis: np.ndarray, remaining: np.ndarray) -> dict[str, float]:
    """The fitted field's leave-one-out errors at the pinholes, for :attr:`DistortionEstimate.extension_ms`: each
    pinhole's ``(I - H_ii)^-1`` times its residual beside the fit (``H``: the hat matrix of the rigid motion and the
    field together; ``basis`` (3N, m) the residual space, ``field_basis`` (3N, P) the field's columns there,
    orthonormal; ``remaining`` (m,) the residual beside the field in ``basis``). Returns their mean square
    (``loo_ms``, mm^2) and the mean of ``tr((I - H_ii)^-1)`` (``loo_noise_factor``): noise of variance s^2 per
    axis gives them ``s^2`` times that on average, exactly, for a field of the fitted family."""
    n = len(basis) // 3
    hat = np.eye(3 * n) - basis @ basis.T + field_basis @ field_basis.T
    blocks = np.stack([np.eye(3) - hat[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    left = (basis @ remaining).reshape(n, 3, 1)
    try:
        loo = np.linalg.solve(blocks, left)[..., 0]
        factor = np.trace(np.linalg.inv(blocks), axis1=-2, axis2=-1)
    except np.linalg.LinAlgError:
        return {"loo_ms": 0.0, "loo_noise_factor": 0.0}
    return {"loo_ms": float(np.mean(np.sum(loo**2, axis=1))), "loo_noise_factor": float(np.mean(factor))}


def fit_field(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
              tracker_to_reference: np.ndarray | None = None) -> DistortionEstimate | None:
    """The smooth field the test picks, fitted to the residuals whether significant or not (None: too few points):
    to ask whether it explains where points left out of the pairing lie (:meth:`DistortionEstimate.field_at`).
    Frames and units as :func:`estimate_distortion`."""
    points, residuals, axes, poses = _arrays(points_reference, residuals_reference, axes_reference,
                                             tracker_to_reference)
    projected = _projected(points, axes, poses, residuals) if len(points) >= 4 else None
    if projected is None:
        return None
    scan, z = projected
    best = _cross_validated(scan, points, poses, residuals)
    share = float(scan.best(z)[1])
    return _fitted(scan, z, best, points, residuals, axes, poses, [f"P{k + 1:02d}" for k in range(len(points))],
                   (), share, float("nan"), 0.0, "")


def _cross_validated(scan: _Scan, points: np.ndarray, poses: np.ndarray | None, residuals: np.ndarray) -> int:
    """The candidate that best predicts each pinhole's residual from the others (leave-one-out, closed form:
    ``(I - H_ii)^-1 e_i`` per pinhole, H the fit's hat matrix): the field to extend beyond the pinholes, where a
    candidate chosen by its fit alone may be the one with most columns."""
    r = residuals.reshape(-1)
    n = len(points)
    scores = []
    for candidate in scan.candidates:
        design = scan.basis @ (scan.basis.T @ _stack(candidate.columns(points, poses, scan.seen)))
        u, singular, _ = np.linalg.svd(design, full_matrices=False)
        u = u[:, singular > singular[0] * 1e-9] if singular[0] > 0 else u[:, :0]
        left = (r - u @ (u.T @ r)).reshape(n, 3)
        hat = np.einsum("iap,ibp->iab", u.reshape(n, 3, -1), u.reshape(n, 3, -1))
        try:
            loo = np.linalg.solve(np.eye(3) - hat, left[..., None])[..., 0]
        except np.linalg.LinAlgError:
            scores.append(np.inf)
            continue
        scores.append(float(np.sum(loo**2)))
    return int(np.argmin(scores))


def _several_points(p_without: float, share: float, p_outlier: float, axial: float = 1.0,
                    unpaired_near: bool = False) -> bool:
    """Whether the evidence is carried by more pinholes than the one of the largest residual (a bad pair is one
    point; a field moves several neighbours): not when that residual is an outlier by itself (its share of the sum
    of squares is beyond noise at :data:`OUTLIER_LEVEL`), the others alone are not significant at
    :data:`WITHOUT_LARGEST_LEVEL`, the field they pick predicts less than :data:`PREDICTED_SHARE` of its
    squared residual, no calibration point near it was left unpaired (``unpaired_near``: a neighbour moved out of
    pairing is a second point moved), and, when the marker axes are known, that residual lies along its pinhole's
    axis (``axial``: its share along it, at least :data:`AXIAL_SHARE`: a probe not fully inserted; a field moves a
    point any way). Untestable without it: counted as several."""
    if not np.isfinite(p_without):
        return True
    return (p_outlier > OUTLIER_LEVEL or p_without <= WITHOUT_LARGEST_LEVEL or share >= PREDICTED_SHARE
            or axial < AXIAL_SHARE or unpaired_near)


def _unpaired_near(points: np.ndarray, index: int, unpaired: np.ndarray | None) -> bool:
    """Whether a calibration point left unpaired (K, 3) lies within :data:`NEIGHBOUR_FRACTION` of the pinholes' RMS
    distance from their centroid of pinhole ``index`` (all Reference, mm)."""
    if unpaired is None or not len(unpaired):
        return False
    radius = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
    gaps = np.linalg.norm(np.asarray(unpaired, dtype=float).reshape(-1, 3) - points[index], axis=1)
    return bool(np.any(gaps < NEIGHBOUR_FRACTION * radius))


def _outlier_p_value(scan: _Scan, residuals: np.ndarray, draws: int = NULL_DRAWS, seed: int = 1) -> float:
    """The Monte Carlo p-value of the largest residual's share of the residual sum of squares under isotropic noise
    (the same geometry: the rigid fit shrinks some points' residuals more than others')."""
    def largest_share(r: np.ndarray) -> np.ndarray:
        squares = np.sum(r.reshape(r.shape[:-1] + (-1, 3)) ** 2, axis=-1)
        return squares.max(axis=-1) / squares.sum(axis=-1)

    null = largest_share(np.random.default_rng(seed).standard_normal((draws, scan.dof)) @ scan.basis.T)
    observed = float(largest_share(np.asarray(residuals, dtype=float).reshape(1, -1))[0])
    return float((1 + np.count_nonzero(null >= observed * (1 - 1e-9))) / (draws + 1))


def _predicted_share(model: Any, points: np.ndarray, poses: np.ndarray | None, axes: np.ndarray | None,
                     residuals: np.ndarray, left_out: int) -> float:
    """How much of pinhole ``left_out``'s squared residual ``model`` (the field the other pinholes' test picked),
    fitted to the other pinholes, predicts there (1 - |r - prediction|^2 / |r|^2; 0 or less: nothing)."""
    basis = _complement(_rigid_jacobian(points, axes))
    seen = None if poses is None else _Seen(points, poses)
    rows = np.ones(3 * len(points), dtype=bool)
    rows[3 * left_out:3 * left_out + 3] = False
    r = residuals.reshape(-1)
    design = basis @ (basis.T @ _stack(model.columns(points, poses, seen)))
    amplitudes, *_ = np.linalg.lstsq(design[rows], r[rows], rcond=None)
    target = residuals[left_out]
    return float(1.0 - np.sum((target - design[~rows] @ amplitudes) ** 2) / np.sum(target**2))
