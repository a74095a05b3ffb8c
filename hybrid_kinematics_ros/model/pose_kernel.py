"""The hybrid pose of one configuration in one compiled call: the parametric stage, then both residual nets.

Every FK service call and every round of the IK's fixed point asks for one pose. Done in steps (the stage's
joint errors, its kernel, each net's kernel, the joint-1 turn of each residual, the rotation), most of a
pose's time is the Python between the kernels, the more so with cold caches (refilled on every request, as
a node's are); in one call, a fraction of it. The maths is
the steps' own, called from here: ``fk_kernel.cyclic_errors`` and ``elastic_pose`` (or ``tip_pose`` for a
stage without compliance), ``mlp_kernel.mlp_values``, and the turn and the rotation as ``model/nets.py``
and ``HybridModel.correct`` write them; tests check the pose against the batch path.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hybrid_kinematics_ros.kinematics import fk_kernel
from hybrid_kinematics_ros.model import mlp_kernel


@numba.njit(cache=True, nogil=True)
def _turned(r, angle, axis):
    """``r (3,)`` turned by ``angle`` about the unit ``axis``: ``AxisTurn.apply`` of one vector."""
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = r[0], r[1], r[2]
    kx, ky, kz = axis[0], axis[1], axis[2]
    along = (1.0 - c) * (kx * x + ky * y + kz * z)
    out = np.empty(3)
    out[0] = c * x + s * (ky * z - kz * y) + along * kx
    out[1] = c * y + s * (kz * x - kx * z) + along * ky
    out[2] = c * z + s * (kx * y - ky * x) + along * kz
    return out


@numba.njit(cache=True, nogil=True)
def _residual(x, net):
    """One net's residual ``(3,)`` at its input ``x (k,)`` (:class:`FastResidual`'s operands ``net``)."""
    center, half_span, n_joints, sincos, flat, layout, codes, members, scale, mean, axis, turn = net
    r = mlp_kernel.mlp_values(
        x.reshape(1, -1), center, half_span, n_joints, sincos, flat, layout, codes, members, scale, mean
    )[0]
    return _turned(r, x[0], axis) if turn else r


@numba.njit(cache=True, nogil=True)
def hybrid_pose(reached, x, offset, coefficients, elastic, stage, position, p_net, orientation, o_net):
    """The hybrid tip pose ``(4, 4)``: the stage at the joints ``reached (n,)`` (after backlash), its zero
    offsets ``offset (n,)`` and cyclic errors ``coefficients (n, K, 2)`` applied, through ``elastic_pose``
    with ``stage`` (``ElasticChain._kernel_operands``) when ``elastic``, else the rigid chain's ``tip_pose``;
    then the position net (``p_net``, when ``position``) adds its residual to the position and the
    orientation net's rotation vector (``o_net``, when ``orientation``) turns the rotation, both at the nets'
    input ``x (k,)`` (the joints, then any condition channels)."""
    q_eff = reached + offset + fk_kernel.cyclic_errors(reached, coefficients)
    generators, revolute, post, axes = stage[0], stage[1], stage[2], stage[3]
    if elastic:
        tip = fk_kernel.elastic_pose(q_eff, *stage, False)[0]
    else:
        tip = fk_kernel.tip_pose(q_eff, generators, revolute, post, axes)
    if position:
        dp = _residual(x, p_net)
        for i in range(3):
            tip[i, 3] += dp[i]
    if orientation:
        r = fk_kernel.rotation(_residual(x, o_net))
        turned = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                turned[i, j] = r[i, 0] * tip[0, j] + r[i, 1] * tip[1, j] + r[i, 2] * tip[2, j]
        tip[:3, :3] = turned
    return tip
