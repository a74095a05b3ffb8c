"""IK on arms we did not tune for (example-robot-data), through the URDF model alone: a target on a wrist
singularity, and the arms with 7 joints (solved, keeping the seed's self-motion)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hybrid_kinematics_ros.ik import lm
from hybrid_kinematics_ros.ik.seeds import valley_seeds
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.model.hybrid import HybridModel

GENEROUS = IKOptions(timeout_s=5.0)  # tests count steps, bench_ik_arms measures time


def arm(example_robot_data, urdf: str, base: str, tip: str) -> HybridModel:
    with warnings.catch_warnings():  # implausible inertials in these URDFs; IK does not use them
        warnings.simplefilter("ignore")
        return HybridModel.analytic_only(chain_from_urdf(example_robot_data / urdf, base, tip))


@pytest.fixture(scope="module")
def talos(example_robot_data):
    return arm(example_robot_data, "talos_data/robots/talos_left_arm.urdf", "arm_left_1_link", "arm_left_7_link")


@pytest.fixture(scope="module")
def panda(example_robot_data):
    return arm(example_robot_data, "panda_description/urdf/panda.urdf", "panda_link0", "panda_hand_tcp")


def test_crawling_seeds_give_way_at_a_wrist_singularity(talos):
    """bench_ik_arms' TALOS target 762 sits on a wrist singularity (smallest singular value 2.5e-5). From 13 of
    the 16 table seeds LM crept towards it, 100 steps each, and the 50 ms budget ran out before the seed that
    converges. Crawls now give way: the classical stage reaches it in under half the steps."""
    solver = IKSolver(talos, GENEROUS)
    q = np.array([2.51177, 0.62682, -0.145863, -2.271929, -1.184256, -0.005792])
    target = talos.fk_single(q)
    steps = 0

    def counted(x):
        nonlocal steps
        steps += 1
        return talos.fk_and_jacobian_single(x, analytic=True)

    solver.urdf_lm = solver.urdf_lm._replace(fk_jac=counted)
    r = solver.solve(target)
    assert r.success, r.message
    assert steps < 600, steps  # 1,257 when every crawl ran its 100 iterations


def test_crawl_rule_spares_linear_convergence():
    """Newton at an exact singularity halves the error per step: the crawl rule must not stop that."""
    target = np.eye(4)
    errors = iter(np.geomspace(1e-4, 1e-12, 60))

    def halving(q):
        T = np.eye(4)
        T[0, 3] = next(errors)
        return T, np.eye(6)[:, :1] * 1e-9  # a step that moves nothing: progress comes from the sequence

    limits = (np.array([-1.0]), np.array([1.0]), np.array([False]))
    crawl = lm.LM(halving, limits, (1e-11, 1e-9), 100)
    _, ep, _, iterations = crawl.solve(target, np.zeros(1), np.inf, stop_crawl=True)
    assert ep <= 1e-11 and iterations > lm.CRAWL_WINDOW


def test_seven_joints_keep_the_seeds_self_motion(panda):
    """Redundant arms are solved: each step is the damped least-squares (smallest) joint motion, so a seed
    displaced along the self-motion stays where it is instead of returning to the configuration the target
    came from."""
    solver = IKSolver(panda, GENEROUS)
    q = np.array([0.3, -0.4, 0.2, -2.0, 0.1, 1.8, 0.5])
    target = panda.fk_single(q)
    _, _, vt = np.linalg.svd(panda.fk_and_jacobian_single(q)[1])
    seed = q + 0.2 * vt[-1]  # along the null space: the pose moves only to second order
    r = solver.solve(target, seed=seed)
    assert r.success, r.message
    assert np.linalg.norm(r.q - seed) < 0.02 < np.linalg.norm(r.q - q)


def test_seven_joints_several_solutions_and_valley(panda):
    solver = IKSolver(panda, GENEROUS)
    q = np.array([1.550493, 1.398457, -1.714737, -0.47369, -0.02151, 2.330395, -0.220215])  # wrist singular
    target = panda.fk_single(q)
    results = solver.solve_many(target, seed=q, max_solutions=4)
    assert results and all(r.success for r in results)
    assert np.allclose(results[0].q, q, atol=1e-6)
    # the valley restarts step along the weakest direction that moves the pose, not along the self-motion
    _, _, vt = np.linalg.svd(panda.fk_and_jacobian_single(q)[1])
    steps = valley_seeds(panda, q, 0.01, solver.limits)
    assert steps
    for seed in steps:
        move = seed - q
        assert abs(vt[-1] @ move) < 0.1 * np.linalg.norm(move)  # 0 but where the limits clip the step
