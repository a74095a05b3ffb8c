"""The compiled LM on the URDF model against the Python loop it replaces (``lm.LM`` with any other
``fk_jac``): the same answers from the same seeds, its rotation error near π against scipy's, and the
deadline checked between its calls."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.ik import lm_kernel
from hybrid_kinematics_ros.ik.lm import LM, ChainFkJac, joint_limits
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import error6


def test_the_compiled_loop_gives_the_python_loops_answers():
    chain = load_robot_config("ur10").chain
    compiled = ChainFkJac(chain)

    def python(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # the same FK, not a ChainFkJac: the Python loop
        return fk.fk_and_jacobian_single(chain, q)

    limits = joint_limits(chain)
    rng = np.random.default_rng(8)
    same = solved = 0
    for k in range(200):
        q = rng.uniform(chain.lower, chain.upper)
        target = fk.fk_single(chain, q)
        seed = q + rng.normal(scale=0.05 if k % 2 else 0.5, size=6)
        a = LM(compiled, limits, (1e-9, 1e-9), 100).solve(target, seed, np.inf, stop_crawl=bool(k % 3))
        b = LM(python, limits, (1e-9, 1e-9), 100).solve(target, seed, np.inf, stop_crawl=bool(k % 3))
        solved += a[1] <= 1e-9 and a[2] <= 1e-9
        # rounding differs (our elimination, not LAPACK's): the same run to 1e-9 rad, the same iterations
        same += np.allclose(a[0], b[0], atol=1e-8) and a[3] == b[3] and (a[1] <= 1e-9) == (b[1] <= 1e-9)
    assert solved > 150 and same >= 195


def test_its_rotation_error_near_pi_is_scipys():
    rng = np.random.default_rng(9)
    out = np.empty(6)
    for angle in np.linspace(2.5, np.pi, 30):
        axis = rng.normal(size=3)
        x = Rotation.random(random_state=rng)
        target, T = np.eye(4), np.eye(4)  # R_target · R_Tᵀ turns by ``angle`` about ``axis``
        target[:3, :3] = (Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)) * x).as_matrix()
        T[:3, :3] = x.as_matrix()
        lm_kernel.error6(target, T, out)
        expected = error6(target, T)
        if angle < np.pi - 1e-9:  # at π itself the vector's sign is a convention
            np.testing.assert_allclose(out, expected, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(out[3:]), np.linalg.norm(expected[3:]), atol=1e-12)


def test_a_past_deadline_runs_no_iteration_and_a_near_one_few():
    chain = load_robot_config("ur10").chain
    q = np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2])
    target = fk.fk_single(chain, q)
    far = q + 0.8
    limits = joint_limits(chain)
    lm = LM(ChainFkJac(chain), limits, (1e-12, 1e-12), 100)
    _, _, _, iterations = lm.solve(target, far, time.perf_counter() - 1)
    assert iterations == 0
    _, pos, _, iterations = lm.solve(target, far, np.inf)
    assert iterations > 0 and pos < 1e-9
