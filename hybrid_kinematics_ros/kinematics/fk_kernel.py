"""One configuration's tip pose, and its geometric Jacobian, compiled: the IK's and the services' inner loop.

The same product as :func:`fk.fk` (``A_0(q_0) ··· A_{n-1}(q_{n-1}) · post``, each factor
``G0 + a G1 + b G2``; see ``chain.py``), joint by joint in one call, where numpy would make about twenty
calls, each costing more than the arithmetic. The elasto-geometric chain's one pose
(:class:`~hybrid_kinematics_ros.kinematics.elastic.ElasticChain`: gravity torques on the rigid frames, the
joints' deflections and the links' bending, then the frames again) is one call too.
The association of the products is the plain left-to-right one, so the poses agree with the batched numpy
code's to rounding (~1e-15), not bit for bit. Compiled on first use and cached on disk, as
:mod:`~hybrid_kinematics_ros.model.mlp_kernel`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np


class ChainOperands(NamedTuple):
    """The rigid chain as the compiled kernels take it after the joints, named in their parameters' order
    (:attr:`Chain.kernel_operands`; every kernel of the IK that takes the chain ends with these)."""

    generators: np.ndarray  # (n, 3, 4, 4): each joint's factor G0 + a G1 + b G2
    revolute: np.ndarray  # (n,) bool
    post: np.ndarray  # (4, 4): the last joint's frame to the tip
    axes: np.ndarray  # (n, 3): each joint's axis in its own frame


class ElasticOperands(NamedTuple):
    """:func:`elastic_pose`'s operands after the joints, named in its parameters' order: the chain's, the loads,
    gravity and the stage's parameters (the optional ones as zeros)."""

    generators: np.ndarray
    revolute: np.ndarray
    post: np.ndarray
    axes: np.ndarray
    segment_com: np.ndarray  # (n, 3) m, each segment's centre of mass in its joint's frame
    mass: np.ndarray  # (n + 1,) kg: each segment's, then the payload's
    beyond: np.ndarray  # (n,) kg: the mass each joint carries
    payload_com: np.ndarray  # (3,) m, tip frame
    gravity: np.ndarray  # (3,) m/s², base frame
    compliance: np.ndarray  # (n,) rad per N·m
    cubic_ratio: float
    torque_ref: float  # N·m
    cubic_compliance: np.ndarray  # (n,)
    signed_compliance: np.ndarray  # (n,)
    bending: np.ndarray  # (n, 3)
    bends: bool  # whether any link bends


@numba.njit(cache=True, nogil=True)
def _frames(q, generators, revolute, bends, frames):
    """Each joint's frame after its motion into ``frames (n, 4, 4)``: the prefix products of the factors, each
    factor's rotation times the joint's bend ``bends[k] (3, 3)`` where ``bends`` has ``n`` rows."""
    n = q.shape[0]
    bent = bends.shape[0] == n
    a_k = np.empty((4, 4))
    for k in range(n):
        if revolute[k]:
            a, b = math.sin(q[k]), 1.0 - math.cos(q[k])
        else:
            a, b = q[k], 0.0
        for i in range(4):
            for j in range(4):
                a_k[i, j] = generators[k, 0, i, j] + a * generators[k, 1, i, j] + b * generators[k, 2, i, j]
        if bent:
            for i in range(3):
                r0, r1, r2 = a_k[i, 0], a_k[i, 1], a_k[i, 2]
                for j in range(3):
                    a_k[i, j] = r0 * bends[k, 0, j] + r1 * bends[k, 1, j] + r2 * bends[k, 2, j]
        if k == 0:
            frames[0] = a_k
            continue
        for i in range(4):
            for j in range(4):
                frames[k, i, j] = (
                    frames[k - 1, i, 0] * a_k[0, j]
                    + frames[k - 1, i, 1] * a_k[1, j]
                    + frames[k - 1, i, 2] * a_k[2, j]
                    + frames[k - 1, i, 3] * a_k[3, j]
                )


@numba.njit(cache=True, nogil=True)
def _times(t, post):
    out = np.zeros((4, 4))
    out[3, 3] = 1.0
    for i in range(3):
        for j in range(4):
            out[i, j] = t[i, 0] * post[0, j] + t[i, 1] * post[1, j] + t[i, 2] * post[2, j] + t[i, 3] * post[3, j]
    return out


@numba.njit(cache=True, nogil=True)
def _jacobian(frames, tip, axes, revolute, bends):
    """The geometric Jacobian ``(6, n)``, rows ``[v; ω]`` as :func:`fk.geometric_jacobian` has them: joint k
    turns about its axis in its frame before bending, ``R_k bend_kᵀ axis_k`` (``bends`` with ``n`` rows)."""
    n = frames.shape[0]
    bent = bends.shape[0] == n
    jac = np.zeros((6, n))
    for k in range(n):
        ax, ay, az = axes[k, 0], axes[k, 1], axes[k, 2]
        if bent:
            ax, ay, az = (
                bends[k, 0, 0] * axes[k, 0] + bends[k, 1, 0] * axes[k, 1] + bends[k, 2, 0] * axes[k, 2],
                bends[k, 0, 1] * axes[k, 0] + bends[k, 1, 1] * axes[k, 1] + bends[k, 2, 1] * axes[k, 2],
                bends[k, 0, 2] * axes[k, 0] + bends[k, 1, 2] * axes[k, 1] + bends[k, 2, 2] * axes[k, 2],
            )
        z = np.empty(3)
        for i in range(3):
            z[i] = frames[k, i, 0] * ax + frames[k, i, 1] * ay + frames[k, i, 2] * az
        if revolute[k]:
            lx, ly, lz = tip[0, 3] - frames[k, 0, 3], tip[1, 3] - frames[k, 1, 3], tip[2, 3] - frames[k, 2, 3]
            jac[0, k] = z[1] * lz - z[2] * ly
            jac[1, k] = z[2] * lx - z[0] * lz
            jac[2, k] = z[0] * ly - z[1] * lx
            for i in range(3):
                jac[3 + i, k] = z[i]
        else:
            for i in range(3):
                jac[i, k] = z[i]
    return jac


@numba.njit(cache=True, nogil=True)
def tip_pose(q, generators, revolute, post, axes):
    """The tip pose ``(4, 4)`` at joints ``q (n,)``."""
    frames = np.empty((q.shape[0], 4, 4))
    _frames(q, generators, revolute, np.empty((0, 3, 3)), frames)
    return _times(frames[-1], post)


@numba.njit(cache=True, nogil=True)
def tip_pose_and_jacobian(q, generators, revolute, post, axes):
    """The tip pose ``(4, 4)`` and the geometric Jacobian ``(6, n)``."""
    frames = np.empty((q.shape[0], 4, 4))
    none = np.empty((0, 3, 3))
    _frames(q, generators, revolute, none, frames)
    tip = _times(frames[-1], post)
    return tip, _jacobian(frames, tip, axes, revolute, none)


@numba.njit(cache=True, nogil=True)
def cyclic_errors(q, coefficients):
    """The joints' cyclic errors ``(n,)`` at one configuration: ``Σ_f a sin(f q) + b cos(f q)`` over harmonics
    ``f = 1 … K`` of ``coefficients (n, K, 2)`` (a, b), each joint's harmonics by the angle-addition recurrence
    from one sine and cosine (rounding ~K·1e-16 relative). The numpy twin is the stage's batch path
    (``ElasticChain._joint_errors``), several times slower for one pose."""
    n, harmonics = coefficients.shape[0], coefficients.shape[1]
    out = np.zeros(n)
    for j in range(n):
        s1, c1 = math.sin(q[j]), math.cos(q[j])
        s, c = s1, c1
        total = 0.0
        for k in range(harmonics):
            total += coefficients[j, k, 0] * s + coefficients[j, k, 1] * c
            s, c = s * c1 + c * s1, c * c1 - s * s1
        out[j] = total
    return out


@numba.njit(cache=True, nogil=True)
def rotation(w):
    """``exp(ŵ)`` (Rodrigues) of one rotation vector ``(3,)``: :func:`se3.exp_so3` inside the kernel, which
    cannot call numpy's; test_elastic checks the kernel's pose against the batch, which uses that one."""
    t = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if t < 1e-8:
        a, b = 1.0 - t * t / 6.0, 0.5 - t * t / 24.0
    else:
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / (t * t)
    x, y, z = w[0], w[1], w[2]
    r = np.empty((3, 3))
    r[0, 0] = 1.0 - b * (y * y + z * z)
    r[1, 1] = 1.0 - b * (x * x + z * z)
    r[2, 2] = 1.0 - b * (x * x + y * y)
    r[0, 1], r[1, 0] = b * x * y - a * z, b * x * y + a * z
    r[0, 2], r[2, 0] = b * x * z + a * y, b * x * z - a * y
    r[1, 2], r[2, 1] = b * y * z - a * x, b * y * z + a * x
    return r


@numba.njit(cache=True, nogil=True)
def elastic_pose(
    q_eff,
    generators,
    revolute,
    post,
    axes,
    segment_com,
    mass,
    beyond,
    payload_com,
    gravity,
    compliance,
    cubic_ratio,
    torque_ref,
    cubic_compliance,
    signed_compliance,
    bending,
    bends,
    jacobian,
):
    """The elasto-geometric chain's tip pose ``(4, 4)`` at the joints ``q_eff (n,)`` its rigid links reach
    before deflection (zero offsets and joint errors applied), and its Jacobian ``(6, n)`` (zeros unless
    ``jacobian``) with the deflections held (``ElasticChain.fk_and_jacobian``'s approximation, before the
    joint errors' slopes). ``mass (n + 1,)``: the segments' and the payload's; ``beyond (n,)``: the mass beyond
    each joint; ``bends``: whether the links bend (``bending (n, 3)`` rad/Nm)."""
    n = q_eff.shape[0]
    frames = np.empty((n, 4, 4))
    none = np.empty((0, 3, 3))
    _frames(q_eff, generators, revolute, none, frames)
    tip = _times(frames[-1], post)
    # first moments beyond each joint, about its origin: Σ_i≥j m_i (c_i − o_j), the payload's last
    first = np.zeros((n, 3))
    run = np.empty(3)
    for i in range(3):
        run[i] = mass[n] * (
            tip[i, 0] * payload_com[0] + tip[i, 1] * payload_com[1] + tip[i, 2] * payload_com[2] + tip[i, 3]
        )
    for k in range(n - 1, -1, -1):
        for i in range(3):
            c = (
                frames[k, i, 0] * segment_com[k, 0]
                + frames[k, i, 1] * segment_com[k, 1]
                + frames[k, i, 2] * segment_com[k, 2]
                + frames[k, i, 3]
            )
            run[i] += mass[k] * c
            first[k, i] = run[i] - beyond[k] * frames[k, i, 3]
    q_def = q_eff.copy()
    torque = np.empty(n)
    for k in range(n):
        ax = np.empty(3)
        for i in range(3):
            ax[i] = frames[k, i, 0] * axes[k, 0] + frames[k, i, 1] * axes[k, 1] + frames[k, i, 2] * axes[k, 2]
        if revolute[k]:  # axis · (first × g)
            fx, fy, fz = first[k, 0], first[k, 1], first[k, 2]
            mx = fy * gravity[2] - fz * gravity[1]
            my = fz * gravity[0] - fx * gravity[2]
            mz = fx * gravity[1] - fy * gravity[0]
            tau = ax[0] * mx + ax[1] * my + ax[2] * mz
        else:  # a prismatic joint carries the weight beyond it along its axis
            tau = beyond[k] * (ax[0] * gravity[0] + ax[1] * gravity[1] + ax[2] * gravity[2])
        torque[k] = tau
        ratio = tau / torque_ref
        q_def[k] += (
            compliance[k] * tau / (1.0 + cubic_ratio * ratio * ratio)
            + cubic_compliance[k] * tau * tau * tau
            + signed_compliance[k] * abs(tau)
        )
    rotations = np.empty((n, 3, 3)) if bends else none
    if bends:
        w = np.empty(3)
        for k in range(n):
            for i in range(3):
                w[i] = torque[k] * bending[k, i]
            rotations[k] = rotation(w)
    _frames(q_def, generators, revolute, rotations, frames)
    tip = _times(frames[-1], post)
    jac = _jacobian(frames, tip, axes, revolute, rotations) if jacobian else np.zeros((6, n))
    return tip, jac
