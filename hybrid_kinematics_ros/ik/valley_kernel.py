"""The valley trace's step (``valley._onto`` and ``valley._advance``), compiled.

A trace takes 20-40 steps along a valley, each one or more Newton steps back onto it: a URDF pose and Jacobian,
a bordered 6×6 system with two right-hand sides and a few norms. In numpy each step cost ~60 µs of small calls
(an RX160 near-singular target's search traced for 0.8-2.2 ms, and walked its branches past the limits into them
for 2.7 ms more); here a few. The maths is the module's own (``valley._onto``'s docstring); tests check the
kernel against numpy.
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
