"""The error model's first-order propagation against Monte Carlo runs of the real fitting code."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from EMRegModule.core.error_model import (
    ErrorModel,
    RegistrationError,
    estimate_isotropic_fle,
    pose_error_covariance,
    registration_covariance,
    registration_error,
    repeated_dwell_ms,
)
from EMRegModule.core.registration import solve_sensor_offset
from EMRegModule.core.transforms import apply_transform, fit_rigid, invert_rigid, make_transform


def _frame(rng: np.random.Generator, n: int, spread_mm: float = 80.0):
    """N sensor points with marker axes on several faces, a true ReferenceToImage and l."""
    origins = rng.uniform(-spread_mm, spread_mm, size=(n, 3))
    axes = np.eye(3)[rng.integers(0, 3, size=n)] * rng.choice([-1.0, 1.0], size=(n, 1))
    reference_to_image = make_transform(Rotation.random(random_state=7).as_matrix(), [30.0, -40.0, 120.0])
    l_true = 14.0
    points_reference = apply_transform(invert_rigid(reference_to_image), origins + l_true * axes)
    return origins, axes, reference_to_image, l_true, points_reference


def test_registration_covariance_matches_monte_carlo_with_anisotropic_errors_and_solved_l():
    rng = np.random.default_rng(11)
    n = 8
    origins, axes, reference_to_image, l_true, points_reference = _frame(rng, n)
    # Different, anisotropic errors per point and per space (Danilchenko & Fitzpatrick's general case).
    factors = rng.normal(size=(n, 3, 3)) * 0.3
    cov_reference = factors @ np.swapaxes(factors, 1, 2) + 0.02 * np.eye(3)
    cov_image = np.array([np.diag(rng.uniform(0.001, 0.03, 3)) for _ in range(n)])
    rotation = reference_to_image[:3, :3]
    cov_total = rotation @ cov_reference @ rotation.T + cov_image
    predicted = registration_covariance(origins + l_true * axes, cov_total, axes)
    targets_image = np.array([[0.0, 0.0, 0.0], [150.0, 20.0, -60.0], [-90.0, 130.0, 40.0]])
    predicted_cov = predicted.at(targets_image)

    chol_reference = np.linalg.cholesky(cov_reference)
    chol_image = np.linalg.cholesky(cov_image)
    errors, l_values = [], []
    for _ in range(500):
        noisy_reference = points_reference + np.einsum("nij,nj->ni", chol_reference, rng.normal(size=(n, 3)))
        noisy_origins = origins + np.einsum("nij,nj->ni", chol_image, rng.normal(size=(n, 3)))
        solution = solve_sensor_offset(noisy_reference, noisy_origins, axes, (10.0, 18.0))
        mapped = apply_transform(solution.reference_to_image, apply_transform(invert_rigid(reference_to_image),
                                                                              targets_image))
        errors.append(mapped - targets_image)
        l_values.append(solution.l_mm)
    errors = np.array(errors)
    for k in range(len(targets_image)):
        measured_ms = float(np.mean(np.sum(errors[:, k] ** 2, axis=1)))
        predicted_ms = float(np.trace(predicted_cov[k]))
        assert predicted_ms == pytest.approx(measured_ms, rel=0.15)
        # the shape too, not only the trace: the largest principal direction agrees
        measured_cov = np.cov(errors[:, k].T)
        assert np.linalg.eigvalsh(predicted_cov[k])[-1] == pytest.approx(np.linalg.eigvalsh(measured_cov)[-1], rel=0.15)
    assert predicted.l_std_mm == pytest.approx(float(np.std(l_values)), rel=0.15)


def test_isotropic_fle_estimate_is_unbiased_with_solved_l_and_matches_fitzpatrick_without_it():
    rng = np.random.default_rng(5)
    n, sigma = 10, 0.3
    origins, axes, reference_to_image, l_true, points_reference = _frame(rng, n)
    estimates_l, estimates_fixed = [], []
    for _ in range(300):
        noisy = points_reference + rng.normal(0.0, sigma, size=(n, 3))
        solution = solve_sensor_offset(noisy, origins, axes, (10.0, 18.0))
        fiducials = origins + solution.l_mm * axes
        residuals = np.linalg.norm(apply_transform(solution.reference_to_image, noisy) - fiducials, axis=1)
        estimates_l.append(estimate_isotropic_fle(residuals, fiducials, axes) ** 2)
        fixed = fit_rigid(noisy, origins + l_true * axes)
        residuals_fixed = np.linalg.norm(apply_transform(fixed, noisy) - (origins + l_true * axes), axis=1)
        estimates_fixed.append(estimate_isotropic_fle(residuals_fixed, origins + l_true * axes) ** 2)
        # without l, the estimate is Fitzpatrick's FLE^2 = FRE^2 N / (N - 2), per axis
        fre2 = float(np.mean(residuals_fixed**2))
        assert 3 * estimates_fixed[-1] == pytest.approx(fre2 * n / (n - 2), rel=1e-9)
    assert np.mean(estimates_l) == pytest.approx(sigma**2, rel=0.08)
    assert np.mean(estimates_fixed) == pytest.approx(sigma**2, rel=0.08)


def test_reference_pose_error_covariance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    lever_arms = np.array([[0.0, 0.0, 0.0], [200.0, 0.0, 0.0], [60.0, -150.0, 90.0]])
    position_sigma, rotation_sigma = 0.1, np.radians(0.05)
    predicted = pose_error_covariance(lever_arms, position_sigma, rotation_sigma)
    rotations = Rotation.from_rotvec(rng.normal(0.0, rotation_sigma, size=(20000, 3))).as_matrix()
    shifts = rng.normal(0.0, position_sigma, size=(20000, 3))
    for k, arm in enumerate(lever_arms):
        moved = rotations @ arm + shifts - arm
        assert np.trace(predicted[k]) == pytest.approx(float(np.mean(np.sum(moved**2, axis=1))), rel=0.05)


def test_degenerate_configurations_give_an_infinite_prediction_never_a_small_number():
    collinear = np.column_stack([np.linspace(-50, 50, 6), np.zeros(6), np.zeros(6)])
    assert not registration_covariance(collinear, np.tile(0.01 * np.eye(3), (6, 1, 1))).determined
    three = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 60.0, 0.0]])
    parallel_axes = np.tile([0.0, 0.0, 1.0], (3, 1))
    covariance = registration_covariance(three, np.tile(0.01 * np.eye(3), (3, 1, 1)), parallel_axes)
    assert not covariance.determined
    assert np.all(np.isinf(covariance.at(np.zeros((1, 3)))))
    # three markers with l free leave 3*3 - 7 = 2 residual degrees of freedom; two markers none
    assert np.isinf(estimate_isotropic_fle(np.zeros(2), three[:2], parallel_axes[:2]))


def test_repeated_dwell_scatter_measures_the_per_dwell_error_whatever_the_common_offset():
    rng = np.random.default_rng(8)
    sigma = 0.3
    estimates = []
    for _ in range(200):
        means = {f"T{k}": np.array([40.0 * k, 0.0, 5.0]) + rng.normal(0, 2.0, 3)  # a common offset per target
                 + rng.normal(0.0, sigma, size=(15, 3)) for k in range(6)}
        ms, dof = repeated_dwell_ms(means)
        assert dof == 6 * 14
        estimates.append(ms)
    assert np.mean(estimates) == pytest.approx(3 * sigma**2, rel=0.03)
    assert repeated_dwell_ms({"T1": np.zeros((1, 3))}) is None


def test_end_to_end_budget_adds_tracking_reference_and_registration():
    rng = np.random.default_rng(2)
    origins, axes, reference_to_image, l_true, points_reference = _frame(rng, 12)
    residuals = rng.normal(0.0, 0.2, size=12)
    error = registration_error(points_reference, origins, axes, l_true, True, residuals)
    assert RegistrationError.from_json(error.to_json()).covariance.parameters == pytest.approx(
        error.covariance.parameters)
    model = ErrorModel.with_priors(reference_to_image, error, reference_error_mm=0.1, reference_error_deg=0.05,
                                   placement_error_mm=0.3)
    targets = np.array([[0.0, 0.0, 0.0], [300.0, 0.0, 0.0]])
    budget = model.budget(targets)
    assert np.allclose(budget.tracking_ms, 3 * error.probe_sigma_mm**2)
    assert np.allclose(budget.placement_ms, 0.09)
    # the reference term grows with the lever arm from the reference sensor
    arms = np.linalg.norm(apply_transform(invert_rigid(reference_to_image), targets), axis=1)
    assert (budget.reference_ms[1] > budget.reference_ms[0]) == (arms[1] > arms[0])
    assert np.allclose(budget.rms_mm**2, budget.registration_ms + budget.tracking_ms + budget.reference_ms + 0.09)


def _fitzpatrick_tre(fiducials: np.ndarray, fle_rms_mm: float, targets: np.ndarray) -> np.ndarray:
    """Fitzpatrick, West & Maurer 1998, written out here as an independent closed form:
    ``TRE^2 = FLE^2 / N (1 + 1/3 sum_k d_k^2 / f_k^2)`` over the principal axes k of the fiducials."""
    centred = fiducials - fiducials.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    ratio = np.zeros(len(targets))
    for k in range(3):
        def off_axis(points, axis=axes[:, k]):
            return np.sum(points**2, axis=1) - (points @ axis) ** 2

        ratio += off_axis(targets - fiducials.mean(axis=0)) / np.mean(off_axis(centred))
    return np.sqrt(fle_rms_mm**2 / len(fiducials) * (1.0 + ratio / 3.0))


def test_isotropic_equal_errors_with_fixed_l_reduce_to_fitzpatricks_formula():
    rng = np.random.default_rng(7)
    fiducials = rng.uniform(-80, 80, size=(8, 3)) * [1.0, 0.6, 0.3] + [40.0, -20.0, 100.0]
    targets = np.array([[0, 0, 0], [60, 40, 100.0], [150, -20, 10]])
    fle_rms = 1.0
    covariance = registration_covariance(fiducials, np.tile(fle_rms**2 / 3 * np.eye(3), (8, 1, 1)))
    ours = np.sqrt(np.trace(covariance.at(targets), axis1=-2, axis2=-1))
    np.testing.assert_allclose(ours, _fitzpatrick_tre(fiducials, fle_rms, targets), rtol=1e-9)


def test_agrees_with_scikit_surgery_where_its_formula_holds():
    """scikit-surgerycore's ``compute_tre_from_fle`` reads eigenvectors as rows, right only for a configuration
    whose principal axes are the coordinate axes and whose centroid is the origin: compare there only."""
    errors = pytest.importorskip("sksurgerycore.algorithms.errors")
    fiducials = np.array([[-50, 0, 0], [50, 0, 0], [0, -30, 0], [0, 30, 0], [0, 0, -10], [0, 0, 10.0]])
    covariance = registration_covariance(fiducials, np.tile(0.5**2 / 3 * np.eye(3), (6, 1, 1)))
    for target in ([0, 0, 0], [20, 40, 60], [100, -5, 3]):
        tre_squared = errors.compute_tre_from_fle(fiducials, 0.5**2, np.array([target], dtype=float))
        ours = np.trace(covariance.at(np.array([target], dtype=float))[0])
        assert ours == pytest.approx(tre_squared, rel=1e-9)

