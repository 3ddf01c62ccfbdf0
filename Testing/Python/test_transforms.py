"""Transforms: trakSTAR angles, quaternions, rigid fitting, FRE and predicted TRE."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from EMRegModule.core import transforms as tf
from EMRegModule.core.frames import lps_to_ras


def test_angles_follow_rz_ry_rx_like_scipy():
    rng = np.random.default_rng(1)
    angles = rng.uniform([-180, -89, -180], [180, 89, 180], size=(200, 3))
    ours = tf.angles_to_rotation(angles[:, 0], angles[:, 1], angles[:, 2])
    # Intrinsic z-y'-x'' (capital letters in scipy) == Rz @ Ry @ Rx.
    reference = Rotation.from_euler("ZYX", angles, degrees=True).as_matrix()
    np.testing.assert_allclose(ours, reference, atol=1e-12)


def test_angles_round_trip_and_single_axes():
    rng = np.random.default_rng(2)
    angles = rng.uniform([-179, -89, -179], [179, 89, 179], size=(100, 3))
    rotation = tf.angles_to_rotation(*angles.T)
    np.testing.assert_allclose(tf.rotation_to_angles(rotation), angles, atol=1e-9)
    # azimuth 90 turns the sensor's x axis onto the tracker's y axis
    np.testing.assert_allclose(tf.angles_to_rotation(90, 0, 0) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # elevation 90 turns x onto -z (Ry convention)
    np.testing.assert_allclose(tf.angles_to_rotation(0, 90, 0) @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    # roll 90 turns y onto z
    np.testing.assert_allclose(tf.angles_to_rotation(0, 0, 90) @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_gimbal_lock_angles_still_reproduce_rotation():
    rotation = tf.angles_to_rotation(30, 90, 20)
    back = tf.rotation_to_angles(rotation)
    np.testing.assert_allclose(tf.angles_to_rotation(*back), rotation, atol=1e-9)


def test_quaternions_match_scipy_and_round_trip():
    rng = np.random.default_rng(3)
    q_xyzw = Rotation.random(50, random_state=4).as_quat()
    q_wxyz = np.column_stack([q_xyzw[:, 3], q_xyzw[:, :3]])
    np.testing.assert_allclose(
        tf.quaternion_to_rotation(q_wxyz), Rotation.from_quat(q_xyzw).as_matrix(), atol=1e-12
    )
    rotation = tf.quaternion_to_rotation(rng.normal(size=(50, 4)))
    np.testing.assert_allclose(tf.quaternion_to_rotation(tf.rotation_to_quaternion(rotation)), rotation, atol=1e-12)
    assert np.all(tf.rotation_to_quaternion(rotation)[:, 0] >= 0)


def test_fit_rigid_recovers_transform_and_weights_matter():
    rng = np.random.default_rng(5)
    points_a = rng.uniform(-100, 100, size=(12, 3))
    a_to_b = tf.make_transform(tf.random_rotation(rng), [10, -20, 30])
    points_b = tf.apply_transform(a_to_b, points_a)
    np.testing.assert_allclose(tf.fit_rigid(points_a, points_b), a_to_b, atol=1e-9)
    assert tf.fre(a_to_b, points_a, points_b) < 1e-9
    # one gross outlier: down-weighting it restores the exact answer
    corrupted = points_b.copy()
    corrupted[0] += [25, 0, 0]
    weights = np.ones(12)
    weights[0] = 0
    np.testing.assert_allclose(tf.fit_rigid(points_a, corrupted, weights), a_to_b, atol=1e-9)
    assert not np.allclose(tf.fit_rigid(points_a, corrupted), a_to_b, atol=1e-3)


def test_fit_rigid_is_reflection_safe():
    points_a = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0]])
    mirrored = points_a * [1, 1, -1]
    a_to_b = tf.fit_rigid(points_a, mirrored)
    assert tf.is_rigid(a_to_b, 1e-9)


def test_fit_rigid_rejects_bad_input():
    with pytest.raises(ValueError):
        tf.fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        tf.fit_rigid(np.zeros((4, 3)), np.zeros((5, 3)))


def test_invert_and_apply():
    rng = np.random.default_rng(6)
    a_to_b = tf.make_transform(tf.random_rotation(rng), rng.normal(size=3) * 50)
    np.testing.assert_allclose(tf.invert_rigid(a_to_b) @ a_to_b, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(tf.invert_rigid(a_to_b), np.linalg.inv(a_to_b), atol=1e-12)


def test_lps_ras_conversion_is_an_involution():
    rng = np.random.default_rng(8)
    transform = tf.make_transform(tf.random_rotation(rng), [1, 2, 3])
    ras = lps_to_ras(transform)
    np.testing.assert_allclose(ras[:3, 3], [-1, -2, 3])
    np.testing.assert_allclose(lps_to_ras(ras), transform)
    assert tf.is_rigid(ras, 1e-9)


def test_rotation_from_y_axis():
    rotation = tf.rotation_from_y_axis([1, 2, 3])
    np.testing.assert_allclose(rotation[:, 1], np.array([1, 2, 3]) / np.sqrt(14))
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_rotation_vectors_and_matrices_match_scipy_at_every_angle():
    """Vectorised log and exp of rotations, including tiny angles and angles a hair below a half turn."""
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(600, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0.0, np.pi, 400), np.full(100, 1e-9), np.pi - rng.uniform(0, 1e-6, 100)])
    vectors = axes * angles[:, None]
    matrices = Rotation.from_rotvec(vectors).as_matrix()
    np.testing.assert_allclose(tf.rotation_matrices(vectors), matrices, atol=1e-12)
    found = tf.rotation_vectors(matrices)
    np.testing.assert_allclose(np.linalg.norm(found, axis=1), angles, atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(found).as_matrix(), matrices, atol=1e-9)
