"""Trajectory compensation: the calibrated robot, sent the corrected joints, lands on the planned poses."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.ik.compensate import compensate
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics import se3

TIGHT = IKOptions(position_tolerance_mm=1e-6, orientation_tolerance_deg=1e-6)
FLOAT32_FLOOR_MM = 1e-5


def plan(a, b, n=300, seconds=6.0):
    """A rest-to-rest joint move (cosine profile), its analytic velocities and accelerations."""
    t = np.linspace(0.0, seconds, n)
    s = 0.5 - 0.5 * np.cos(np.pi * t / seconds)
    ds = 0.5 * np.pi / seconds * np.sin(np.pi * t / seconds)
    dds = 0.5 * (np.pi / seconds) ** 2 * np.cos(np.pi * t / seconds)
    d = np.asarray(b) - np.asarray(a)
    return t, a + s[:, None] * d, ds[:, None] * d, dds[:, None] * d


A = np.array([0.3, -1.5, 1.6, -1.2, 0.9, 0.4])
B = np.array([0.9, -1.0, 1.1, -0.6, 1.5, 1.0])


def errors_against_plan(model, q_corrected, q_plan):
    """Hybrid FK of the corrected joints against the URDF FK of the planned ones (mm, deg)."""
    got, want = model.fk(q_corrected), model.fk(q_plan, analytic=True)
    return np.array([se3.pose_errors(g, w) for g, w in zip(got, want, strict=True)]).T


def test_corrected_points_land_on_the_planned_poses(trained):
    model = trained[1]
    t, q, qd, qdd = plan(A, B)
    result = compensate(IKSolver(model, TIGHT), q, t, qd, qdd)
    assert result.success, result.message
    assert result.position_error_mm.max() <= 1e-6 and result.orientation_error_deg.max() <= 1e-6
    # evaluated afresh (the batched FK path): the nets compute in float32, so two FK paths of the same
    # model differ by up to ~2e-6 mm; that is the floor any check of the 1e-6 mm tolerance stands on
    pos, rot = errors_against_plan(model, result.positions, q)
    assert pos.max() < FLOAT32_FLOOR_MM and rot.max() < 1e-5
    # the plan itself misses by the calibration's correction; the corrected joints differ from it
    uncorrected, _ = errors_against_plan(model, q, q)
    assert uncorrected.mean() > 0.05 and np.abs(result.positions - q).max() > 1e-5
    # velocities and accelerations consistent with the corrected positions on the kept time grid
    np.testing.assert_allclose(result.velocities, np.gradient(result.positions, t, axis=0), atol=2e-3)
    np.testing.assert_allclose(result.accelerations, np.gradient(result.velocities, t, axis=0), atol=2e-2)
    # rest to rest stays rest to rest (the correction moves slowly)
    assert np.abs(result.velocities[[0, -1]]).max() < 1e-3


def test_a_trajectory_through_a_wrist_singularity(trained):
    """Joint 5 crosses 0: there the corrected wrist would have to spin. Either the points are corrected
    and the path stays continuous, or the first point that cannot be followed is named, never a jump."""
    model = trained[1]
    a, b = A.copy(), B.copy()
    a[4], b[4] = 0.6, -0.6
    t, q, qd, _ = plan(a, b, n=401)
    result = compensate(IKSolver(model, TIGHT), q, t, qd)
    good = slice(None) if result.success else slice(0, result.failed_index)
    pos, rot = errors_against_plan(model, result.positions[good], q[good])
    assert pos.max() < FLOAT32_FLOOR_MM and rot.max() < 1e-5
    plan_step = np.abs(np.diff(q, axis=0)).max()
    assert np.abs(np.diff(result.positions[good], axis=0)).max() < 10 * plan_step
    if not result.success:
        k = result.failed_index
        assert abs(q[k, 4]) < 0.2 and f"point {k}" in result.message and "singularity" in result.message
        assert result.velocities.shape == q.shape  # the caller still gets every array


def test_refuse_policy_names_the_first_point_outside_the_calibrated_range(trained):
    model = trained[1]
    j = int(np.argmax(model.chain.upper - model.trained_upper))
    a, b = A.copy(), A.copy()
    a[j] = model.trained_upper[j] - 0.1
    b[j] = 0.5 * (model.trained_upper[j] + model.chain.upper[j])
    t, q, _, _ = plan(a, b, n=50)
    plan_outside = int(np.flatnonzero(~model.in_calibrated_range(q))[0])
    options = IKOptions(position_tolerance_mm=1e-6, orientation_tolerance_deg=1e-6, require_calibrated_range=True)
    result = compensate(IKSolver(model, options), q, t, require_calibrated_range=True)
    # the corrected joints, a few mrad off the plan, leave the range within a few points of the plan's exit
    first_outside = int(np.flatnonzero(~model.in_calibrated_range(result.positions))[0])
    assert not result.success and result.failed_index == first_outside
    assert abs(first_outside - plan_outside) <= 5
    assert "outside the calibrated range" in result.message and model.joint_names[j] in result.message


def test_malformed_trajectories_are_refused(trained):
    solver = IKSolver(trained[1], TIGHT)
    t, q, _, _ = plan(A, B, n=5)
    with pytest.raises(IKError, match=r"point 3 at 0\.0"):
        compensate(solver, q, np.array([0.0, 0.1, 0.2, 0.0, 0.3]))
    with pytest.raises(IKError, match=r"\(N, 6\)"):
        compensate(solver, q[:, :5], t)
    with pytest.raises(IKError, match="velocities"):
        compensate(solver, q, t, velocities=q[:3])
