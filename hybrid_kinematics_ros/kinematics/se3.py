"""SE(3) maths in one convention: 4x4 homogeneous matrices, (position, quaternion xyzw), batch first, SI units.

Rotations go through scipy's ``Rotation``; only the tiny operations on hot paths are written out here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics.errors import KinematicsError


def matrix_from_pose(position: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """``(B, 4, 4)`` from positions ``(B, 3)`` and unit quaternions ``(B, 4)`` in xyzw order."""
    position = np.atleast_2d(np.asarray(position, dtype=float))
    quat = np.atleast_2d(np.asarray(quat_xyzw, dtype=float))
    norms = np.linalg.norm(quat, axis=1)
    if not np.all(np.abs(norms - 1.0) < 1e-6):
        bad = int(np.argmax(np.abs(norms - 1.0)))
        raise KinematicsError(f"quaternion {bad} has norm {norms[bad]:.6g}; orientations must be unit quaternions")
    out = np.zeros((len(position), 4, 4))
    out[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
    out[:, :3, 3] = position
    out[:, 3, 3] = 1.0
    return out


def pose_from_matrix(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(B, 3)`` and quaternions ``(B, 4)`` xyzw (scalar part non-negative) of ``(B, 4, 4)``."""
    t = np.asarray(t, dtype=float).reshape(-1, 4, 4)
    quat = Rotation.from_matrix(t[:, :3, :3]).as_quat()
    quat *= np.where(quat[:, 3:4] < 0, -1.0, 1.0)
    return t[:, :3, 3].copy(), quat


def quat_from_rotation(r: np.ndarray) -> np.ndarray:
    """xyzw quaternion (scalar part non-negative) of one rotation matrix, by Shepperd's method.

    scipy's ``Rotation`` has a large fixed cost per call at batch size 1; this path serves single poses in
    nodes, in Python floats (each numpy call on a scalar costs more than the arithmetic). Tested against scipy.
    """
    return np.array(quat_of_rows(np.asarray(r, dtype=float)[:3, :3].tolist()))


def quat_of_rows(rows: list[list[float]]) -> tuple[float, float, float, float]:
    """:func:`quat_from_rotation` of a rotation (or pose) matrix given as nested lists (``T.tolist()``), in
    Python floats only: a service converts one pose with a single numpy call."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = (row[:3] for row in rows[:3])
    trace = m00 + m11 + m22
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    scale = (-1.0 if q[3] < 0.0 else 1.0) / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return scale * q[0], scale * q[1], scale * q[2], scale * q[3]


def matrix_of_pose_one(position: Sequence[float], quat_xyzw: Sequence[float]) -> np.ndarray:
    """:func:`matrix_from_pose` of one position and unit quaternion, ``(4, 4)``, from Python floats with one
    numpy call (a service's request, where scipy's Rotation would cost more than the rest)."""
    x, y, z, w = quat_xyzw
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    return np.array(
        (
            (1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy), position[0]),
            (2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx), position[1]),
            (2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy), position[2]),
            (0.0, 0.0, 0.0, 1.0),
        )
    )


def from_rotvec(position: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``(B, 4, 4)`` from positions and axis-angle vectors (the exponential map of SO(3) with a translation)."""
    position = np.atleast_2d(np.asarray(position, dtype=float))
    out = np.zeros((len(position), 4, 4))
    out[:, :3, :3] = Rotation.from_rotvec(np.atleast_2d(rotvec)).as_matrix()
    out[:, :3, 3] = position
    out[:, 3, 3] = 1.0
    return out


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``(..., 3, 3)`` of vectors ``(..., 3)``: ``skew(w) @ r == w × r``."""
    w = np.asarray(w, dtype=float)
    k = np.zeros((*w.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return k


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (Rodrigues, exact near zero).

    scipy's ``Rotation`` gives the same, but its set-up per call costs too much for one pose; one vector takes
    a path of Python floats (several times faster than the array path with a batch of one).
    """
    w = np.asarray(w, dtype=float)
    if w.shape == (3,):
        return _exp_so3_one(*w.tolist())
    theta = np.sqrt(np.sum(w * w, axis=-1))[..., None, None]
    moving = theta > 0.0
    safe = np.where(moving, theta, 1.0)
    a = np.where(moving, np.sin(safe) / safe, 1.0)  # sin θ / θ
    half = np.sin(0.5 * safe) / safe
    b = np.where(moving, 2.0 * half * half, 0.5)  # (1 − cos θ) / θ² = 2 sin²(θ/2) / θ², without cancellation
    k = skew(w)
    return np.eye(3) + a * k + b * (k @ k)


def _exp_so3_one(x: float, y: float, z: float) -> np.ndarray:
    """:func:`exp_so3` of one vector."""
    t2 = x * x + y * y + z * z
    if t2 == 0.0:
        return np.eye(3)
    t = math.sqrt(t2)
    half = math.sin(0.5 * t) / t
    return rodrigues_one(x, y, z, math.sin(t) / t, 2.0 * half * half)


def rodrigues_one(x: float, y: float, z: float, a: float, b: float) -> np.ndarray:
    """``I + a K + b K²`` for ``K`` the skew matrix of ``(x, y, z)``, written out in Python floats with
    ``K² = w wᵀ − θ² I``: the one-vector form of the exponential and of its Jacobians, which differ in
    ``a`` and ``b`` only."""
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    return np.array(
        [
            [1.0 - b * (y * y + z * z), bxy - az, bxz + ay],
            [bxy + az, 1.0 - b * (x * x + z * z), byz - ax],
            [bxz - ay, byz + ax, 1.0 - b * (x * x + y * y)],
        ]
    )


def rotvec(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vectors ``(B, 3)`` of rotation matrices ``(B, 3, 3)`` (the logarithm of SO(3))."""
    return Rotation.from_matrix(np.asarray(rotation).reshape(-1, 3, 3)).as_rotvec()


def inverse(t: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)`` without a general matrix inverse."""
    t = np.asarray(t, dtype=float)
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def point_at(t: np.ndarray, offset: np.ndarray | None) -> np.ndarray:
    """``(..., 3)``: the point at ``offset`` (``(3,)`` or one per frame, ``(..., 3)``) in the frames
    ``t (..., 4, 4)``; their origins when None."""
    t = np.asarray(t)
    if offset is None:
        return t[..., :3, 3]
    return t[..., :3, 3] + np.einsum("...ij,...j->...i", t[..., :3, :3], np.asarray(offset, dtype=float))


def pose_difference(t_true: np.ndarray, t_model: np.ndarray) -> np.ndarray:
    """Paper eq. 1, ``T_diff = T_true · T_model^-1``, so that ``T_diff · T_model = T_true``."""
    return np.asarray(t_true) @ inverse(t_model)


def rotation_angle(rotation: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices ``(..., 3, 3)``, accurate near zero (atan2, not arccos)."""
    r = np.asarray(rotation)
    skew = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (trace - 1.0))


def pose_errors(t_a: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error in mm and orientation error in degrees between two batches of poses."""
    t_a, t_b = np.asarray(t_a), np.asarray(t_b)
    pos_mm = 1e3 * np.linalg.norm(t_a[..., :3, 3] - t_b[..., :3, 3], axis=-1)
    rel = np.swapaxes(t_b[..., :3, :3], -1, -2) @ t_a[..., :3, :3]
    return pos_mm, np.degrees(rotation_angle(rel))


def fit_rigid(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transforms ``(B, 4, 4)`` with ``T · source ≈ target``, and the RMS residual ``(B,)``.

    ``source`` is ``(k, 3)`` (one layout for every batch item, e.g. nominal reflector points on a tool) or
    ``(B, k, 3)``; ``target`` is ``(B, k, 3)``; ``k >= 3`` non-collinear points. Kabsch by a batched SVD,
    with the reflection guard: scipy's ``Rotation.align_vectors`` gives the same rotation one batch item
    per call, which costs far more over a whole measurement file.
    """
    target = np.asarray(target, dtype=float)
    source = np.broadcast_to(np.asarray(source, dtype=float), target.shape)
    cs = source.mean(axis=-2, keepdims=True)
    ct = target.mean(axis=-2, keepdims=True)
    h = np.einsum("bki,bkj->bij", source - cs, target - ct)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)))
    fix = np.ones((len(target), 3))
    fix[:, 2] = np.where(d == 0.0, 1.0, d)
    rotation = np.swapaxes(vt, -1, -2) @ (fix[:, :, None] * np.swapaxes(u, -1, -2))
    out = np.zeros((len(target), 4, 4))
    out[:, :3, :3] = rotation
    out[:, :3, 3] = ct[:, 0] - np.einsum("bij,bj->bi", rotation, cs[:, 0])
    out[:, 3, 3] = 1.0
    fitted = np.einsum("bij,bkj->bki", rotation, source) + out[:, None, :3, 3]
    residual = np.sqrt(np.mean(np.sum((fitted - target) ** 2, axis=-1), axis=-1))
    return out, residual


def log_so3(r: np.ndarray) -> np.ndarray:
    """Rotation vector of one rotation matrix; accurate near zero, scipy near π."""
    return np.array(_log_so3_floats(r))


def _log_so3_floats(r: np.ndarray) -> tuple[float, float, float]:
    """:func:`log_so3` in Python floats: the IK's inner loops take it once a step, where each numpy call
    costs a microsecond or more."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    x, y, z = h - f, c - g, d - b
    s = 0.5 * math.sqrt(x * x + y * y + z * z)
    angle = math.atan2(s, 0.5 * (a + e + i - 1.0))
    if angle > 3.0:
        return tuple(rotvec(r[None])[0].tolist())
    k = 0.5 if angle < 1e-9 else angle / (2.0 * s)
    return k * x, k * y, k * z


def error6(target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``[p_t − p; log(R_t Rᵀ)]`` in m and rad, base frame."""
    (tx, ty, tz), (px, py, pz) = target[:3, 3].tolist(), T[:3, 3].tolist()
    return np.array((tx - px, ty - py, tz - pz, *_log_so3_floats(target[:3, :3] @ T[:3, :3].T)))


def error6_batch(targets: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``(B, 6)``: :func:`error6` of poses ``T (B, 4, 4)`` against ``targets`` ``(B, 4, 4)`` or one ``(4, 4)``.
    The rotation vector in closed form as :func:`log_so3` (scipy's Rotation costs more than the rest for a few
    poses, on the valley search's and the closed forms' paths), scipy's where the angle nears π."""
    r = targets[..., :3, :3] @ T[:, :3, :3].mT
    skew = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=1)
    s = 0.5 * np.linalg.norm(skew, axis=1)
    angle = np.arctan2(s, 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rotation = np.where(angle < 1e-9, 0.5, angle / (2.0 * s))[:, None] * skew
    far = angle > 3.0
    if far.any():
        rotation[far] = rotvec(r[far])
    return np.concatenate([targets[..., :3, 3] - T[:, :3, 3], rotation], axis=1)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """``(B, 3, 3)``: maps d(ω) to the angular velocity of ``exp(ω)`` in the base frame; ``(3, 3)`` for one
    vector ``(3,)``, in Python floats (faster than numpy for one)."""
    if w.shape == (3,):
        x, y, z = w.tolist()
        t = math.sqrt(x * x + y * y + z * z)
        if t < 1e-8:
            return rodrigues_one(x, y, z, 0.5, 1.0 / 6.0)
        return rodrigues_one(x, y, z, (1.0 - math.cos(t)) / (t * t), (t - math.sin(t)) / (t * t * t))
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = skew(w)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * k + b * (k @ k)
