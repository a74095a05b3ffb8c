"""The valley trace's compiled step against the numpy it replaces: the bordered Newton step back onto a valley,
and the step along it, halved where the valley turns."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.ik import valley_kernel
from hybrid_kinematics_ros.ik.lm import error6
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config


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
