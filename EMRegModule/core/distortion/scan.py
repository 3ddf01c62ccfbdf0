"""The distortion test: each candidate field's share of the residuals beyond the rigid fit, and its null.

The residual vector lives in the complement of the rigid fit's Jacobian (``Scan.basis``). Each candidate
(:mod:`.fields`) is projected there; its share of ``|z|^2`` becomes a tail probability (Beta for the share test, a
chi-square against a known noise), the smallest over the candidates is the statistic, and its distribution under
noise alone is drawn by Monte Carlo for the geometry (:func:`.null_statistics`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..error_model import fiducial_jacobian
from ..transforms import mean_rigid
from .fields import Bumps, Dipole, Modes, Polynomial, Seen, fibonacci_sphere

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
#: The known-noise test counts only when the share test's p-value is at most this (chosen on the development
#: fields: it keeps most of the known-noise test's gain, and a pivoting stylus's calibration, whose dwells do not show
#: its tip error, no longer looks distorted).
SHARE_SUPPORT = 0.2
#: Generic smooth candidates: polynomial degrees, Gaussian-process lengths (fractions of the pinholes' RMS distance
#: from their centroid) and numbers of their smoothest modes.
POLYNOMIAL_DEGREES = (1, 2, 3)
GP_LENGTH_FRACTIONS = (0.5, 1.0, 2.0)
GP_MODES = (4, 8)
#: The null distribution: "gaussian" (isotropic noise drawn) or "permutation" (the residual vectors shuffled).
NULL = "gaussian"


@dataclass(frozen=True)
class NoisePrior:
    """The probe's per-dwell localisation error known apart from the residuals tested: ``sigma_mm`` per axis (mm),
    and ``source``, where it comes from (words for ``registration.json`` and the report)."""

    sigma_mm: float
    source: str


def rigid_jacobian(points: np.ndarray, axes: np.ndarray | None) -> np.ndarray:
    """The stacked rigid-fit Jacobian (3N, P) at the pinholes (rotation about their centroid, translation, l)."""
    return fiducial_jacobian(points, points.mean(axis=0), axes).reshape(3 * len(points), -1)


def rigid_complement(jacobian: np.ndarray) -> np.ndarray:
    """An orthonormal basis (3N, m) of what the rigid fit leaves: residuals live there."""
    u, s, _ = np.linalg.svd(jacobian, full_matrices=True)
    return u[:, int(np.sum(s > s[0] * 1e-10)):]


def stack_columns(columns: np.ndarray) -> np.ndarray:
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
class Scan:
    """Candidate fields in the residual basis Q (3N, m): induced dipoles around the frame (with the transmitter's
    poses), single Gaussian bumps, and generic smooth fields (polynomials, a Gaussian process's smoothest modes)."""

    basis: np.ndarray
    groups: list
    seen: Seen | None = None

    @classmethod
    def of(cls, points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None) -> Scan:
        basis = rigid_complement(rigid_jacobian(points, axes))
        seen = None if poses is None else Seen(points, poses)
        kinds = [_bump_candidates(points)] + [[c] for c in _generic_candidates(points)]
        if seen is not None:
            kinds.insert(0, _dipole_candidates(seen, poses))
        groups = []
        for candidates in kinds:
            if not candidates:
                continue
            design = np.stack([basis.T @ stack_columns(c.columns(points, poses, seen)) for c in candidates])
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
        """The rank candidate ``index`` (of :attr:`.candidates`) was tested with."""
        for group in self.groups:
            if index < len(group.candidates):
                return int(group.ranks[index])
            index -= len(group.candidates)
        raise IndexError(index)

    def best(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For z (..., m): the smallest candidate p-value of the share test (:func:`._share_p_values`, no noise
        level), the share of |z|^2 that candidate explains, and its index in :attr:`.candidates` (each (...,))."""
        return self.best_both(z)[0]

    def best_both(self, z: np.ndarray, sigma_mm: float | None = None) -> list[tuple[np.ndarray, np.ndarray,
                                                                                     np.ndarray]]:
        """:meth:`.best` of the share test, and with ``sigma_mm`` (the noise per axis known) also of the known-noise
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


def pinhole_radius(points: np.ndarray) -> float:
    """The pinholes' RMS distance from their centroid (mm): the frame's size, which the candidates' widths and the
    neighbour and power rules scale with."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def _generic_candidates(points: np.ndarray) -> list:
    """Smooth fields of no physical family (Reference frame): polynomials of :data:`.POLYNOMIAL_DEGREES` and the
    :data:`.GP_MODES` smoothest modes of Gaussian processes :data:`.GP_LENGTH_FRACTIONS` of the frame's size long."""
    centroid = points.mean(axis=0)
    radius = max(pinhole_radius(points), 1.0)
    fields: list = [Polynomial(centroid, radius, degree) for degree in POLYNOMIAL_DEGREES]
    fields += [Modes.of(points, radius * fraction, modes) for fraction in GP_LENGTH_FRACTIONS for modes in GP_MODES
               if modes < len(points)]
    return fields


def _dipole_candidates(seen: Seen, poses: np.ndarray) -> list[Dipole]:
    """Objects around the pinholes (Tracker frame): :data:`.OBJECT_DIRECTIONS` x :data:`.OBJECT_GAPS_MM`."""
    points_tracker = seen.points_tracker
    centre = points_tracker.mean(axis=0)
    radius = float(np.max(np.linalg.norm(points_tracker - centre, axis=1)))
    mean = mean_rigid(poses)
    candidates = []
    for gap in OBJECT_GAPS_MM:
        for direction in fibonacci_sphere(OBJECT_DIRECTIONS):
            position = centre + direction * (radius + gap)
            if np.linalg.norm(position) >= MIN_TRANSMITTER_DISTANCE_MM:
                candidates.append(Dipole(position, mean))
    return candidates


def _bump_candidates(points: np.ndarray) -> list[Bumps]:
    """Single bumps at the pinholes and pushed out from them, of :data:`.LENGTH_FRACTIONS` widths."""
    centroid = points.mean(axis=0)
    radius = pinhole_radius(points)
    places = np.concatenate([points, centroid + OUTWARD * (points - centroid)])
    return [Bumps(place[None], np.array([max(radius * f, 1.0)])) for place in places for f in LENGTH_FRACTIONS]


def null_statistics(scan: Scan, draws: int = NULL_DRAWS, seed: int = 0,
                    residuals: np.ndarray | None = None, known_noise: bool = False) -> np.ndarray:
    """The test statistic (the smallest candidate p-value) under noise alone (draws,) for this geometry
    (deterministic: seeded). Without ``residuals``: isotropic Gaussian noise (exact for it, whatever its size);
    with ``residuals`` (N, 3): those vectors shuffled among the pinholes (a permutation null). ``known_noise``: the
    statistics of the share and of the known-noise tests of the same draws (draws, 2) (:meth:`.Scan.best_both`, the
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


def _p_value(scan: Scan, statistic: float, residuals: np.ndarray | None = None,
             null: np.ndarray | None = None) -> float:
    """The Monte Carlo p-value of a statistic (a smallest candidate p-value: small is significant) against
    ``null`` (draws,) or the share test's :func:`.null_statistics`."""
    if null is None:
        null = null_statistics(scan, residuals=None if NULL == "gaussian" else residuals)
    return float((1 + np.count_nonzero(null <= statistic * (1 + 1e-9))) / (len(null) + 1))


def project_residuals(points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None,
               residuals: np.ndarray) -> tuple[Scan, np.ndarray] | None:
    """The candidates' scan of these pinholes and the residuals projected beyond the rigid fit, ``z`` (None: too few
    degrees of freedom to test, or nothing left beyond the fit)."""
    scan = Scan.of(points, axes, poses)
    if not scan.groups or scan.dof < MIN_DOF + 3:
        return None
    z = scan.basis.T @ residuals.reshape(-1)
    return (scan, z) if np.any(z) else None


def as_arrays(points_reference: np.ndarray, residuals_reference: np.ndarray, axes_reference: np.ndarray | None,
            tracker_to_reference: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                              np.ndarray | None]:
    """The inputs of :func:`.estimate_distortion` / :func:`.fit_field` as float arrays: points and residuals (N, 3),
    axes (N, 3) or None, the transmitter's poses (N, 4, 4) or None."""
    points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
    residuals = np.asarray(residuals_reference, dtype=float).reshape(-1, 3)
    axes = None if axes_reference is None else np.asarray(axes_reference, dtype=float).reshape(-1, 3)
    poses = None if tracker_to_reference is None else np.asarray(tracker_to_reference, dtype=float).reshape(-1, 4, 4)
    return points, residuals, axes, poses


def scan_residuals(points: np.ndarray, axes: np.ndarray | None, poses: np.ndarray | None, residuals: np.ndarray,
          noise: NoisePrior | None = None, support: float = SHARE_SUPPORT
          ) -> tuple[Scan, np.ndarray, float, float, int, np.ndarray] | None:
    """The scan, z, statistic's share, p-value, best candidate and the null draws of residuals (None: too few to
    test). With a ``noise`` prior: the share test and the known-noise test both, the smaller p-value's own and its
    candidate (the known-noise one only when the share test's p-value is at most ``support``); the null draws are
    then (draws, 2), else (draws,)."""
    projected = project_residuals(points, axes, poses, residuals)
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


def joint_null(null: np.ndarray, support: float) -> np.ndarray:
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
    draws = joint_null(null, support)
    observed = min(p_share, p_known) if p_share <= support else p_share
    return float((1 + np.count_nonzero(draws <= observed * (1 + 1e-9))) / (len(draws) + 1))


def outlier_p_value(scan: Scan, residuals: np.ndarray, draws: int = NULL_DRAWS, seed: int = 1) -> float:
    """The Monte Carlo p-value of the largest residual's share of the residual sum of squares under isotropic noise
    (the same geometry: the rigid fit shrinks some points' residuals more than others')."""
    def largest_share(r: np.ndarray) -> np.ndarray:
        squares = np.sum(r.reshape(r.shape[:-1] + (-1, 3)) ** 2, axis=-1)
        return squares.max(axis=-1) / squares.sum(axis=-1)

    null = largest_share(np.random.default_rng(seed).standard_normal((draws, scan.dof)) @ scan.basis.T)
    observed = float(largest_share(np.asarray(residuals, dtype=float).reshape(1, -1))[0])
    return float((1 + np.count_nonzero(null >= observed * (1 - 1e-9))) / (draws + 1))
