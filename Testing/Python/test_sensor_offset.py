"""FRE(l) (paper Eq. 10) and the batched rigid fit, checked against an independent oracle.

The oracle is scipy's ``Rotation.align_vectors`` (Kabsch through a quaternion eigenproblem, not
an SVD) applied to the centred points, and a brute-force scan over l written here: nothing of
EMReg's fitting code is used to compute the expected values.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from synth_registration import pairing_problem

from EMRegModule.core.calibration import CalibrationPoint, FrameCalibration
from EMRegModule.core.registration import register
from EMRegModule.core.sensor_offset import fre_curve, solve_sensor_offset
from EMRegModule.core.transforms import fit_rigid, fit_rigid_batch, make_transform, random_rotation
from EMRegModule.marker_model import MarkerModel

L_RANGE = (11.0, 18.5)


def _oracle_fit(points_a: np.ndarray, points_b: np.ndarray, weights: np.ndarray | None = None):
    """Rotation and translation of the least-squares rigid fit A -> B from scipy (independent code)."""
    w = np.ones(len(points_a)) if weights is None else np.asarray(weights, dtype=float)
    centroid_a = w @ points_a / w.sum()
    centroid_b = w @ points_b / w.sum()
    rotation, _ = Rotation.align_vectors(points_b - centroid_b, points_a - centroid_a, weights=w)
    matrix = rotation.as_matrix()
    return matrix, centroid_b - matrix @ centroid_a


def _oracle_fre(l_mm: float, points, origins, axes) -> float:
    """FRE(l) of Eq. 10 by the oracle fit: RMS distance after fitting points onto origins + l * axes."""
    pinholes = origins + l_mm * axes
    rotation, translation = _oracle_fit(points, pinholes)
    return float(np.sqrt(np.mean(np.sum((points @ rotation.T + translation - pinholes) ** 2, axis=1))))


def _brute_force_minimum(points, origins, axes) -> tuple[float, float]:
    """(l, FRE) at the oracle's minimum over the pinhole range: 10 micrometre steps, then 0.5 micrometre
    steps around the best one."""
    coarse = np.linspace(*L_RANGE, 751)
    k = int(np.argmin([_oracle_fre(v, points, origins, axes) for v in coarse]))
    fine = np.linspace(coarse[max(k - 1, 0)], coarse[min(k + 1, len(coarse) - 1)], 41)
    values = np.array([_oracle_fre(v, points, origins, axes) for v in fine])
    return float(fine[np.argmin(values)]), float(values.min())


def _problem(seed: int, n: int = 12, noise_mm: float = 0.4, l_true: float = 14.3):
    """Markers with spread axes, calibration points at ``origin + l_true * axis`` moved into a
    Reference frame, with noise: FRE(l) has a clear minimum near ``l_true``."""
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-120, 120, (n, 3))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    image_to_reference = make_transform(random_rotation(rng), rng.uniform(-300, 300, 3))
    pinholes = origins + l_true * axes + rng.normal(0, noise_mm / np.sqrt(3), (n, 3))
    points = pinholes @ image_to_reference[:3, :3].T + image_to_reference[:3, 3]
    return points, origins, axes


@pytest.mark.parametrize("seed", range(4))
def test_fit_rigid_batch_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    points_a = rng.normal(size=(5, 7, 3)) * 60
    truth = [make_transform(random_rotation(rng), rng.uniform(-200, 200, 3)) for _ in range(5)]
    points_b = np.stack([p @ t[:3, :3].T + t[:3, 3] for p, t in zip(points_a, truth, strict=True)])
    points_b += rng.normal(0, 0.5, points_b.shape)
    weights = rng.uniform(0.1, 2.0, (5, 7))
    for w in (None, weights):
        rotation, translation = fit_rigid_batch(points_a, points_b, w)
        assert rotation.shape == (5, 3, 3) and translation.shape == (5, 3)
        for k in range(5):
            expected_rotation, expected_translation = _oracle_fit(points_a[k], points_b[k],
                                                                  None if w is None else w[k])
            np.testing.assert_allclose(rotation[k], expected_rotation, atol=1e-9)
            np.testing.assert_allclose(translation[k], expected_translation, atol=1e-7)
            single = fit_rigid(points_a[k], points_b[k], None if w is None else w[k])
            np.testing.assert_allclose(single, make_transform(rotation[k], translation[k]), atol=1e-9)


def test_fit_rigid_batch_never_returns_a_reflection():
    points = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0], [3, 4, 5]])
    rotation, _ = fit_rigid_batch(np.stack([points, points]), np.stack([points * [1, 1, -1], points]))
    np.testing.assert_allclose(np.linalg.det(rotation), [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(rotation[1], np.eye(3), atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_fre_curve_matches_a_brute_force_oracle(seed):
    points, origins, axes = _problem(seed)
    l_values = np.linspace(*L_RANGE, 31)
    curve = fre_curve(l_values, points, origins, axes)
    expected = np.array([_oracle_fre(v, points, origins, axes) for v in l_values])
    np.testing.assert_allclose(curve.fre_mm, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(curve.sse_mm2, len(points) * expected**2, rtol=1e-9)
    # the stored fits reproduce the stored residuals
    for k in (0, 15, 30):
        pinholes = origins + l_values[k] * axes
        mapped = points @ curve.rotation[k].T + curve.translation[k]
        np.testing.assert_allclose(curve.residuals_mm[k], np.linalg.norm(mapped - pinholes, axis=1), atol=1e-9)


def test_fre_curve_is_batched_over_point_sets():
    sets = [_problem(seed, n=6) for seed in range(4)]
    points = np.stack([s[0] for s in sets])
    origins = np.stack([s[1] for s in sets])
    axes = np.stack([s[2] for s in sets])
    l_values = np.array([11.0, 14.0, 17.5])
    batched = fre_curve(l_values, points, origins, axes)
    assert batched.fre_mm.shape == (4, 3) and batched.reference_to_image.shape == (4, 3, 4, 4)
    for k, (p, o, a) in enumerate(sets):
        np.testing.assert_allclose(batched.fre_mm[k], [_oracle_fre(v, p, o, a) for v in l_values], atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_solved_offset_is_the_brute_force_minimum(seed):
    points, origins, axes = _problem(seed + 10)
    l_brute, fre_brute = _brute_force_minimum(points, origins, axes)
    solution = solve_sensor_offset(points, origins, axes, L_RANGE)
    assert abs(solution.l_mm - l_brute) < 1e-3
    assert solution.fre_mm <= fre_brute + 1e-9
    assert solution.fre_mm == pytest.approx(_oracle_fre(solution.l_mm, points, origins, axes), abs=1e-9)


def test_registration_l_and_fre_are_the_brute_force_minimum():
    problem = pairing_problem(21)
    markers = [{"id": f"I{k + 1:02d}", "origin": o, "axis": a}
               for k, (o, a) in enumerate(zip(problem.origins_image, problem.axes_image, strict=True))]
    calibration = FrameCalibration([CalibrationPoint(f"P{k + 1:02d}", p, d, 100, 0.2) for k, (p, d) in
                                    enumerate(zip(problem.points_reference, problem.directions_reference,
                                                  strict=True))])
    result = register(markers, calibration, MarkerModel())
    image = np.array([int(p["image_marker"][1:]) - 1 for p in result.pairs])
    cal = np.array([int(p["calibration_point"][1:]) - 1 for p in result.pairs])
    args = (problem.points_reference[cal], problem.origins_image[image], problem.axes_image[image])
    l_brute, fre_brute = _brute_force_minimum(*args)
    assert abs(result.sensor_offset_l_mm - l_brute) < 1e-3
    assert result.fre_mm == pytest.approx(_oracle_fre(result.sensor_offset_l_mm, *args), abs=1e-9)
    assert result.fre_mm <= fre_brute + 1e-9
