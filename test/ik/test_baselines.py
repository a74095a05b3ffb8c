"""The baselines bench_ik compares against: the paper's scipy refinement with eq. 2 or the 6-vector cost,
and Wang et al.'s compensated target."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.ik.baselines import ScipyRefiner, eq2_residual, scipy_refine_solver, wang_baseline
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.lm import joint_limits
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics import se3

GENEROUS = IKOptions(timeout_s=1.0)


def test_eq2_is_the_paper_cost_in_mm():
    a = se3.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])[0]
    b = se3.from_rotvec([0.001, 0.0, 0.0], [0.0, 0.0, 0.0])[0]
    assert np.sum(eq2_residual(a, b) ** 2) == pytest.approx(1.0)  # 1 mm
    r = Rotation.from_rotvec([0.0, 0.0, 0.01]).as_matrix()
    c = a.copy()
    c[:3, :3] = r
    assert np.sum(eq2_residual(a, c) ** 2) == pytest.approx(np.sum((np.eye(3) - r) ** 2))


@pytest.mark.parametrize("cost", ["pose6", "eq2"])
def test_scipy_refinement_reaches_the_hybrid_target(trained, cost):
    _, model, _, _ = trained
    solver = scipy_refine_solver(model, GENEROUS, cost)
    q = np.random.default_rng(4).uniform(model.chain.lower, model.chain.upper, (5, model.chain.dof))
    for target in model.fk(q):
        r = solver.solve(target)
        assert r.success, r.message
        assert "status" in r.stats and r.stats.get("method") != "lm"  # scipy refined it, not our LM


def test_eq2_jacobian_matches_finite_differences(trained):
    """The analytic Jacobian handed to scipy: ∂(eq. 2 residual)/∂q by central differences of the hybrid FK."""
    _, model, _, _ = trained
    refiner = ScipyRefiner(model, joint_limits(model.chain), 1e-4, 1e-4, 0.02, 1.0, cost="eq2")
    q = np.array([0.3, -1.1, 1.2, -0.7, 0.9, 0.2])
    target = model.fk_single(q + 0.01)
    fun, jac = refiner.residual(target)
    h = 1e-6
    numeric = np.column_stack([(fun(q + h * e) - fun(q - h * e)) / (2 * h) for e in np.eye(len(q))])
    np.testing.assert_allclose(jac(q), numeric, atol=1e-3 * np.abs(numeric).max())


def test_unknown_cost_is_refused(trained):
    with pytest.raises(IKError, match="cost must be one of pose6, eq2"):
        scipy_refine_solver(trained[1], GENEROUS, "eq3")


def test_wang_baseline_misses_what_ours_reaches(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    q0 = np.array([0.2, -1.3, 1.4, -1.2, 1.0, 0.1])
    wang = wang_baseline(solver, model.fk(q0)[0], seed=q0)
    ours = solver.solve(model.fk(q0)[0], seed=q0)
    assert ours.position_error_mm < wang.position_error_mm
