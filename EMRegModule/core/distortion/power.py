"""What a clean result covers: the smallest field the distortion test finds, at a session's noise and pinholes."""

from __future__ import annotations

import numpy as np

from .fields import gaussian_kernel
from .scan import SHARE_SUPPORT, Scan, joint_null, pinhole_radius

#: The detectable size: the non-rigid RMS at the pinholes the test finds in this share of random smooth fields
#: (:func:`.detectable_rms`), drawn (:data:`.POWER_DRAWS` of them, Gaussian processes of :data:`.POWER_LENGTH_FRACTIONS`
#: of the pinholes' RMS distance from their centroid) with this session's noise and geometry.
POWER_LEVEL = 0.9
POWER_DRAWS = 300
POWER_LENGTH_FRACTIONS = (0.5, 1.0, 2.0)
#: Bisection steps of each draw's smallest detected size (the size resolved to 2^-steps of its bracket).
POWER_STEPS = 10
#: Doublings of a draw's size, from 4 x the noise, before it counts as never found (2^10: a field 4000 x the noise).
POWER_WIDENINGS = 10


def detectable_rms(scan: Scan, points: np.ndarray, null: np.ndarray, alpha: float, noise_sigma_mm: float,
                   prior_sigma_mm: float | None = None, support: float = SHARE_SUPPORT,
                   max_fre_mm: float = float("inf")) -> float:
    """The smallest non-rigid field (RMS at the pinholes, mm) the test finds in :data:`.POWER_LEVEL` of random smooth
    fields with this session's pinholes ``points`` (N, 3, Reference) and noise (``noise_sigma_mm`` per axis; the
    test's own known noise ``prior_sigma_mm``, None: the share test alone, ``null`` then (draws,) else (draws, 2)). A
    field whose residuals' RMS exceeds ``max_fre_mm`` counts as caught: the registration refuses such an FRE.

    No family is assumed: the fields are Gaussian processes of several lengths (:data:`.POWER_LENGTH_FRACTIONS`),
    their non-rigid part scaled to each size, drawn with noise of the session's size (deterministic seed). Each
    draw's smallest detected size is found by bisection on the same draw (the test's verdict grows with the size),
    and the :data:`.POWER_LEVEL` quantile of those is the answer. The one-bad-pair check is left out: it overrules
    single points, not smooth fields. The answer is the size of field this session could miss: a registration
    that found nothing says nothing about fields smaller than it. Infinite when more than 1 - :data:`.POWER_LEVEL` of
    the fields are missed at every size (the share test alone judges a field's shape, not its size: one that no
    candidate follows is never found, however large)."""
    rng = np.random.default_rng(7)
    n = len(points)
    radius = max(pinhole_radius(points), 1.0)
    factors = [np.linalg.cholesky(gaussian_kernel(points, points, radius * fraction) + 1e-9 * np.eye(n))
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
        combined_null = joint_null(null, support)

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
