"""One configuration's tip pose, and its geometric Jacobian, compiled: the IK's and the services' inner loop.

The same product as :func:`fk.fk` (``A_0(q_0) ··· A_{n-1}(q_{n-1}) · post``, each factor
``G0 + a G1 + b G2``; see ``chain.py``), joint by joint in one call, where :func:`fk.fk_single` makes about
twenty numpy calls (a UR10's pose and Jacobian: 4 against 23 µs). The association of the products is the
plain left-to-right one, so the pose agrees with :func:`fk.fk`'s to rounding (~1e-15), not bit for bit.
Compiled on first use and cached on disk, as :mod:`~hybrid_kinematics_ros.model.mlp_kernel`.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _product(q, generators, revolute, post, axes, z, origins):
    """The tip pose ``(4, 4)``; each joint's axis in the base frame into ``z (n, 3)`` and its frame's origin
    into ``origins (n, 3)`` when those have ``n`` rows (else they are left alone)."""
    n = q.shape[0]
    keep = z.shape[0] == n
    t = np.eye(4)
    a_k = np.empty((4, 4))
    out = np.empty((4, 4))
    for k in range(n):
        if revolute[k]:
            a, b = math.sin(q[k]), 1.0 - math.cos(q[k])
        else:
            a, b = q[k], 0.0
        for i in range(4):
            for j in range(4):
                a_k[i, j] = generators[k, 0, i, j] + a * generators[k, 1, i, j] + b * generators[k, 2, i, j]
        for i in range(3):  # the bottom row stays (0, 0, 0, 1)
            for j in range(4):
                out[i, j] = t[i, 0] * a_k[0, j] + t[i, 1] * a_k[1, j] + t[i, 2] * a_k[2, j] + t[i, 3] * a_k[3, j]
        for i in range(3):
            for j in range(4):
                t[i, j] = out[i, j]
        if keep:
            for i in range(3):
                z[k, i] = t[i, 0] * axes[k, 0] + t[i, 1] * axes[k, 1] + t[i, 2] * axes[k, 2]
                origins[k, i] = t[i, 3]
    tip = np.eye(4)
    for i in range(3):
        for j in range(4):
            tip[i, j] = t[i, 0] * post[0, j] + t[i, 1] * post[1, j] + t[i, 2] * post[2, j] + t[i, 3] * post[3, j]
    return tip


@numba.njit(cache=True, nogil=True)
def tip_pose(q, generators, revolute, post, axes):
    """The tip pose ``(4, 4)`` at joints ``q (n,)``."""
    none = np.empty((0, 3))
    return _product(q, generators, revolute, post, axes, none, none)


@numba.njit(cache=True, nogil=True)
def tip_pose_and_jacobian(q, generators, revolute, post, axes):
    """The tip pose ``(4, 4)`` and the geometric Jacobian ``(6, n)``, rows ``[v; ω]``, as
    :func:`fk.geometric_jacobian` has them."""
    n = q.shape[0]
    z, origins = np.empty((n, 3)), np.empty((n, 3))
    tip = _product(q, generators, revolute, post, axes, z, origins)
    jac = np.zeros((6, n))
    for k in range(n):
        if revolute[k]:
            lx, ly, lz = tip[0, 3] - origins[k, 0], tip[1, 3] - origins[k, 1], tip[2, 3] - origins[k, 2]
            jac[0, k] = z[k, 1] * lz - z[k, 2] * ly
            jac[1, k] = z[k, 2] * lx - z[k, 0] * lz
            jac[2, k] = z[k, 0] * ly - z[k, 1] * lx
            for i in range(3):
                jac[3 + i, k] = z[k, i]
        else:
            for i in range(3):
                jac[i, k] = z[k, i]
    return tip, jac
