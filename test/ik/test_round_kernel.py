"""The fixed point's compiled round against the numpy it replaces: error6 (scipy's rotation vector near π),
the compensated target, and the closed forms' fold by whole turns."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.ik.analytic import fold
from hybrid_kinematics_ros.ik.round_kernel import chord_step, error_and_compensated, nearest_copy
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import error6


def _pose(rotation: Rotation, position: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotation.as_matrix(), position
    return T


def test_the_rounds_error_and_compensated_target_are_numpys():
    chain = load_robot_config("ur10").chain
    rng = np.random.default_rng(4)
    far = 0
    for angle in (0.0, 1e-12, 1e-6, 1e-3, 0.5, 2.9, 3.1, np.pi - 1e-9):
        for _ in range(20):
            q = rng.uniform(chain.lower, chain.upper)
            target = _pose(Rotation.random(random_state=rng), rng.normal(size=3))
            # the hybrid pose: the target turned by ``angle`` about a random axis and moved by a millimetre
            axis = rng.normal(size=3)
            turn = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis))
            hybrid = _pose(turn * Rotation.from_matrix(target[:3, :3]), target[:3, 3] + 1e-3 * rng.normal(size=3))
            e, moved = error_and_compensated(target, hybrid, q, *chain.kernel_operands)
            expected = target @ se3.inverse(hybrid) @ fk.fk_single(chain, q)
            np.testing.assert_allclose(moved, expected, atol=1e-14, rtol=0)
            if angle > 3.0:  # error6's scipy path there; the kernel's axis from the rotation's symmetric part
                far += 1
            # at π itself the vector's sign is a convention
            np.testing.assert_allclose(e, error6(target, hybrid), atol=1e-13 if angle <= 3.0 else 1e-9, rtol=0)
            np.testing.assert_allclose(np.linalg.norm(e[3:]), angle, atol=1e-9)
    assert far == 40


def test_the_nearest_copy_within_the_limits_is_folds_nearest_row():
    lower = np.array([-2 * np.pi, -np.pi, -2.8, -2 * np.pi, -np.pi, -2 * np.pi])
    upper = np.array([2 * np.pi, 0.0, 2.8, 2 * np.pi, np.pi, 2 * np.pi])
    rng = np.random.default_rng(5)
    empty = 0
    for _ in range(300):
        answers = rng.uniform(-np.pi, np.pi, (rng.integers(0, 9), 6))  # IK-Geo's answers lie in (-π, π]
        seed = rng.uniform(lower, upper)
        folded = fold(answers, seed, lower, upper)
        found = nearest_copy(answers, seed, lower, upper)
        if not len(folded):  # no row has a copy within the limits (q2 > 0, |q3| > 2.8)
            assert found.shape == (0,)
            empty += 1
            continue
        np.testing.assert_array_equal(found, folded[np.argmin(np.linalg.norm(folded - seed, axis=1))])
    assert 0 < empty < 300


def test_the_chord_step_is_numpys_solve_and_none_where_singular():
    chain = load_robot_config("ur10").chain
    lower, upper = chain.lower.copy(), chain.upper.copy()
    rng = np.random.default_rng(6)
    clipped = 0
    for _ in range(200):
        q = rng.uniform(lower, upper)
        e = rng.normal(scale=rng.choice([1e-6, 1e-3, 1.0]), size=6)
        jac = fk.fk_and_jacobian_single(chain, q)[1]
        expected = np.clip(q + np.linalg.solve(jac, e), lower, upper)
        clipped += int(np.any((expected == lower) | (expected == upper)))
        np.testing.assert_allclose(chord_step(q, e, *chain.kernel_operands, lower, upper), expected, atol=1e-9)
    assert clipped  # some steps leave the limits and are clipped, as np.clip does
    q = np.zeros(6)  # the UR10 stretched out, its wrist straight: the Jacobian's rank is lost exactly
    q[4] = 0.0
    with np.testing.assert_raises(np.linalg.LinAlgError):
        np.linalg.solve(fk.fk_and_jacobian_single(chain, q)[1], np.ones(6))
    assert chord_step(q, np.ones(6), *chain.kernel_operands, lower, upper).shape == (0,)
