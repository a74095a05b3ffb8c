"""One round of the closed forms' fixed point (:mod:`~hybrid_kinematics_ros.ik.fixed_point`), its arithmetic compiled.

A round takes the hybrid pose at its configuration, its error to the target, the compensated target and the
closed forms' branch nearest it: a UR10 solve makes five rounds, and in numpy each of these steps costs a
dozen calls of a microsecond or more, most of a round once the hybrid pose is one compiled call
(``model/pose_kernel.py``). The maths is that of ``se3.error6``, ``solver.compensated_target`` and
``analytic.fold``; tests check these kernels against them.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hybrid_kinematics_ros.ik import lm_kernel
from hybrid_kinematics_ros.kinematics import fk_kernel

TAU = 2.0 * math.pi


@numba.njit(cache=True, nogil=True)
def error_and_compensated(target, hybrid, q, generators, revolute, post, axes):
    """``se3.error6(target, hybrid)`` ``(6,)`` (``lm_kernel.error6``) and the compensated target
    ``target · hybrid⁻¹ · T_URDF(q)`` ``(4, 4)`` (``solver.compensated_target``), the URDF pose from the chain's
    kernel operands."""
    e = np.empty(6)
    lm_kernel.error6(target, hybrid, e)
    urdf = fk_kernel.tip_pose(q, generators, revolute, post, axes)
    # hybrid⁻¹ · urdf = [Rᵀ R_u, Rᵀ (p_u − p)], then target times it
    inner = np.zeros((4, 4))
    for i in range(3):
        for j in range(4):
            total = 0.0
            for m in range(3):
                total += hybrid[m, i] * (urdf[m, j] - (hybrid[m, 3] if j == 3 else 0.0))
            inner[i, j] = total
    inner[3, 3] = 1.0
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(4):
            out[i, j] = target[i, 0] * inner[0, j] + target[i, 1] * inner[1, j] + target[i, 2] * inner[2, j]
        out[i, 3] += target[i, 3]
    out[3, 3] = 1.0
    return e, out


@numba.njit(cache=True, nogil=True)
def nearest_copy(q, seed, lower, upper):
    """The row of ``q (k, n)`` whose copy by whole turns within ``[lower, upper]`` (each joint's nearest the
    seed, as ``analytic.fold``) lies nearest ``seed``, that copy ``(n,)``; an empty array where no row has
    one."""
    best, best_d = np.empty(0), math.inf
    n = q.shape[1]
    row = np.empty(n)
    for k in range(q.shape[0]):
        d = 0.0
        ok = True
        for j in range(n):
            v = q[k, j]
            first = math.ceil((lower[j] - 1e-12 - v) / TAU)
            last = math.floor((upper[j] + 1e-12 - v) / TAU)
            if first > last:
                ok = False
                break
            shift = min(max(np.rint((seed[j] - v) / TAU), first), last)
            row[j] = v + TAU * shift
            d += (row[j] - seed[j]) ** 2
        if ok and d < best_d:
            best, best_d = row.copy(), d
    return best


@numba.njit(cache=True, nogil=True)
def chord_step(q, e, generators, revolute, post, axes, lower, upper):
    """``q (6,)`` moved by Newton's chord step for the error ``e (6,)`` on the URDF model's Jacobian at ``q``,
    clipped into ``[lower, upper]`` (``FixedPoint.newton_step``): the 6×6 system by ``lm_kernel.solve``; an empty
    array where a pivot is exactly zero (a singular Jacobian, where ``numpy.linalg.solve`` raises)."""
    jac = fk_kernel.tip_pose_and_jacobian(q, generators, revolute, post, axes)[1]
    step = e.copy()
    if not lm_kernel.solve(jac.copy(), step):
        return np.empty(0)
    out = np.empty(q.shape[0])
    for i in range(q.shape[0]):
        out[i] = min(max(q[i] + step[i], lower[i]), upper[i])
    return out
