"""IK round trips through the hybrid model, several solutions, clean failures, limits never violated."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.seeds import VALLEY_STEPS_RAD, valley_seeds
from hybrid_kinematics_ros.ik.solver import SINGULAR, IKOptions, IKSolver, pose_problem
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import CONFIG_DIR, load_robot_config
from hybrid_kinematics_ros.model.hybrid import HybridModel

GENEROUS = IKOptions(timeout_s=1.0)  # tests check correctness; bench/ measures speed


def targets(model, n, seed):
    q = np.random.default_rng(seed).uniform(model.chain.lower, model.chain.upper, (n, model.chain.dof))
    return q, model.fk(q)


def test_hybrid_round_trip_ur10(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    _, T = targets(model, 40, 1)
    for target in T:
        r = solver.solve(target)
        assert r.success, r.message
        assert r.position_error_mm < 1e-4 and r.orientation_error_deg < 1e-4
        assert np.all(r.q >= model.chain.lower) and np.all(r.q <= model.chain.upper)
        pos, _ = se3.pose_errors(model.fk(r.q)[0], target)
        assert pos == pytest.approx(r.position_error_mm, abs=2e-6)  # batched float32 nets round differently


def test_the_fixed_point_reaches_the_polish_tolerance_in_about_four_hybrid_evaluations(trained, monkeypatch):
    """Each closed-form round cuts the error ~100× and within LINEAR_M a chord step on the URDF Jacobian as much:
    about four hybrid FKs a target (this fixture's small nets: 4.3), none with the hybrid Jacobian (it cost more
    than the round it saved), to errors below 1e-6 mm."""
    _, model, _, _ = trained
    _, T = targets(model, 30, 5)
    solver = IKSolver(model, GENEROUS)
    calls = {"fk": 0, "jacobian": 0}
    fk_single, fk_and_jacobian_single = model.fk_single, model.fk_and_jacobian_single

    def counted_fk(q, analytic=False):
        calls["fk"] += not analytic
        return fk_single(q, analytic=analytic)

    def counted_jacobian(q, analytic=False):
        calls["jacobian"] += not analytic
        return fk_and_jacobian_single(q, analytic=analytic)

    monkeypatch.setattr(model, "fk_single", counted_fk)
    monkeypatch.setattr(model, "fk_and_jacobian_single", counted_jacobian)
    errors = []
    for target in T:
        r = solver.solve(target)
        assert r.success, r.message
        errors.append(r.position_error_mm)
    assert calls["jacobian"] == 0 and calls["fk"] / len(T) <= 4.8, calls
    assert np.mean(errors) < 1e-6, np.mean(errors)


def test_round_trip_rx160_analytic_model():
    cfg = load_robot_config("rx160")
    model = HybridModel.analytic_only(cfg.chain)
    solver = IKSolver(model, GENEROUS)
    _, T = targets(model, 30, 2)
    for target in T:
        r = solver.solve(target, analytic=True)
        assert r.success, r.message
        assert np.all(r.q >= model.chain.lower - 1e-12) and np.all(r.q <= model.chain.upper + 1e-12)


def test_near_elbow_singularity(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    q = np.array([0.3, -1.2, 1e-3, -1.0, 1.2, 0.4])
    r = solver.solve(model.fk(q)[0], seed=q + 0.05)
    assert r.success, r.message


def test_lm_stops_on_a_floor_beyond_reach():
    """A target 0.3 mm beyond the stretched arm's reach: LM settles on the nearest pose and says so within
    a few steps, instead of creeping through its whole iteration budget (the solver then tries other branches)."""
    chain = load_robot_config("ur10").chain
    solver = IKSolver(HybridModel.analytic_only(chain))
    q = np.array([0.3, -0.8, 0.0, -1.0, 1.2, 0.4])  # elbow straight
    frames = fk.joint_frames(chain, q[None])[0]
    outward = frames[3, :3, 3] - frames[1, :3, 3]  # shoulder to wrist
    target = fk.fk_single(chain, q)
    target[:3, 3] += 3e-4 * outward / np.linalg.norm(outward)
    for seed in (q + 0.05, q - 0.05):
        deadline = time.perf_counter() + 60
        tight = solver.urdf_lm._replace(tol=(1e-9, 1e-9), max_iterations=100)
        _, pos, _, iterations = tight.solve(target, seed, deadline)
        assert pos == pytest.approx(3e-4, rel=1e-3) and iterations < 20


def test_near_misses_at_a_wrist_singularity_restart_along_the_valley():
    """At joint_5 = 0 the UR10's wrist joints 4 and 6 trade off; a near miss there restarts along that
    direction (the Jacobian's weak one), and nowhere else."""
    chain = load_robot_config("ur10").chain
    solver = IKSolver(HybridModel.analytic_only(chain))
    singular = np.array([0.3, -1.2, 1.3, -0.9, 1e-5, 0.2])
    seeds = valley_seeds(solver.model, singular, 0.01, solver.limits)
    assert len(seeds) == len(VALLEY_STEPS_RAD)
    _, J = solver.model.fk_and_jacobian_single(singular, analytic=True)
    for seed, step in zip(seeds, VALLEY_STEPS_RAD, strict=True):
        move = seed - singular
        assert np.linalg.norm(move) == pytest.approx(abs(step))
        assert set(np.argsort(-np.abs(move))[:2]) == {3, 5}  # mostly joints 4 and 6
        assert np.linalg.norm(J @ move) < 1e-3 * abs(step)  # the pose hardly moves
    assert valley_seeds(solver.model, singular, 1.0, solver.limits) == []  # not a near miss
    regular = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    assert valley_seeds(solver.model, regular, 0.01, solver.limits) == []  # not singular


def test_the_rank_check_is_the_svds_verdict():
    """_rank_lost's determinant shortcut proves regularity only: on regular, near-singular and singular
    configurations of each family it says what the smallest singular value says."""
    for robot in ("ur10", "rx160"):
        chain = load_robot_config(robot).chain
        solver = IKSolver(HybridModel.analytic_only(chain))
        rng = np.random.default_rng(6)
        for _ in range(60):
            q = rng.uniform(-3, 3, 6)
            q[4] = rng.choice([q[4], 0.0, 1e-9, 1e-7, 1e-5, 1e-3])  # the wrist at and near its singularity
            q[2] = rng.choice([q[2], 0.0, 1e-8])  # the elbow stretched, or not
            jac = solver.model.fk_and_jacobian_single(q, analytic=True)[1]
            assert solver._rank_lost(q) == (np.linalg.svd(jac, compute_uv=False)[-1] < SINGULAR)


def test_ur10_distinct_branches():
    """Full URDF limits: the UR10 has up to 8 analytic branches; they are distinct and all reach the target."""
    chain = chain_from_urdf(CONFIG_DIR / "ur10.urdf", "base_link", "tool0")
    model = HybridModel.analytic_only(chain)
    solver = IKSolver(model, IKOptions(timeout_s=1.0))
    q = np.array([0.4, -1.1, 1.3, -0.8, 1.1, 0.3])
    results = solver.solve_many(model.fk(q)[0], seed=q, max_solutions=8, analytic=True)
    assert len(results) == 8
    assert np.allclose(results[0].q, q, atol=1e-6)  # nearest to the seed first
    dists = [np.linalg.norm(r.q - q) for r in results]
    assert dists == sorted(dists)
    for i, a in enumerate(results):
        assert a.success
        for b in results[i + 1 :]:
            wrapped = (a.q - b.q + np.pi) % (2 * np.pi) - np.pi
            assert np.abs(wrapped).max() > 1e-3


def test_unreachable_target_fails_cleanly(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, IKOptions(timeout_s=0.05))
    target = np.eye(4)
    target[:3, 3] = [3.0, 0.0, 0.5]  # 3 m away: the UR10 reaches 1.3 m
    r = solver.solve(target)
    assert not r.success
    assert "no solution within tolerance" in r.message
    assert solver.solve_many(target, max_solutions=3) == []


def test_outside_calibrated_range_can_be_refused(trained):
    _, model, _, _ = trained
    narrow = HybridModel(model.chain, model.nets, {"trained_range": {"lower": [-0.5] * 6, "upper": [0.5] * 6}})
    q = np.array([1.0, -0.3, 0.4, -0.2, 0.3, 0.1])  # shoulder_pan_joint outside the trained range
    strict = IKSolver(narrow, IKOptions(timeout_s=1.0, require_calibrated_range=True))
    r = strict.solve(narrow.fk(q)[0], seed=q)
    # other branches are tried too; every one of them leaves the trained box here
    assert not r.success and "outside the calibrated joint range (" in r.message
    assert not r.in_calibrated_range
    lenient = IKSolver(narrow, IKOptions(timeout_s=1.0)).solve(narrow.fk(q)[0], seed=q)
    assert lenient.success and not lenient.in_calibrated_range


def test_bad_requests_raise(trained):
    _, model, _, _ = trained
    solver = IKSolver(model)
    with pytest.raises(IKError, match="finite 4x4"):
        solver.solve(np.full((4, 4), np.nan))
    with pytest.raises(IKError, match="6 finite joint values"):
        solver.solve(np.eye(4), seed=np.zeros(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(IKError, match="not orthonormal"):
        solver.solve(bad)
    mirrored = np.eye(4)
    mirrored[2, 2] = -1.0  # orthonormal columns, and a reflection
    with pytest.raises(IKError, match="not orthonormal"):
        solver.solve(mirrored)


def test_trajectory(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    q0 = np.array([0.2, -1.3, 1.4, -1.2, 1.0, 0.1])
    path = q0 + np.linspace(0, 0.3, 25)[:, None] * np.array([1, 0.5, -0.5, 0.3, 0.2, 0.1])
    results = solver.solve_trajectory(model.fk(path), seed=q0)
    assert all(r.success for r in results)


def test_the_requests_pose_check_is_numpys():
    """pose_problem's float arithmetic against numpy's orthonormality and determinant, near the 1e-6 edge."""
    rng = np.random.default_rng(3)
    for scale in (0.0, 1e-7, 1e-6, 1e-5, 1e-3):
        for _ in range(40):
            pose = np.eye(4)
            pose[:3, :3] = se3.exp_so3(rng.normal(size=3)) * rng.choice([1.0, -1.0]) + scale * rng.normal(size=(3, 3))
            r = pose[:3, :3]
            bad = np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0
            assert (pose_problem(pose) is not None) == bad
    pose = np.eye(4)
    pose[1, 3] = np.inf
    assert "finite" in pose_problem(pose)


def test_the_pose_error_is_scipys_rotation_vector():
    """error6's Python-float rotation vector against scipy's, from nearly zero to nearly a half turn."""
    from scipy.spatial.transform import Rotation

    from hybrid_kinematics_ros.kinematics.se3 import error6

    rng = np.random.default_rng(4)
    for angle in (1e-12, 1e-7, 0.3, 2.0, 2.99, 3.01, np.pi - 1e-6):
        axis = rng.normal(size=3)
        w = angle * axis / np.linalg.norm(axis)
        target, pose = np.eye(4), np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        target[:3, 3], pose[:3, 3] = rng.normal(size=3), rng.normal(size=3)
        target[:3, :3] = Rotation.from_rotvec(w).as_matrix() @ pose[:3, :3]
        e = error6(target, pose)
        np.testing.assert_allclose(e[:3], target[:3, 3] - pose[:3, 3], atol=1e-15)
        np.testing.assert_allclose(e[3:], w, atol=1e-13, rtol=0)


def test_a_chain_with_a_continuous_joint_builds_its_solver_and_solves():
    """The solver's warm-up at construction stays within finite limits (a continuous joint's are infinite: its
    first warm-up target was NaN, and every arm with one, a Jaco's, was refused at construction)."""
    chain = load_robot_config("ur10").chain
    lower, upper = chain.lower.copy(), chain.upper.copy()
    lower[5], upper[5] = -np.inf, np.inf
    chain = replace(chain, lower=lower, upper=upper)
    solver = IKSolver(HybridModel.analytic_only(chain))
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 4.0])
    result = solver.solve(fk.fk_single(chain, q))
    assert result.success, result.message
