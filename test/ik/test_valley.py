"""The root search along a singular valley of the URDF model (ik/valley.py), through a trained hybrid model:
from the URDF model's answer a radian along the valley from the solution, where LM through the hybrid model
settles in a local minimum, it finds a hybrid configuration that reaches the target, checked on the hybrid
FK."""

from __future__ import annotations

import time

import numpy as np

from hybrid_kinematics_ros.ik.lm import joint_limits
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.ik.valley import NEAR_SINGULAR, valley_starts, weak_direction

TOL_M = 1e-8  # the solver's inner tolerance at its default 1e-4 mm
GENEROUS = IKOptions(timeout_s=5.0)  # tests check answers; bench_ik_singular measures time


def wrist_singular(model, n: int, seed: int) -> np.ndarray:
    """UR10 configurations with the wrist straight (q5 = 0): axes 4 and 6 line up."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.8 * model.chain.lower, 0.8 * model.chain.upper, (n, 6))
    q[:, 4] = 0.0
    return q


def hybrid_errors(model, q: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    T = model.fk_single(q)
    position = 1e3 * np.linalg.norm(T[:3, 3] - target[:3, 3])
    cos = np.clip(0.5 * (np.trace(T[:3, :3].T @ target[:3, :3]) - 1.0), -1.0, 1.0)
    return float(position), float(np.degrees(np.arccos(cos)))


def answered_methods(solver: IKSolver, targets: np.ndarray) -> list[str | None]:
    """Every target solved from a mid-limits seed and reached within 1e-4 mm and 1e-4° on the hybrid FK;
    returns the method of each answer."""
    methods = []
    for target in targets:
        result = solver.solve(target)
        assert result.success, result.message
        position, rotation = hybrid_errors(solver.model, result.q, target)
        assert position < 1e-4 and rotation < 1e-4
        methods.append(result.stats.get("method"))
    return methods


def test_a_start_a_radian_along_the_valley_finds_a_hybrid_solution(trained):
    _, model, _, _ = trained
    limits = joint_limits(model.chain)
    solver = IKSolver(model, GENEROUS)
    found = lm_short = searched = 0
    for q_star in wrist_singular(model, 12, seed=3):
        target = model.fk_single(q_star)
        v, sigma = weak_direction(model, q_star)
        assert sigma < 1e-6  # the URDF model is singular there
        # the URDF model's answer from a seed a radian along its weak motion (joint 4 or 6 a radian further)
        start = solver.classical(target, q_star + 1.0 / np.abs(v).max() * v, time.perf_counter() + 60.0)[0]
        starts = valley_starts(model, target, start, limits, time.perf_counter() + 60.0, TOL_M)
        if starts is None:  # that answer is another branch, away from the singularity: no valley to search
            assert weak_direction(model, start)[1] > NEAR_SINGULAR
            continue
        searched += 1
        assert len(starts) >= 1
        q, _, _ = solver.refiner.unbounded(target, starts[0], time.perf_counter() + 60.0)  # as the solver does
        position, rotation = hybrid_errors(model, q, target)
        found += position < 1e-4 and rotation < 1e-4
        q_lm, _, _ = solver.refiner.unbounded(target, start, time.perf_counter() + 60.0)
        position, rotation = hybrid_errors(model, q_lm, target)
        lm_short += not (position < 1e-4 and rotation < 1e-4)
    assert searched >= 8, searched
    # measured 8-9 of 11 through the valley; LM through the hybrid model alone from the same answers: 0 of 11
    assert found >= 0.6 * searched, (found, searched)
    assert lm_short >= searched // 2, (lm_short, searched)


def test_no_search_away_from_a_singularity(trained):
    _, model, _, _ = trained
    q = np.array([0.3, -1.2, 1.4, -0.6, 1.1, 0.2])
    assert weak_direction(model, q)[1] > NEAR_SINGULAR
    target = model.fk_single(q)
    assert valley_starts(model, target, q, joint_limits(model.chain), time.perf_counter() + 60.0, TOL_M) is None


def test_the_solver_answers_wrist_singular_hybrid_targets_within_tolerance(trained):
    """Mid-limits seed, so the classical answer lies elsewhere on the valley: every answer reaches the target
    through the hybrid FK, and some of them come from the valley search."""
    _, model, _, _ = trained
    methods = answered_methods(IKSolver(model, GENEROUS), model.fk(wrist_singular(model, 12, seed=4)))
    assert "singular valley" in methods, methods
