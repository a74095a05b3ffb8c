"""SE(3) helpers: property-based round trips and checks against scipy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.errors import KinematicsError

finite = st.floats(-10, 10, allow_nan=False)
positions = arrays(np.float64, (5, 3), elements=finite)
quats = arrays(np.float64, (5, 4), elements=st.floats(-1, 1, allow_nan=False)).filter(
    lambda q: np.all(np.linalg.norm(q, axis=1) > 0.1)
)


def normalised(q):
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@settings(max_examples=200, deadline=None)
@given(positions, quats)
def test_pose_matrix_round_trip(p, q):
    q = normalised(q)
    t = se3.matrix_from_pose(p, q)
    p2, q2 = se3.pose_from_matrix(t)
    np.testing.assert_allclose(p2, p, atol=1e-12)
    # a quaternion and its negative are the same rotation
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(se3.matrix_from_pose(p2, q2), t, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(positions, quats, positions, quats)
def test_pose_difference_composes_back(p1, q1, p2, q2):
    t_true = se3.matrix_from_pose(p1, normalised(q1))
    t_model = se3.matrix_from_pose(p2, normalised(q2))
    diff = se3.pose_difference(t_true, t_model)
    np.testing.assert_allclose(diff @ t_model, t_true, atol=1e-11)
    np.testing.assert_allclose(se3.inverse(t_true) @ t_true, np.broadcast_to(np.eye(4), t_true.shape), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, (5, 3), elements=st.floats(-3.0, 3.0, allow_nan=False)), positions)
def test_rotvec_exp_log_round_trip(w, p):
    w = w * np.minimum(1.0, 3.1 / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-300))
    t = se3.from_rotvec(p, w)
    np.testing.assert_allclose(se3.rotvec(t[:, :3, :3]), w, atol=1e-9)
    np.testing.assert_allclose(se3.rotation_angle(t[:, :3, :3]), np.linalg.norm(w, axis=1), atol=1e-9)


def test_pose_errors_units_and_small_angles():
    t = se3.from_rotvec([0.1, 0.2, 0.3], [0.0, 0.0, 0.0])
    moved = se3.from_rotvec([0.1, 0.2, 0.301], [0.0, 1e-9, 0.0])
    pos_mm, rot_deg = se3.pose_errors(moved, t)
    assert pos_mm[0] == pytest.approx(1.0)
    assert rot_deg[0] == pytest.approx(np.degrees(1e-9), rel=1e-6)  # arccos would give 0 here


def test_non_unit_quaternion_is_refused():
    with pytest.raises(KinematicsError, match="unit quaternions"):
        se3.matrix_from_pose([0, 0, 0], [0, 0, 0, 2.0])


@settings(max_examples=300, deadline=None)
@given(quats)
def test_single_quaternion_conversion_matches_scipy(q):
    r = Rotation.from_quat(normalised(q)).as_matrix()
    for m in r:
        ours = se3.quat_from_rotation(m)
        np.testing.assert_allclose(Rotation.from_quat(ours).as_matrix(), m, atol=1e-12)
        expected = Rotation.from_matrix(m).as_quat()
        if abs(expected[3]) > 1e-9:  # at w = 0 (half turns) q and -q both have w >= 0: either is right
            expected *= -1.0 if expected[3] < 0 else 1.0
            np.testing.assert_allclose(ours, expected, atol=1e-12)
        assert ours[3] >= 0.0


@settings(max_examples=200, deadline=None)
@given(positions, quats)
def test_one_pose_from_floats_matches_scipy(p, q):
    q = normalised(q)
    for position, quat in zip(p, q, strict=True):
        ours = se3.matrix_of_pose_one(position.tolist(), quat.tolist())
        np.testing.assert_allclose(ours, se3.matrix_from_pose(position, quat)[0], atol=1e-12, rtol=0)


def test_fit_rigid_matches_scipy_align_vectors_and_recovers_a_known_pose():
    rng = np.random.default_rng(4)
    layout = rng.uniform(-0.1, 0.1, (4, 3))
    truth = se3.from_rotvec(rng.uniform(-2, 2, (30, 3)), rng.uniform(-2, 2, (30, 3)))
    measured = np.einsum("bij,kj->bki", truth[:, :3, :3], layout) + truth[:, None, :3, 3]
    fitted, residual = se3.fit_rigid(layout, measured)
    np.testing.assert_allclose(fitted, truth, atol=1e-12)
    assert np.all(residual < 1e-12)
    noisy = measured + rng.normal(0, 1e-4, measured.shape)
    fitted, residual = se3.fit_rigid(layout, noisy)
    for b in range(len(truth)):
        rot, _ = Rotation.align_vectors(noisy[b] - noisy[b].mean(0), layout - layout.mean(0))
        np.testing.assert_allclose(fitted[b, :3, :3], rot.as_matrix(), atol=1e-10)
    assert np.all((residual > 1e-5) & (residual < 1e-3))
    # a mirrored point set has no rotation onto it: the fit stays a rotation (det +1) and reports the misfit
    fitted, residual = se3.fit_rigid(layout, -measured[:1])
    assert np.linalg.det(fitted[0, :3, :3]) == pytest.approx(1.0) and residual[0] > 1e-3
