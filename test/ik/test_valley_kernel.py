"""The valley search's compiled steps against the numpy they replace: the bordered Newton step back onto a
valley, the step along it, halved where the valley turns, and one bracket point's chord step and error along the
lost direction."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.ik import valley, valley_kernel
from hybrid_kinematics_ros.ik.lm import joint_limits, project
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import error6


def _numpy_onto(chain, pose, x, border, v):
    """The step as numpy writes it: (JᵀJ + b bᵀ) [step, w] = [Jᵀe, v]."""
    T, J = fk.fk_and_jacobian_single(chain, x)
    step, w = np.linalg.solve(J.T @ J + np.outer(border, border), np.stack([J.T @ error6(pose, T), v], 1)).T
    return x + step, w / np.linalg.norm(w), float(np.linalg.norm(step))


def test_the_step_onto_a_valley_is_numpys_and_its_trace_keeps_to_it():
    rng = np.random.default_rng(8)
    for robot in ("ur10", "rx160"):
        chain = load_robot_config(robot).chain
        ops = chain.kernel_operands
        for _ in range(50):
            q = rng.uniform(chain.lower, chain.upper)
            q[4] = rng.choice([0.0, 1e-4, 1e-2])  # the wrist straight or nearly: a valley of q4 and q6
            pose = fk.fk_single(chain, q)
            v = np.linalg.svd(fk.fk_and_jacobian_single(chain, q)[1])[2][-1]
            x = q + rng.uniform(0.05, 0.3) * v + 1e-3 * rng.normal(size=6)  # off the valley
            got = valley_kernel.onto(pose, x, v, v, *ops)
            want = _numpy_onto(chain, pose, x, v, v)
            np.testing.assert_allclose(got[0], want[0], atol=1e-10)
            np.testing.assert_allclose(got[1], want[1], atol=1e-8)
            assert abs(got[2] - want[2]) < 1e-10
            # a step along from q, back onto the valley: where the wrist is exactly straight (a valley of exact
            # solutions), the URDF pose there is nearer q's than a step along the weak motion alone leaves it
            # (a UR10's valley curves away from its tangent; an RX160's is straight)
            x, w, ok = valley_kernel.advance(pose, q, v, 0.35, 1.0, 3, *ops)
            assert ok and abs(w @ v) > 0.5 and np.linalg.norm(x - q) > 0.04
            if q[4] != 0.0:
                continue
            tangent = np.linalg.norm(error6(pose, fk.fk_single(chain, q + 0.35 * v)))
            assert np.linalg.norm(error6(pose, fk.fk_single(chain, x))) < 0.1 * tangent + 1e-9


def test_one_rows_chord_step_and_error_along_are_settles_and_alongs():
    """A pose a millimetre and a milliradian off the URDF pose stands in for the hybrid one; near a singularity
    the joint held is the one that moves most along the weak motion (the search's: the other five columns keep
    their rank), away from one any."""
    rng = np.random.default_rng(9)
    for robot in ("ur10", "rx160"):
        chain = load_robot_config(robot).chain
        limits = joint_limits(chain)
        lower, upper, _ = limits
        for _ in range(60):
            q = rng.uniform(lower, upper)
            q[4] = rng.choice([0.0, 1e-4, 0.5])
            q = np.clip(q, lower, upper)
            T = fk.fk_single(chain, q)
            T[:3, 3] += 1e-3 * rng.normal(size=3)
            target = fk.fk_single(chain, np.clip(q + 1e-3 * rng.normal(size=6), lower, upper))
            _, J = fk.fk_and_jacobian_single(chain, q)
            j = int(rng.integers(6)) if q[4] == 0.5 else int(np.argmax(np.abs(np.linalg.svd(J)[2][-1])))
            got = valley_kernel.settle_step(target, T, q, j, lower, upper, *chain.kernel_operands)
            free = [c for c in range(6) if c != j]
            J5, e = J[:, free], error6(target, T)
            want = q.copy()
            step = np.linalg.solve(J5.T @ J5 + 1e-12 * np.eye(5), J5.T @ e)
            want[free] = project(q[free] + step, *(side[free] for side in limits))
            np.testing.assert_allclose(got, want, atol=1e-9)
            r, across = valley_kernel.along_one(target, T, q, j, *chain.kernel_operands)
            r_np, across_np = valley.along(e[None], J[None], np.array([j]))
            assert abs(r - r_np[0]) < 1e-12 + 1e-9 * abs(r_np[0]) and abs(across - across_np[0]) < 1e-12
