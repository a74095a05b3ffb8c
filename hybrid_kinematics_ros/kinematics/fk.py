"""Forward kinematics and geometric Jacobians (numpy) of a :class:`Chain`, batched (torch: ``torch_chain.py``).

Each joint step is one matrix product with the constant block ``[G0 | G1 | G2]`` followed by a weighted
sum (see ``chain.py``), so a batch needs one BLAS call per joint and block, and no per-sample Python loop.
"""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.kinematics import fk_kernel
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.errors import KinematicsError


def check_joints(chain: Chain, q: np.ndarray) -> np.ndarray:
    """``q`` as a float64 ``(B, n)`` array; raises on a wrong joint count or non-finite values."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != chain.dof:
        raise KinematicsError(f"expected joints of shape (B, {chain.dof}) for {chain.dof} joints, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise KinematicsError("joint values contain NaN or infinity")
    return q


CHUNK = 2048  # samples per block: keeps the working set in cache, which makes numpy faster here


def transposed_generators(chain: Chain) -> np.ndarray:
    """``(n, 12, 4)``: row ``(c, j)``, column ``m`` holds ``G_c[m, j]``, for left-multiplying transposed frames."""
    return np.ascontiguousarray(chain.generators.transpose(0, 1, 3, 2).reshape(chain.dof, 12, 4))


def _frames_block(chain: Chain, gt: np.ndarray, a: np.ndarray, b: np.ndarray, out: np.ndarray, every: bool) -> None:
    """Write frames of one block into ``out`` (``(nb, n + 1, 4, 4)`` if ``every`` else ``(nb, 4, 4)``).

    Frames are carried transposed and without their constant last row, as ``X[j, i, b] = T_b[i, j]``
    (``(4, 3, nb)``), so every joint is one gemm ``(12, 4) @ (4, 3 nb)`` plus contiguous vector updates.
    """
    nb = a.shape[0]
    g = chain.generators[0]
    x = (g[0][:3, :, None] + a[:, 0] * g[1][:3, :, None] + b[:, 0] * g[2][:3, :, None]).transpose(1, 0, 2)
    if every:
        out[:, 0, :3] = x.transpose(2, 1, 0)
    for k in range(1, chain.dof):
        y = (gt[k] @ x.reshape(4, 3 * nb)).reshape(3, 4, 3, nb)
        x = y[0] + a[:, k] * y[1] + b[:, k] * y[2]
        if every:
            out[:, k, :3] = x.transpose(2, 1, 0)
    tip = (chain.post.T @ x.reshape(4, 3 * nb)).reshape(4, 3, nb).transpose(2, 1, 0)
    if every:
        out[:, -1, :3] = tip
    else:
        out[:, :3] = tip


def _batched(chain: Chain, q: np.ndarray, every: bool) -> np.ndarray:
    q = check_joints(chain, q)
    a, b = chain.coefficients(q)
    shape = (q.shape[0], chain.dof + 1, 4, 4) if every else (q.shape[0], 4, 4)
    out = np.empty(shape)
    out[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    gt = transposed_generators(chain)
    for s in range(0, q.shape[0], CHUNK):
        _frames_block(chain, gt, a[s : s + CHUNK], b[s : s + CHUNK], out[s : s + CHUNK], every)
    return out


def joint_frames(chain: Chain, q: np.ndarray) -> np.ndarray:
    """Frames of every joint after its motion plus the tip: ``(B, n + 1, 4, 4)`` in the base frame."""
    return _batched(chain, q, every=True)


def fk(chain: Chain, q: np.ndarray) -> np.ndarray:
    """Tip poses ``(B, 4, 4)`` for joints ``(B, n)`` (a 1-D ``q`` is a batch of one)."""
    return _batched(chain, q, every=False)


def fk_single(chain: Chain, q: np.ndarray) -> np.ndarray:
    """Tip pose ``(4, 4)`` of one configuration ``(n,)``: the low-overhead path for services and IK, compiled
    (:mod:`~hybrid_kinematics_ros.kinematics.fk_kernel`). A few configurations ``(k, n)`` give
    ``(k, 4, 4)`` without :func:`fk`'s set-up: the joint factors ``G0 + a G1 + b G2`` in one batched
    product, then their product (``post`` and identities appended to a power of two) as a tree of 3 batched
    matrix products for 6 or 7 joints instead of a chain of 7. Both differ from :func:`fk`'s by rounding only.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:  # contiguous: a strided view would compile the kernel once more
        return fk_kernel.tip_pose(np.ascontiguousarray(q), *chain.kernel_operands)
    tail = chain.single_operands[2]
    factors = joint_factors(chain, q)  # (k, n, 4, 4), the factors' axis first, each a batch over the configurations
    factors = np.concatenate((factors, tail[None].repeat(len(q), 0)), axis=1).swapaxes(0, 1)
    while len(factors) > 1:
        factors = factors[0::2] @ factors[1::2]
    return factors[0]


def joint_factors(chain: Chain, q: np.ndarray) -> np.ndarray:
    """``(…, n, 4, 4)``: each joint's transform ``G0 + a G1 + b G2`` at ``q (…, n)``, in one batched product
    (a few configurations' :func:`fk_single`, the elasto-geometric chain's one-pose path)."""
    flat, ones, _, revolute = chain.single_operands
    a, b = (np.sin(q), 1.0 - np.cos(q)) if revolute else chain.coefficients(q)
    if q.ndim == 1:  # one configuration: np.array of the rows costs less than np.stack
        return (np.array((ones, a, b)).T[:, None] @ flat).reshape(-1, 4, 4)
    coef = np.stack((np.ones_like(q), a, b), axis=-1)[..., None, :]  # (…, n, 1, 3)
    return (coef @ flat).reshape(*q.shape, 4, 4)


def geometric_jacobian(
    z: np.ndarray, lever: np.ndarray, revolute: np.ndarray, all_revolute: bool | None = None
) -> np.ndarray:
    """Geometric Jacobian ``(..., 6, n)``, rows ``[v; ω]`` of the tip origin, from each joint's axis in the
    base frame ``z (..., n, 3)`` and the lever from the joint's origin to the tip ``(..., n, 3)``.

    A revolute joint moves the tip by ``z × lever`` and turns it about ``z``; a prismatic one moves it along
    ``z``. The cross product is written out: ``np.cross``'s overhead dominates on the small arrays of one pose.
    ``all_revolute``: whether every joint is, when the caller knows (it saves a test on one pose's path).
    """
    jac = np.empty((*z.shape[:-2], 6, z.shape[-2]))
    jac[..., 0, :] = z[..., 1] * lever[..., 2] - z[..., 2] * lever[..., 1]
    jac[..., 1, :] = z[..., 2] * lever[..., 0] - z[..., 0] * lever[..., 2]
    jac[..., 2, :] = z[..., 0] * lever[..., 1] - z[..., 1] * lever[..., 0]
    jac[..., 3:, :] = np.swapaxes(z, -1, -2)
    prismatic = ~revolute
    if not all_revolute and prismatic.any():
        jac[..., :3, prismatic] = np.swapaxes(z[..., prismatic, :], -1, -2)
        jac[..., 3:, prismatic] = 0.0
    return jac


def jacobian_from_frames(chain: Chain, frames: np.ndarray, tip: np.ndarray | None = None) -> np.ndarray:
    """Geometric Jacobian ``(..., 6, n)`` from the joint frames ``(..., n + 1, 4, 4)`` of :func:`joint_frames`
    (the tip last), or from ``(..., n, 4, 4)`` and the ``tip (..., 4, 4)``."""
    if tip is None:
        frames, tip = frames[..., :-1, :, :], frames[..., -1, :, :]
    z = np.einsum("...kij,kj->...ki", frames[..., :3, :3], chain.axes)
    lever = tip[..., None, :3, 3] - frames[..., :3, 3]
    return geometric_jacobian(z, lever, chain.revolute)


def fk_and_jacobian(chain: Chain, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    frames = joint_frames(chain, q)
    return frames[:, -1], jacobian_from_frames(chain, frames)


def fk_and_jacobian_single(chain: Chain, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One configuration: tip pose ``(4, 4)`` and geometric Jacobian ``(6, n)`` (the IK inner loop), compiled
    (:mod:`~hybrid_kinematics_ros.kinematics.fk_kernel`)."""
    return fk_kernel.tip_pose_and_jacobian(np.ascontiguousarray(q, dtype=float), *chain.kernel_operands)
