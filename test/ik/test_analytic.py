"""The closed-form IK path: each chain's family, every branch checked on our own FK against the joints that made
the target, the count against IK-Geo's own, and the solver's path at and near singularities, through the
URDF model and through a hybrid model."""

from __future__ import annotations

import warnings

import ik_geo
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.bench_ik_singular import cases
from hybrid_kinematics_ros.ik.analytic import CHECK_M, AnalyticIK, classify, fold, geometry
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.seeds import NEAR_M, NEAR_RAD
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import error6, error6_batch
from hybrid_kinematics_ros.model.hybrid import HybridModel
from test.ik.test_valley import hybrid_errors

GENEROUS = IKOptions(timeout_s=5.0)  # tests check paths and answers; bench_ik_singular measures time

ARMS = {  # example-robot-data: URDF, base, tip, the family its axes make
    "UR5": ("ur_description/urdf/ur5_robot.urdf", "base_link", "tool0", "three_parallel_two_intersecting"),
    "Jaco": ("kinova_description/robots/kinova.urdf", "base", "j2s6s200_end_effector", "spherical_two_parallel"),
    "Z1": ("z1_description/urdf/z1.urdf", "link00", "link06", "three_parallel_two_intersecting"),
    "Panda": ("panda_description/urdf/panda.urdf", "panda_link0", "panda_hand_tcp", None),  # 7 joints
}


def chain_of(example_robot_data, name: str):
    urdf, base, tip, _ = ARMS[name]
    with warnings.catch_warnings():  # implausible inertials in these URDFs; IK does not use them
        warnings.simplefilter("ignore")
        return chain_from_urdf(example_robot_data / urdf, base, tip)


def wrapped(d: np.ndarray) -> np.ndarray:
    return (d + np.pi) % (2 * np.pi) - np.pi


def random_joints(chain, n: int, seed: int) -> np.ndarray:
    lower = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    upper = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    return np.random.default_rng(seed).uniform(lower, upper, (n, chain.dof))


@pytest.mark.parametrize(
    ("robot", "family"),
    [
        ("ur10", "three_parallel_two_intersecting"),
        ("rx160", "spherical_two_parallel"),
        ("kr16", "spherical_two_parallel"),
    ],
)
def test_embedded_robots_get_their_family_and_every_target_its_own_joints(robot, family):
    chain = load_robot_config(robot).chain
    closed = AnalyticIK.of(chain)
    assert closed is not None and closed.family == family
    q = random_joints(chain, 200, 1)
    for qi, target in zip(q, fk.fk(chain, q), strict=True):
        branches = closed.branches(target, qi + 0.01)
        assert len(branches) >= 1
        # the joints that made the target come first: the branch nearest a seed beside them (to 1e-6 rad, or
        # 1e-4 near the wrist singularity: the RX160's rounded π/2 leaves its wrist 7e-10 m off)
        assert np.abs(branches[0] - qi).max() < (1e-6 if abs(qi[4]) > 0.1 else 1e-4), (qi, branches[0])
        reached = fk.fk(chain, branches)
        assert np.abs(reached - target).max() < 1e-5  # every branch checked on our FK


@pytest.mark.parametrize("name", list(ARMS))
def test_arms_we_did_not_tune_for_are_classified(example_robot_data, name):
    chain = chain_of(example_robot_data, name)
    found = classify(chain)
    assert (found[0] if found else None) == ARMS[name][3]
    if found is None:
        assert IKSolver(HybridModel.analytic_only(chain)).path == "iterative"


def test_an_offset_wrist_falls_to_the_next_family_and_a_tilted_elbow_to_none():
    """Move the UR10's joint 6 sideways: axes 5 and 6 no longer meet, and three parallel axes are left,
    whose closed forms still give each target its joints. Tilt joint 3's axis too: no family, iterative."""
    chain = load_robot_config("ur10").chain
    pre = chain.pre.copy()
    pre[5, 0, 3] += 0.01
    offset = chain.with_geometry(pre, chain.post)
    closed = AnalyticIK.of(offset)
    assert closed.family == "three_parallel"
    q = random_joints(offset, 50, 4)
    hits = []
    for qi, target in zip(q, fk.fk(offset, q), strict=True):
        branches = closed.branches(target, qi)
        hits.append(len(branches) > 0 and np.abs(branches[0] - qi).max() < 1e-6)
    assert np.mean(hits) >= 0.95, np.mean(hits)
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_rotvec([0.01, 0.0, 0.0]).as_matrix()
    pre[2] = pre[2] @ tilt
    assert classify(chain.with_geometry(pre, chain.post)) is None


def test_a_wrist_with_intersecting_first_axes_gets_its_own_family():
    """The KR16 without its shoulder offset (axes 1 and 2 meet) and with joint 3 tilted (axes 2 and 3 no
    longer parallel): IK-Geo's spherical-two-intersecting family, which assumes axes 1 and 2 meet."""
    chain = load_robot_config("kr16").chain
    pre = chain.pre.copy()
    pre[1][:2, 3] = 0.0
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix()
    pre[2] = pre[2] @ tilt
    arm = chain.with_geometry(pre, chain.post)
    closed = AnalyticIK.of(arm)
    assert closed.family == "spherical_two_intersecting"
    q = random_joints(arm, 100, 8)
    for qi, target in zip(q, fk.fk(arm, q), strict=True):
        branches = closed.branches(target, qi + 0.01)
        assert len(branches) and np.abs(branches[0] - qi).max() < 1e-6


def test_the_branch_count_is_ik_geos_own(example_robot_data):
    """Against IK-Geo called directly with its conventions (H, P at the axes' meeting points, the tip's
    rotation at zero taken out, the rotation as columns): as many exact branches inside the limits, and
    ``solve_many`` returns each of them."""
    chain = chain_of(example_robot_data, "UR5")
    family, points = classify(chain)
    g = geometry(chain)
    p = np.vstack([points[0], np.diff(points, axis=0), g.tip[:3, 3] - points[-1]])
    robot = getattr(ik_geo.Robot, family)(g.axes.tolist(), p.tolist())
    model = HybridModel.analytic_only(chain)
    solver = IKSolver(model, GENEROUS)
    for target in fk.fk(chain, random_joints(chain, 40, 2)):
        answers = robot.get_ik((target[:3, :3] @ g.tip[:3, :3].T).T.tolist(), target[:3, 3].tolist())
        exact = np.array([q for q, least_squares in answers if not least_squares])
        inside = fold(exact, chain.mid_limits(), solver.lower, solver.upper)
        assert len(solver.closed_form.branches(target, chain.mid_limits())) == len(inside)
        assert len(solver.solve_many(target, max_solutions=16, analytic=True)) == len(inside)


def test_fold_keeps_each_joint_within_its_limits_nearest_the_seed():
    lower, upper = np.array([-2 * np.pi, -1.0]), np.array([2 * np.pi, 1.0])
    q = np.array([[3.0, 0.5], [3.0, 3.0]])  # the second: 3 rad on joint 2 has no equivalent in ±1
    out = fold(q, np.array([-3.0, 0.0]), lower, upper)
    np.testing.assert_allclose(out, [[3.0 - 2 * np.pi, 0.5]])
    # a seed wound up far beyond the limits: the turn inside them nearest it
    np.testing.assert_allclose(
        fold(np.array([[0.5]]), np.array([20.0]), np.array([0.0]), np.array([13.0])), [[0.5 + 2 * np.pi]]
    )


def test_a_branch_past_a_joint_limit_is_clipped_into_the_limits():
    """The UR10's q3 made 0.1 rad past its -2.8 rad limit: that branch is not among the in-limit ones, and
    ``clipped`` gives it with q3 at the limit and the other joints as they were, ``past_limits`` as it is;
    in-limit branches stay out."""
    chain = load_robot_config("ur10").chain
    ik = AnalyticIK.of(chain)
    rng = np.random.default_rng(4)
    for _ in range(5):
        q = rng.uniform(chain.lower, chain.upper)
        q[4] = rng.choice([-1, 1]) * rng.uniform(0.3, 1.5)  # a regular wrist
        q[2] = chain.lower[2] - 0.1
        target = fk.fk_single(chain, q)
        assert not any(np.abs(wrapped(b - q)).max() < 1e-6 for b in ik.branches(target, q))
        expected = np.clip(q, chain.lower, chain.upper)
        clipped = ik.clipped(target, q)
        assert np.all((clipped >= chain.lower) & (clipped <= chain.upper))
        assert min(np.abs(wrapped(c - expected)).max() for c in clipped) < 1e-6
        # the others: no copy of them lies within the limits
        for c in clipped:
            assert not any(np.abs(wrapped(b - c)).max() < 1e-9 for b in ik.branches(target, q))
        # unclipped (the valley search walks from these into the limits): that branch itself, q3 0.1 past its
        # lower limit rather than 0.58 past the upper one, whatever the seed; exact on our FK
        for seed in (q, np.r_[q[:2], 2.0, q[3:]]):
            past = ik.past_limits(target, seed)
            assert min(np.abs(c - q).max() for c in past) < 1e-6
        assert np.all(np.any((past < chain.lower) | (past > chain.upper), axis=1))
        for c in past:
            assert np.abs(error6(target, fk.fk_single(chain, c))).max() < 1e-9


@pytest.mark.parametrize("q5", [0.0, 1e-4])
def test_urdf_targets_at_and_near_the_wrist_singularity(q5):
    """Near it the closed forms answer at once. Exactly at it the wrist's branch has no closed-form answer
    (its solutions form a continuum): the answer is the member nearest the seed, and the result says the
    target is singular."""
    chain = load_robot_config("rx160").chain
    solver = IKSolver(HybridModel.analytic_only(chain), GENEROUS)
    q = random_joints(chain, 20, 3)
    q[:, 4] = q5
    singular = 0
    for qi, target in zip(q, fk.fk(chain, q), strict=True):
        seed = qi + 0.01  # near the configuration that made the target
        result = solver.solve(target, seed, analytic=True)
        assert result.success, result.message
        assert result.stats["path"] == "closed form (spherical_two_parallel)"
        if q5:  # one closed-form answer, no LM
            assert result.stats["attempts"] == 1 and "singular" not in result.stats
            assert np.abs(result.q - qi).max() < 1e-6
        elif result.stats.get("singular"):
            assert "singular" in result.message, result.message
            assert np.abs(result.q - seed).max() < 0.02  # the continuum's member near the seed
            singular += 1
    # IK-Geo leaves the singular branch out altogether for a few targets (1 of these 20): another branch
    assert singular >= (18 if q5 == 0.0 else 0), singular


def test_hybrid_targets_near_a_shoulder_singularity_take_the_fixed_point(trained):
    """The UR10's wrist centre 1e-4 rad from its shoulder singularity: the hybrid solution comes from the
    closed forms' fixed point, not from LM through the hybrid model."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    chain = model.chain
    q = np.array([0.4, -1.0, 1.2, -0.7, 0.9, 0.3])

    def sigma(x: float) -> float:
        v = q.copy()
        v[1] = x
        return np.linalg.svd(fk.fk_and_jacobian_single(chain, v)[1], compute_uv=False)[-1]

    grid = np.linspace(-np.pi, 0.0, 2001)
    q[1] = grid[np.argmin([sigma(x) for x in grid])]
    assert sigma(q[1]) < 5e-3  # on the singularity to within the grid
    methods = []
    for offset in (1e-4, 2e-3, -2e-3):
        target = model.fk_single(q + np.array([0, offset, 0, 0, 0, 0]))
        result = solver.solve(target, seed=q)
        assert result.success, result.message
        methods.append(result.stats.get("method"))
    assert methods.count("closed-form fixed point") >= 2, methods


def test_hybrid_targets_beyond_the_urdf_models_reach_start_from_its_nearest_answers(trained):
    """The UR10's wrist on the cylinder its shoulder offset leaves around axis 1 (its shoulder singularity): a
    hybrid target there lies beyond the URDF model's reach about half the time, with no exact branch. The
    closed forms' least-squares answers, a correction's size away, start the hybrid solutions, of ``solve`` and
    of ``solve_many``: no URDF-model restart runs (they all failed, and took half the budget)."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    qs = cases(model.chain, 20, np.random.default_rng(7))["wrist centre on axis 1"]
    beyond = 0
    for q, target in zip(qs, model.fk(qs), strict=True):
        if len(solver.branches(target, q)):  # within the URDF model's reach: the usual path
            continue
        beyond += 1
        near = solver.closed_form.approximations(target, q, NEAR_M, NEAR_RAD)
        assert len(near), "a least-squares answer within a correction's size of the target"
        assert np.all(np.linalg.norm(error6_batch(target, fk.fk(model.chain, near))[:, :3], axis=1) > CHECK_M)
        result = solver.solve(target)
        assert result.success, (result.position_error_mm, result.stats)
        assert result.stats["beyond_urdf_reach"] and result.stats["attempts"] == 0
        assert max(hybrid_errors(model, result.q, target)) < 1e-4
        # several solutions start from the same answers (the URDF-model seed searches found none here)
        many = solver.solve_many(target, max_solutions=8)
        assert many and all(max(hybrid_errors(model, r.q, target)) < 1e-4 for r in many), len(many)
    assert beyond >= 5, beyond


def test_a_near_miss_beyond_reach_restarts_along_its_weak_direction_before_the_valley_search(trained):
    """Beyond the URDF model's reach, the nearest least-squares answer's fixed point can stall next to a hybrid
    solution at a near-singular Jacobian. The restarts along its weak direction (a few ms of LM) run before the
    valley search, which took a 50 ms budget where they would have solved (an RX160, elbow stretched). On the
    UR10 with its elbow stretched they find 4 of the 10 beyond reach here, each a solution through the hybrid FK."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    qs = cases(model.chain, 100, np.random.default_rng(8))["elbow stretched"]
    beyond, weak = 0, 0
    for target in model.fk(qs):
        result = solver.solve(target)
        if not result.stats.get("beyond_urdf_reach"):
            continue
        beyond += 1
        assert result.success, (result.position_error_mm, result.stats)
        assert max(hybrid_errors(model, result.q, target)) < 1e-4
        if result.stats.get("weak_restart"):
            weak += 1
            assert result.stats.get("method") != "singular valley" and result.stats["attempts"] == 0
    assert beyond >= 5 and weak >= 2, (beyond, weak)


def test_the_fixed_points_side_by_side_are_each_branchs_own(trained):
    """``solve_many``'s fixed points run in step, the rounds before a Newton step batched: each branch ends where
    its fixed point alone ends (the batch's float32 products differ by about a nanometre, which the Newton
    rounds after absorb), within the polish tolerance through the hybrid FK."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    rng = np.random.default_rng(11)
    q = rng.uniform(model.chain.lower, model.chain.upper, (15, 6))
    checked = 0
    for target in model.fk(q):
        starts = list(solver.branches(target, model.chain.mid_limits()))
        if len(starts) < 2:
            continue
        together = solver.fixed_points(target, starts, float("inf"))
        for start, (q_many, errors, beyond) in zip(starts, together, strict=True):
            q_one, errors_one, beyond_one = solver.fixed_point(target, start, float("inf"))
            assert beyond == beyond_one and np.allclose(q_many, q_one, atol=1e-8), (q_many - q_one, errors, errors_one)
            if not beyond:
                assert max(hybrid_errors(model, q_many, target)) < 1e-5, errors  # mm and degrees
            checked += 1
    assert checked >= 20, checked


def test_a_chain_of_five_joints_gets_one_clear_line(example_robot_data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chain = chain_from_urdf(example_robot_data / "so_arm_description/urdf/so100.urdf", "base", "gripper")
    solver = IKSolver(HybridModel.analytic_only(chain))
    with pytest.raises(IKError, match=r"IK needs a chain of 6 or 7 joints; base -> gripper has 5: choose another"):
        solver.solve(fk.fk(chain, np.zeros(5))[0])


def test_the_batched_pose_error_is_lm_error6_at_every_angle():
    rng = np.random.default_rng(5)
    T = np.tile(np.eye(4), (40, 1, 1))
    T[:, :3, :3] = Rotation.random(40, random_state=6).as_matrix()
    T[:, :3, 3] = rng.normal(size=(40, 3))
    target = fk.fk(load_robot_config("ur10").chain, np.full(6, 0.3))[0]
    T[0, :3, :3] = target[:3, :3]  # no rotation
    T[1, :3, :3] = target[:3, :3] @ Rotation.from_rotvec([1e-9, 0.0, 0.0]).as_matrix().T
    T[2, :3, :3] = target[:3, :3] @ Rotation.from_rotvec([0.0, np.pi - 1e-3, 0.0]).as_matrix().T
    np.testing.assert_allclose(error6_batch(target, T), [error6(target, t) for t in T], atol=1e-12)
    # a target per pose, and scipy's rotation vector of each rotation between them
    targets = np.concatenate([T[1:], T[:1]])
    rotvec = Rotation.from_matrix(targets[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1)).as_rotvec()
    np.testing.assert_allclose(error6_batch(targets, T)[:, 3:], rotvec, atol=1e-12)


def test_several_solutions_of_a_singular_target_include_the_singular_branch():
    """At q5 = 0 the wrist's branch has no closed-form answer; ``solve_many`` still finds a member of its
    continuum: the configuration that made the target, up to the q4/q6 trade-off (same pose). The RX160's
    spherical wrist: its continuum is q4 + q6 alone (the UR's four parallel axes move q2 and q3 too)."""
    chain = load_robot_config("rx160").chain
    solver = IKSolver(HybridModel.analytic_only(chain), GENEROUS)
    q = random_joints(chain, 20, 9)
    q[:, 4] = 0.0
    found = 0
    for qi, target in zip(q, fk.fk(chain, q), strict=True):
        results = solver.solve_many(target, max_solutions=16, analytic=True)  # from mid-limits
        # the same branch: joints 1-3 and 5 as made (4 and 6 trade off along the continuum)
        found += any(np.abs(np.delete(wrapped(r.q - qi), [3, 5])).max() < 1e-5 for r in results)
    assert found >= 18, found


@pytest.mark.parametrize("robot", ["ur10", "rx160"])
def test_the_quick_urdf_answer_is_the_classical_stage_s(robot):
    """Where the nearest exact branch needs no polish and no branch is singular, ``solve`` answers from it at
    once: the same joints as the whole classical stage (every branch checked and polished), from any seed,
    with the wrist near its singularity too (where a rough branch must take the stage's polish)."""
    chain = load_robot_config(robot).chain
    solver = IKSolver(HybridModel.analytic_only(chain), GENEROUS)
    rng = np.random.default_rng(11)
    q = random_joints(chain, 60, 5)
    q[:20, 4] = rng.choice([-1.0, 1.0], 20) * 1e-4
    seeds = random_joints(chain, 60, 6)
    for target, seed in zip(fk.fk(chain, q), seeds, strict=True):
        result = solver.solve(target, seed, analytic=True)
        staged, *_ = solver.classical(target, seed, float("inf"), branches=solver.branches(target, seed))
        assert result.success and result.stats["attempts"] == 1, result.message
        np.testing.assert_allclose(result.q, staged, atol=1e-9, rtol=0)
