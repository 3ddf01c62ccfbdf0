"""Automatic pairing of image markers with calibration points (paper section 2.5).

The two sets come unordered, with missing and extra points on either side (calibrated
markers absent from the CT, CT markers never calibrated, decoys the detector kept, a pause
of the probe mistaken for a dwell). Each image marker is a segment of possible pinhole
points ``origin + l * axis`` (the sensor offset l in [a, b] is unknown until registration);
each calibration point is a pinhole point with its direction, in the Reference frame.

The paper treats pairing as a constraint-satisfaction problem over the distance graph. Here:

- **Constraints.** Two calibration points (i, k) may pair with two image markers (j, m) only
  if their distance lies in the interval the image distance |q_j(l) - q_m(l)| spans over
  l in [a, b], widened by the localisation tolerance, and the angle between their directions
  matches the angle between the marker axes (both invariant under the rigid motion).
- **Search.** Seed triangles of calibration points (ranked by how many of their distances the
  image can explain, large well-shaped triangles first) are matched to every image triangle
  satisfying the three edge constraints. Each match fixes a rigid transform (l chosen on a
  grid); all calibration points are mapped through it and checked against the image segments.
  The best candidates are refined (mutual nearest neighbours, l and the rigid fit re-solved,
  tolerance tightened) until the assignment stops changing.
- **Safety.** Every distinct refined pairing is kept. When a rival pairing that contradicts
  the best one explains nearly as many points (fewer than ``ambiguity_margin`` points less),
  the layout does not identify the pairing and :class:`NoSafeAnswerError` is raised. Fewer
  than ``min_pairs`` pairs is refused the same way.

Tolerances follow from the expected localisation errors (RMS, 3D): the tracker's for a
calibration point, the image's for a marker, and the angular error of the directions.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from ..settings import PairingSettings
from .sensor_offset import fre_curve

if TYPE_CHECKING:  # scipy.spatial is imported where the tree is built: readers of registration.json skip its 0.1 s
    from scipy.spatial import cKDTree


@dataclass
class PairingResult:
    """The pairing and the coarse registration that proved it.

    ``pairs``: (image_index, calibration_index) sorted by calibration index;
    ``reference_to_image`` (4x4) and ``l_mm``: the refined transform and offset of the best
    pairing; ``residuals_mm`` per pair; ``rival_support``: pairs explained by the best rival
    pairing (0 when none); ``hypotheses``: transforms tried; ``seeds``: seed triangles used.
    """

    pairs: list[tuple[int, int]]
    reference_to_image: np.ndarray
    l_mm: float
    residuals_mm: np.ndarray
    rival_support: int = 0
    rival_fre_mm: float = float("nan")
    hypotheses: int = 0
    seeds: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def support(self) -> int:
        return len(self.pairs)


@dataclass
class _Candidate:
    assignment: dict[int, int]  # calibration index -> image index
    reference_to_image: np.ndarray
    l_mm: float
    residuals: np.ndarray  # per pair, in calibration-index order of `assignment`
    cost: float

    @property
    def support(self) -> int:
        return len(self.assignment)

    @property
    def key(self) -> frozenset[tuple[int, int]]:
        return frozenset(self.assignment.items())

    @property
    def fre(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2))) if len(self.residuals) else float("nan")

    def conflicts_with(self, other: _Candidate) -> bool:
        """True when the two pairings disagree on some point (not merely one being a subset)."""
        inverse = {j: i for i, j in other.assignment.items()}
        for i, j in self.assignment.items():
            if i in other.assignment and other.assignment[i] != j:
                return True
            if j in inverse and inverse[j] != i:
                return True
        return False


def pair_markers(
    origins_image: np.ndarray,
    axes_image: np.ndarray,
    points_reference: np.ndarray,
    directions_reference: np.ndarray | None,
    l_range_mm: tuple[float, float],
    settings: PairingSettings | None = None,
    unsigned_directions: bool = False,
) -> PairingResult:
    """Pair image markers (origins (M, 3) and unit +Y axes (M, 3), image space, mm) with
    calibration points (pinhole sensor points (N, 3) and unit directions (N, 3) or NaN, in
    the Reference frame) for a sensor offset l in ``l_range_mm`` = (a, b).

    ``unsigned_directions``: the directions are known only up to one common sign (the probe's
    axis convention is not known): a mapped direction may lie along the marker axis or
    against it. The pairwise angle constraints are unchanged (invariant under a common sign).

    Raises :class:`NoSafeAnswerError` when fewer than ``min_pairs`` pairs are found or when
    two different pairings explain the data about equally well (symmetric layout).
    """
    settings = settings or PairingSettings()
    problem = _Problem(origins_image, axes_image, points_reference, directions_reference, l_range_mm, settings)
    problem.unsigned = bool(unsigned_directions)
    return problem.solve()


# --- the search -----------------------------------------------------------------------------


class _Problem:
    def __init__(self, origins, axes, points, directions, l_range, settings: PairingSettings) -> None:
        self.origins = np.asarray(origins, dtype=float).reshape(-1, 3)
        axes = np.asarray(axes, dtype=float).reshape(-1, 3)
        self.axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        self.points = np.asarray(points, dtype=float).reshape(-1, 3)
        if directions is None:
            directions = np.full_like(self.points, np.nan)
        directions = np.asarray(directions, dtype=float).reshape(-1, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        self.a, self.b = float(l_range[0]), float(l_range[1])
        if not self.a <= self.b:
            raise EMRegError(f"pairing: sensor offset range [{self.a}, {self.b}] is empty")
        self.settings = settings
        self.n_image = len(self.origins)
        self.n_cal = len(self.points)
        self.tol_d = settings.distance_tolerance_mm
        self.tol_point = settings.point_tolerance_mm
        self.tol_loose = 2.0 * self.tol_point + 1.0
        self.tol_angle = settings.angle_tolerance_deg
        self.cos_loose = np.cos(np.radians(min(2.0 * self.tol_angle, 60.0)))
        self.cos_tight = np.cos(np.radians(min(self.tol_angle, 45.0)))
        self.l_grid = np.linspace(self.a, self.b, max(2, int(np.ceil((self.b - self.a) / 0.5)) + 1))
        self.hypotheses = 0
        self.unsigned = False  # directions known up to a common sign: compare |cos|
        self._tree: cKDTree | None = None

    # --- invariants ----------------------------------------------------------------------

    def _tables(self) -> None:
        p = self.points
        self.d_cal = np.linalg.norm(p[:, None] - p[None], axis=2)
        w = self.origins[None, :] - self.origins[:, None]  # (M, M, 3): o_m - o_j
        v = self.axes[None, :] - self.axes[:, None]
        def dist(l_value):
            return np.linalg.norm(w + l_value[..., None] * v, axis=2)
        vv = np.sum(v * v, axis=2)
        with np.errstate(invalid="ignore", divide="ignore"):
            l_star = np.where(vv > 1e-12, -np.sum(w * v, axis=2) / vv, self.a)
        l_star = np.clip(l_star, self.a, self.b)
        at_a, at_b, at_star = dist(np.full(vv.shape, self.a)), dist(np.full(vv.shape, self.b)), dist(l_star)
        self.d_img_lo = np.minimum(np.minimum(at_a, at_b), at_star) - self.tol_d
        self.d_img_hi = np.maximum(at_a, at_b) + self.tol_d
        np.fill_diagonal(self.d_img_lo, np.inf)
        np.fill_diagonal(self.d_img_hi, -np.inf)
        self.angle_cal = _angles(self.directions)
        self.angle_img = _angles(self.axes)

    def _compatible(self, i: int, k: int) -> np.ndarray:
        """(M, M) mask: image pairs (j, m) that calibration pair (i, k) may map onto."""
        d = self.d_cal[i, k]
        ok = (self.d_img_lo <= d) & (d <= self.d_img_hi)
        angle = self.angle_cal[i, k]
        if np.isfinite(angle):
            ok &= np.abs(self.angle_img - angle) <= self.tol_angle
        return ok

    def _unary_scores(self) -> np.ndarray:
        """Per calibration point: the largest fraction of its distances some image marker explains."""
        n, m = self.n_cal, self.n_image
        best = np.zeros(n)
        off_diagonal = ~np.eye(n, dtype=bool)
        for j in range(m):
            lo = np.delete(self.d_img_lo[j], j)
            hi = np.delete(self.d_img_hi[j], j)
            order = np.argsort(lo)
            lo, hi_max = lo[order], np.maximum.accumulate(hi[order])
            idx = np.searchsorted(lo, self.d_cal, side="right") - 1
            inside = (idx >= 0) & (hi_max[np.clip(idx, 0, None)] >= self.d_cal) & off_diagonal
            best = np.maximum(best, inside.sum(axis=1))
        return best / max(1, n - 1)

    # --- seeds ---------------------------------------------------------------------------

    def _seed_triangles(self, scores: np.ndarray):
        """Calibration triangles to start from: drawn from the best-explained points in growing
        tiers (8, 14, 22, 30 points), best scores then largest smallest-height first."""
        order = np.argsort(-scores, kind="stable")
        used: set[tuple[int, int, int]] = set()
        for top in (8, 14, 22, 30):
            pool = sorted(order[:min(top, self.n_cal)].tolist())
            triangles = np.array([t for t in itertools.combinations(pool, 3) if t not in used], dtype=int)
            if len(triangles):
                used.update(map(tuple, triangles.tolist()))
                heights = _triangle_heights(self.points[triangles])
                keep = heights >= 10.0
                triangles, heights = triangles[keep], heights[keep]
                score = np.round(scores[triangles].sum(axis=1), 1)
                for k in np.lexsort((-heights, -score)):
                    yield tuple(triangles[k].tolist())
            if top >= self.n_cal:
                return

    def _image_triangles(self, tri: tuple[int, int, int]) -> np.ndarray:
        i, k, n = tri
        jm = np.argwhere(self._compatible(i, k))
        if len(jm) == 0:
            return np.zeros((0, 3), dtype=int)
        ok = self._compatible(i, n)[jm[:, 0]] & self._compatible(k, n)[jm[:, 1]]
        rows, o = np.nonzero(ok)
        triples = np.column_stack([jm[rows], o])
        distinct = (triples[:, 2] != triples[:, 0]) & (triples[:, 2] != triples[:, 1])
        return triples[distinct]

    # --- hypotheses ----------------------------------------------------------------------

    def _triangle_transforms(self, tri, triples: np.ndarray) -> np.ndarray:
        """ReferenceToImage (T, 4, 4) per image triangle, l chosen on the grid by fit residual (FRE(l))."""
        curve = fre_curve(self.l_grid, self.points[list(tri)], self.origins[triples], self.axes[triples])
        best = np.argmin(curve.sse_mm2, axis=1)
        return curve.reference_to_image[np.arange(len(triples)), best]

    def _segment_distances(self, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (T, N, M) of mapped calibration points from the image pinhole segments,
        and cosines (T, N, M) between mapped directions and marker axes (1 where unknown).

        Written with matrix products only: with rel = x - o_j and s = clip(rel . u_j, a, b),
        |rel - s u_j|^2 = |rel|^2 - 2 s (rel . u_j) + s^2.
        """
        mapped = np.einsum("tij,nj->tni", transforms[:, :3, :3], self.points) + transforms[:, None, :3, 3]
        origin_dot_axis = np.sum(self.origins * self.axes, axis=1)
        along = mapped @ self.axes.T - origin_dot_axis  # (T, N, M): rel . u_j
        rel2 = (np.sum(mapped**2, axis=2)[..., None] - 2.0 * (mapped @ self.origins.T)
                + np.sum(self.origins**2, axis=1))
        clipped = np.clip(along, self.a, self.b)
        distance = np.sqrt(np.maximum(rel2 - 2.0 * clipped * along + clipped**2, 0.0))
        directions = np.einsum("tij,nj->tni", transforms[:, :3, :3], self.directions)
        cos = directions @ self.axes.T
        if self.unsigned:
            cos = np.abs(cos)
        return distance, np.where(np.isnan(cos), 1.0, cos)

    def _loose_assignments(self, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per hypothesis: nearest image marker of each calibration point within the loose
        tolerance of its pinhole segment (-1 if none), and the count of such points.

        A k-d tree over the segments' midpoints proposes the few markers that can be that
        close (segment distance >= midpoint distance - half the segment's length)."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.origins + 0.5 * (self.a + self.b) * self.axes)
        k = min(3, self.n_image)
        mapped = np.einsum("tij,nj->tni", transforms[:, :3, :3], self.points) + transforms[:, None, :3, 3]
        directions = np.einsum("tij,nj->tni", transforms[:, :3, :3], self.directions)
        flat = mapped.reshape(-1, 3)
        _, index = self._tree.query(flat, k=k, distance_upper_bound=self.tol_loose + 0.5 * (self.b - self.a))
        index = index.reshape(len(flat), k)
        found = index < self.n_image
        safe = np.where(found, index, 0)
        rel = flat[:, None, :] - self.origins[safe]
        along = np.clip(np.sum(rel * self.axes[safe], axis=2), self.a, self.b)
        distance = np.linalg.norm(rel - along[..., None] * self.axes[safe], axis=2)
        cos = np.sum(directions.reshape(-1, 1, 3) * self.axes[safe], axis=2)
        if self.unsigned:
            cos = np.abs(cos)
        ok = found & (distance <= self.tol_loose) & ((cos >= self.cos_loose) | np.isnan(cos))
        distance = np.where(ok, distance, np.inf)
        best = np.argmin(distance, axis=1)
        rows = np.arange(len(flat))
        assignment = np.where(ok[rows, best], safe[rows, best], -1).reshape(len(transforms), self.n_cal)
        return assignment, np.sum(assignment >= 0, axis=1)

    def _refine(self, reference_to_image: np.ndarray) -> _Candidate | None:
        """Iterate assignment (mutual nearest) and the fit with l, from loose to tight tolerance."""
        transform = reference_to_image
        l_value: float | None = None
        previous: frozenset | None = None
        for iteration in range(8):
            if l_value is None:
                distance, cos = self._segment_distances(transform[None])
                distance, cos = distance[0], cos[0]
                tolerance, min_cos = self.tol_loose, self.cos_loose
            else:
                mapped = self.points @ transform[:3, :3].T + transform[:3, 3]
                pinholes = self.origins + l_value * self.axes
                distance = np.linalg.norm(mapped[:, None] - pinholes[None], axis=2)
                cos = (self.directions @ transform[:3, :3].T) @ self.axes.T
                cos = np.where(np.isnan(cos), 1.0, np.abs(cos) if self.unsigned else cos)
                tolerance = self.tol_point if iteration >= 3 else max(self.tol_point, self.tol_loose / 2)
                min_cos = self.cos_tight
            assignment = _mutual_nearest(np.where(cos >= min_cos, distance, np.inf), tolerance)
            if len(assignment) < 3:
                return None
            key = frozenset(assignment.items())
            cal = np.fromiter(assignment.keys(), dtype=int)
            img = np.fromiter(assignment.values(), dtype=int)
            transform, l_value, residuals = _fit_with_offset(
                self.points[cal], self.origins[img], self.axes[img], self.l_grid)
            if key == previous and iteration >= 3:
                break
            previous = key
        keep = residuals <= self.tol_point
        if not np.all(keep):
            if np.count_nonzero(keep) < 3:
                return None
            assignment = {int(i): int(j) for i, j, k in zip(cal, img, keep, strict=True) if k}
            cal, img = cal[keep], img[keep]
            transform, l_value, residuals = _fit_with_offset(
                self.points[cal], self.origins[img], self.axes[img], self.l_grid)
        sigma2 = (self.settings.point_sigma_mm**2) / 3.0
        cap = self.settings.n_sigma**2
        cost = float(np.sum(np.minimum(residuals**2 / sigma2, cap)) + cap * (self.n_cal - len(residuals)))
        return _Candidate(assignment, transform, l_value, residuals, cost)

    # --- driver --------------------------------------------------------------------------

    def _try_seed(self, tri: tuple[int, int, int], floor: int, candidates: dict, tried: set,
                  exclude: tuple[int, int, int] | None = None) -> int:
        """Enumerate the image triangles a seed may map onto, verify them in one batch, refine
        those explaining at least ``floor`` points; returns the best loose count seen."""
        triples = self._image_triangles(tri)
        if exclude is not None and len(triples):
            triples = triples[~np.all(triples == np.asarray(exclude), axis=1)]
        if len(triples) == 0:
            return 0
        transforms = self._triangle_transforms(tri, triples)
        self.hypotheses += len(transforms)
        loose, count = self._loose_assignments(transforms)
        for h in np.argsort(-count, kind="stable"):
            if count[h] < floor:
                break
            signature = tuple(loose[h].tolist())
            if signature in tried:
                continue
            tried.add(signature)
            candidate = self._refine(transforms[h])
            if candidate is not None:
                candidates.setdefault(candidate.key, candidate)
        return int(count.max())

    def _moves(self, best: _Candidate, other: _Candidate) -> bool:
        """True when the other pairing's transform puts some of the best pairing's calibration
        points somewhere else (beyond the point tolerance): a different registration, not the
        same one with a near-duplicate point swapped in."""
        points = self.points[sorted(best.assignment)]
        a, b = best.reference_to_image, other.reference_to_image
        shift = (points @ a[:3, :3].T + a[:3, 3]) - (points @ b[:3, :3].T + b[:3, 3])
        return bool(np.max(np.linalg.norm(shift, axis=1)) > self.tol_point)

    def _rival_seeds(self, best: _Candidate, count: int):
        """Random well-shaped triangles of paired calibration points (with their image triangle
        under the best pairing, to exclude): a rival pairing that explains nearly as many points
        contains some of them, so trying each finds it."""
        paired = np.array(sorted(best.assignment))
        if len(paired) < 3:
            return
        rng = np.random.default_rng(len(paired))
        drawn = np.sort(paired[np.argsort(rng.random((20 * count, len(paired))), axis=1)[:, :3]], axis=1)
        drawn = drawn[_triangle_heights(self.points[drawn]) >= 10.0]
        _, first = np.unique(drawn, axis=0, return_index=True)
        for k in np.sort(first)[:count]:
            tri = tuple(drawn[k].tolist())
            yield tri, tuple(best.assignment[i] for i in tri)

    def solve(self) -> PairingResult:
        s = self.settings
        if min(self.n_cal, self.n_image) < s.min_pairs:
            raise NoSafeAnswerError(
                f"pairing needs at least {s.min_pairs} markers on each side, got {self.n_image} image markers "
                f"and {self.n_cal} calibration points"
            )
        self._tables()
        scores = self._unary_scores()
        candidates: dict[frozenset, _Candidate] = {}
        tried: set[tuple[int, ...]] = set()
        confirming = seeds = best_loose = 0
        best: _Candidate | None = None
        # 1. Find the pairing that explains the most points.
        for tri in self._seed_triangles(scores):
            seeds += 1
            floor = max(s.min_pairs, best_loose - s.ambiguity_margin - 3)
            best_loose = max(best_loose, self._try_seed(tri, floor, candidates, tried))
            previous = best
            best = _best(candidates.values())
            if best is not previous:
                confirming = 0
            if best is not None and all(i in best.assignment for i in tri):
                confirming += 1
            if (best is not None and best.support >= s.min_pairs and confirming >= 2) or seeds >= s.max_seeds:
                break
        if best is None or best.support < s.min_pairs:
            found = 0 if best is None else best.support
            raise NoSafeAnswerError(
                f"pairing: only {found} image markers could be paired consistently with calibration points "
                f"(at least {s.min_pairs} needed); check that the CT and the calibration show the same frame "
                "and the marker model"
            )
        # 2. Look for a rival pairing that contradicts it and explains nearly as many points.
        for _ in range(2):
            floor = max(s.min_pairs, best.support - s.ambiguity_margin - 2)
            for tri, image_tri in self._rival_seeds(best, s.rival_seeds):
                seeds += 1
                self._try_seed(tri, floor, candidates, tried, exclude=image_tri)
            new_best = _best(candidates.values())
            if new_best is best:
                break
            best = new_best
        rivals = [c for c in candidates.values() if c.conflicts_with(best) and self._moves(best, c)]
        rival = _best(rivals)
        if rival is not None and best.support - rival.support < s.ambiguity_margin:
            raise NoSafeAnswerError(
                f"ambiguous pairing: two different pairings explain {best.support} and {rival.support} markers "
                f"(FRE {best.fre:.2f} and {rival.fre:.2f} mm); the marker layout is (nearly) symmetric, "
                "so the calibration points cannot be told apart by their distances; "
                "make the layout asymmetric or label the calibration dwells"
            )
        order = sorted(best.assignment)
        return PairingResult(
            pairs=[(best.assignment[i], i) for i in order],
            reference_to_image=best.reference_to_image, l_mm=best.l_mm,
            residuals_mm=np.asarray(best.residuals),
            rival_support=0 if rival is None else rival.support,
            rival_fre_mm=float("nan") if rival is None else rival.fre,
            hypotheses=self.hypotheses, seeds=seeds,
        )


def _best(candidates) -> _Candidate | None:
    """The candidate explaining most points (then the lowest truncated cost)."""
    return max(candidates, key=lambda c: (c.support, -c.cost), default=None)


# --- small numerical helpers ------------------------------------------------------------------


def _angles(unit: np.ndarray) -> np.ndarray:
    """Pairwise angles (deg) between unit vectors (NaN where a vector is unknown)."""
    cos = np.clip(unit @ unit.T, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def _triangle_heights(triangles: np.ndarray) -> np.ndarray:
    """Smallest height (mm) of each triangle (T, 3, 3): small for thin or tiny triangles."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                               np.linalg.norm(a - c, axis=1)]), axis=0)
    return np.divide(twice_area, longest, out=np.zeros_like(longest), where=longest > 0)


def _fit_with_offset(points: np.ndarray, origins: np.ndarray, axes: np.ndarray,
                     l_grid: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Rigid fit of points onto ``origins + l * axes`` with l minimising FRE(l) on the grid, then
    refined by a parabola through the grid minimum. Returns (transform, l, residuals)."""
    sse = fre_curve(l_grid, points, origins, axes).sse_mm2
    k = int(np.argmin(sse))
    l_best = float(l_grid[k])
    if 0 < k < len(l_grid) - 1:
        y0, y1, y2 = sse[k - 1], sse[k], sse[k + 1]
        denominator = y0 - 2 * y1 + y2
        if denominator > 1e-12:
            step = l_grid[k + 1] - l_grid[k]
            l_best = float(np.clip(l_grid[k] + 0.5 * step * (y0 - y2) / denominator, l_grid[k - 1], l_grid[k + 1]))
    at_best = fre_curve([l_best], points, origins, axes)
    return at_best.reference_to_image[0], l_best, at_best.residuals_mm[0]


def _mutual_nearest(distance: np.ndarray, tolerance: float) -> dict[int, int]:
    """Pairs (row -> column) that are each other's nearest and closer than ``tolerance``."""
    if distance.size == 0:
        return {}
    row_best = np.argmin(distance, axis=1)
    col_best = np.argmin(distance, axis=0)
    rows = np.arange(distance.shape[0])
    ok = (col_best[row_best] == rows) & (distance[rows, row_best] <= tolerance)
    return {int(i): int(row_best[i]) for i in rows[ok]}
