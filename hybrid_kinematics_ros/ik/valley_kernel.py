"""The valley trace's step (``valley._onto`` and ``valley._advance``), compiled.

A trace takes 20-40 steps along a valley, each one or more Newton steps back onto it: a URDF pose and Jacobian,
a bordered 6×6 system with two right-hand sides and a few norms. In numpy each step is mostly the overhead of
small calls, and a search's traces take milliseconds of a request's budget; compiled, a fraction of that. The
maths is the module's own (``valley._onto``'s docstring); tests check the kernel against numpy.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hybrid_kinematics_ros.ik import lm_kernel
from hybrid_kinematics_ros.kinematics import fk_kernel


@numba.njit(cache=True, nogil=True)
def onto(pose, x, border, v, generators, revolute, post, axes):
    """One Newton step from ``x (n,)`` back onto the valley of the URDF ``pose (4, 4)``, along no ``border (n,)``:
    the point, the (unit) weak motion there, turned from ``v (n,)``, and the step's length; the step's length
    is inf where the bordered matrix is singular."""
    n = x.shape[0]
    jac = fk_kernel.tip_pose_and_jacobian(x, generators, revolute, post, axes)
    T, J = jac[0], jac[1]
    e = np.empty(6)
    lm_kernel.error6(pose, T, e)
    a = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            total = border[i] * border[j]
            for r in range(6):
                total += J[r, i] * J[r, j]
            a[i, j] = total
    step = np.empty(n)
    for i in range(n):
        total = 0.0
        for r in range(6):
            total += J[r, i] * e[r]
        step[i] = total
    w = v.copy()
    if not (lm_kernel.solve(a.copy(), step) and lm_kernel.solve(a, w)):
        return x.copy(), v.copy(), math.inf
    moved = math.sqrt(np.sum(step * step))
    return x + step, w / math.sqrt(np.sum(w * w)), moved


@numba.njit(cache=True, nogil=True)
def advance(pose, q, v, step, turn, halvings, generators, revolute, post, axes):
    """The next point of the valley from its point ``q`` along its weak motion ``v``, and the weak motion there:
    ``step`` on, halved where a Newton step back onto the valley is longer than ``turn`` times the step, up to
    ``halvings`` times. The third value: False where no step short enough keeps to it."""
    h = step
    for _ in range(halvings + 1):
        x, w, moved = onto(pose, q + h * v, v, v, generators, revolute, post, axes)
        if moved < turn * h:
            return x, w, True
        h /= 2.0
    return q.copy(), v.copy(), False


@numba.njit(cache=True, nogil=True)
def _det(a):
    """The determinant of a small square ``a`` (overwritten) by elimination with partial pivoting."""
    n = a.shape[0]
    det = 1.0
    for k in range(n):
        if lm_kernel.pivot(a, k) != k:
            det = -det
        if a[k, k] == 0.0:
            return 0.0
        det *= a[k, k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for c in range(k, n):
                a[i, c] -= f * a[k, c]
    return det


@numba.njit(cache=True, nogil=True)
def settle_step(target, T, q, j, lower, upper, generators, revolute, post, axes):
    """``valley.settle``'s chord step of one row: the joints ``q (n,)`` but ``j`` moved by the least-squares step
    that removes the error of the pose ``T`` (the hybrid pose at ``q``) to ``target`` on the URDF Jacobian's
    other columns, each wrapped by 2π where it passed a limit and that lands inside (``lm.project``), then
    clipped; ``q`` itself where the step's matrix is singular."""
    n = q.shape[0]
    J = fk_kernel.tip_pose_and_jacobian(q, generators, revolute, post, axes)[1]
    e = np.empty(6)
    lm_kernel.error6(target, T, e)
    cols = np.empty(n - 1, dtype=np.int64)
    m = 0
    for c in range(n):
        if c != j:
            cols[m] = c
            m += 1
    a = np.empty((m, m))
    b = np.empty(m)
    for i in range(m):
        for k in range(m):
            total = 1e-12 if i == k else 0.0
            for r in range(6):
                total += J[r, cols[i]] * J[r, cols[k]]
            a[i, k] = total
        total = 0.0
        for r in range(6):
            total += J[r, cols[i]] * e[r]
        b[i] = total
    out = q.copy()
    if not lm_kernel.solve(a, b):
        return out
    for i in range(m):
        out[cols[i]] += b[i]
    lm_kernel._project(out, lower, upper, revolute)
    out[j] = q[j]  # held, as it was (a bracket across a seam lies on its first end's turn)
    return out


@numba.njit(cache=True, nogil=True)
def along_one(target, T, q, j, generators, revolute, post, axes):
    """``valley.along`` of one row: the error of the pose ``T`` at ``q`` to ``target`` along the unit normal
    to the URDF Jacobian's columns but ``j``'s (its signed 5×5 minors, as ``valley._normal``), and the error
    left across it."""
    J = fk_kernel.tip_pose_and_jacobian(q, generators, revolute, post, axes)[1]
    e = np.empty(6)
    lm_kernel.error6(target, T, e)
    n = q.shape[0]
    u = np.empty(6)
    minor = np.empty((5, 5))
    for skip in range(6):
        row = 0
        for r in range(6):
            if r == skip:
                continue
            col = 0
            for c in range(n):
                if c != j:
                    minor[row, col] = J[r, c]
                    col += 1
            row += 1
        u[skip] = (1.0 if skip % 2 == 0 else -1.0) * _det(minor)
    norm = max(math.sqrt(np.sum(u * u)), 1e-300)
    along = 0.0
    for r in range(6):
        u[r] /= norm
        along += u[r] * e[r]
    across = 0.0
    for r in range(6):
        across += (e[r] - along * u[r]) ** 2
    return along, math.sqrt(across)
