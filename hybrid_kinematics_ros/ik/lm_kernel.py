"""Levenberg-Marquardt on the URDF model, compiled: ``lm.LM.solve``'s loop, its rules and constants, in one call.

The classical stage, the restarts from the seed table, the polish of least-squares answers and the URDF pass
of a trajectory all run LM on the URDF model, often from dozens of seeds within one request's budget (hundreds
next to a joint limit with the wrist straight). In numpy an iteration is mostly the overhead of small calls;
compiled, a fraction of it. numba has no clock, so the loop runs ``steps`` iterations at most per call and
returns its state; ``lm.LM.solve`` checks the deadline between calls.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hybrid_kinematics_ros.kinematics import fk_kernel

RUNNING, DONE = 0, 1  # the state a call ends in: it may go on (steps used up), or it has stopped


@numba.njit(cache=True, nogil=True)
def error6(target, T, out):
    """``se3.error6`` into ``out (6,)``; near π (beyond 3 rad) the axis from the rotation's symmetric part, as
    scipy's rotation vector does there."""
    for i in range(3):
        out[i] = target[i, 3] - T[i, 3]
    r = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r[i, j] = target[i, 0] * T[j, 0] + target[i, 1] * T[j, 1] + target[i, 2] * T[j, 2]
    x, y, z = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    s = 0.5 * math.sqrt(x * x + y * y + z * z)
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    angle = math.atan2(s, c)
    if angle <= 3.0:
        k = 0.5 if angle < 1e-9 else angle / (2.0 * s)
        out[3], out[4], out[5] = k * x, k * y, k * z
        return
    # (R + Rᵀ)/2 − cos θ I = (1 − cos θ) k kᵀ: the axis from its largest diagonal's column, signed by R − Rᵀ
    m = 0
    for i in range(1, 3):
        if r[i, i] > r[m, m]:
            m = i
    axis = np.empty(3)
    for i in range(3):
        axis[i] = 0.5 * (r[i, m] + r[m, i]) - (c if i == m else 0.0)
    norm = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    sign = 1.0 if axis[0] * x + axis[1] * y + axis[2] * z >= 0.0 else -1.0
    for i in range(3):
        out[3 + i] = sign * angle * axis[i] / norm


@numba.njit(cache=True, nogil=True)
def _project(q, lower, upper, revolute):
    """``lm.project`` of one configuration, in place."""
    two_pi = 2.0 * math.pi
    for j in range(q.shape[0]):
        v = q[j]
        if revolute[j] and v > upper[j] and v - two_pi >= lower[j]:
            v -= two_pi
        if revolute[j] and v < lower[j] and v + two_pi <= upper[j]:
            v += two_pi
        q[j] = min(max(v, lower[j]), upper[j])


@numba.njit(cache=True, nogil=True)
def pivot(a, k):
    """Partial pivoting of a small square ``a`` at column ``k``: row ``k`` swapped with the row at or below it
    whose entry in that column is largest in magnitude; that row's index."""
    p = k
    for i in range(k + 1, a.shape[0]):
        if abs(a[i, k]) > abs(a[p, k]):
            p = i
    if p != k:
        for j in range(a.shape[1]):
            a[k, j], a[p, j] = a[p, j], a[k, j]
    return p


@numba.njit(cache=True, nogil=True)
def solve(a, b):
    """``a x = b`` for a small square ``a`` by Gaussian elimination with partial pivoting (both overwritten);
    False where a pivot is exactly zero."""
    n = b.shape[0]
    for k in range(n):
        p = pivot(a, k)
        if a[k, k] == 0.0:
            return False
        if p != k:
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k, n):
                a[i, j] -= f * a[k, j]
            b[i] -= f * b[k]
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total -= a[i, j] * b[j]
        b[i] = total / a[i, i]
    return True


@numba.njit(cache=True, nogil=True)
def lm_steps(
    target,
    q,
    state,
    steps,
    lower,
    upper,
    revolute,
    tol_m,
    tol_rad,
    max_iterations,
    stop_crawl,
    constants,
    generators,
    chain_revolute,
    post,
    axes,
):
    """Up to ``steps`` iterations of ``lm.LM.solve`` from ``q (n,)`` (in place, projected into the limits on the
    first call) on the chain's kernel operands. ``state (6,)``: λ, iterations, slow steps, the crawl window's
    cost, whether started, and (out) RUNNING or DONE. ``constants``: STALL_ITERATIONS, STALL_COST,
    CRAWL_WINDOW, CRAWL_GAIN, FLOOR_RATIO, FLOOR_STEPS, LAMBDA_DOWN, LAMBDA_UP, LAMBDA_MIN, LAMBDA_MAX.
    Returns the pose error ``(6,)`` at ``q``."""
    stall_iterations, stall_cost, crawl_window, crawl_gain = constants[0], constants[1], constants[2], constants[3]
    floor_ratio, floor_steps, down, up, lam_min, lam_max = (
        constants[4],
        constants[5],
        constants[6],
        constants[7],
        constants[8],
        constants[9],
    )
    n = q.shape[0]
    if state[4] == 0.0:
        _project(q, lower, upper, revolute)
        state[4] = 1.0
    T, J = fk_kernel.tip_pose_and_jacobian(q, generators, chain_revolute, post, axes)
    e = np.empty(6)
    error6(target, T, e)
    cost = 0.0
    for i in range(6):
        cost += e[i] * e[i]
    lam, iterations, slow, window_cost = state[0], int(state[1]), int(state[2]), state[3]
    if iterations == 0:
        window_cost = cost
    e_new = np.empty(6)
    jtj = np.empty((n, n))
    rhs = np.empty(n)
    q_new = np.empty(n)
    done = False
    used = 0
    while iterations < max_iterations:
        if (
            math.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2) <= tol_m
            and math.sqrt(e[3] ** 2 + e[4] ** 2 + e[5] ** 2) <= tol_rad
        ):
            done = True
            break
        if iterations >= stall_iterations and cost > stall_cost:
            done = True
            break
        if stop_crawl and iterations and iterations % crawl_window == 0:
            if cost < stall_cost and cost * crawl_gain > window_cost:
                done = True
                break
            window_cost = cost
        if used == steps:
            break
        used += 1
        iterations += 1
        for a in range(n):
            total = 0.0
            for k in range(6):
                total += J[k, a] * e[k]
            rhs[a] = total
            for b in range(n):
                total = 0.0
                for k in range(6):
                    total += J[k, a] * J[k, b]
                jtj[a, b] = total
        diagonal = np.empty(n)
        for a in range(n):
            diagonal[a] = jtj[a, a]
        for a in range(n):
            jtj[a, a] += lam * (diagonal[a] + 1e-9)
        if not solve(jtj, rhs):  # numpy's solve raises there: the Python loop would stop with an error
            done = True
            break
        for a in range(n):
            q_new[a] = q[a] + rhs[a]
        _project(q_new, lower, upper, revolute)
        T_new, J_new = fk_kernel.tip_pose_and_jacobian(q_new, generators, chain_revolute, post, axes)
        error6(target, T_new, e_new)
        cost_new = 0.0
        for i in range(6):
            cost_new += e_new[i] * e_new[i]
        if cost_new < cost:
            slow = slow + 1 if cost_new > floor_ratio * cost and cost_new < stall_cost else 0
            q[:] = q_new
            J = J_new
            e[:] = e_new
            cost = cost_new
            lam = max(lam / down, lam_min)
            if slow >= floor_steps:
                done = True
                break
        else:
            lam = lam * up
            if lam >= lam_max:
                done = True
                break
    if iterations >= max_iterations:
        done = True
    state[0], state[1], state[2], state[3] = lam, iterations, slow, window_cost
    state[5] = 1.0 if done else 0.0
    return e
