"""An elasto-geometric chain: a :class:`Chain` whose joints have zero offsets and deflect under gravity.

This one model serves two masters: the virtual cell's ground truth (which adds gear errors and stiffening)
and the parametric calibration stage (which identifies its parameters from data). Effects:

- joint zero offsets: ``q_eff = q + zero_offset``;
- cyclic joint errors (transmission and encoder errors): ``q_eff += Σ_f a_f sin(f q) + b_f cos(f q)``, a
  Fourier series in each joint's own commanded angle (``joint_error``, harmonics ``f = 1 … K``);
- a joint error map (``joint_map``): a table of each joint's error against its own commanded angle,
  interpolated linearly, for the errors of shorter period than the Fourier series carries;
- joint compliance: the gravity torque ``τ`` about each joint (URDF inertials plus the payload) turns
  the joint by ``c τ / (1 + r (τ/τ_ref)²)`` (``r = 0``: a linear spring);
- bending: the link after joint k turns by the rotation vector ``b_k τ_k`` (in the joint's frame, after
  its motion), typically perpendicular to the joint axis.

With all of them zero it is the rigid chain, and every method takes the plain FK path at no extra cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from hybrid_kinematics_ros.kinematics import fk, fk_kernel
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.se3 import exp_so3

GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s², in the base frame: a floor-mounted robot's
CHUNK = 4096


@dataclass(frozen=True, eq=False)
class JointMap:
    """Each joint's error (rad) against its own commanded angle: ``values[k, i]`` at ``lower[k] + i · step``,
    linear in between, held at the end values beyond (the map says nothing new outside what it saw)."""

    lower: np.ndarray  # (n,) rad: the angle of each joint's first knot
    step: float  # rad between knots
    values: np.ndarray  # (n, m) rad

    def _knots(self, q: np.ndarray, lower: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """The knot at or left of each angle (the last but one beyond the end) and the fraction of a step
        past it (below 0 or above 1 outside the map)."""
        x = (q - lower) / self.step
        i0 = np.clip(np.floor(x), 0, self.values.shape[1] - 2).astype(int)
        return i0, x - i0

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Errors ``(..., n)`` at commanded ``q (..., n)`` and their slopes ``d error / d q``."""
        if q.ndim == 1:
            return self._one(q.tolist())
        i0, frac = self._knots(q, self.lower)
        inside = (frac >= 0.0) & (frac <= 1.0)
        rows = np.arange(len(self.lower))
        left, right = self.values[rows, i0], self.values[rows, i0 + 1]
        return left + np.clip(frac, 0.0, 1.0) * (right - left), np.where(inside, (right - left) / self.step, 0.0)

    @cached_property
    def _lists(self) -> tuple[list[list[float]], list[float]]:
        return self.values.tolist(), self.lower.tolist()

    def _one(self, q: list[float]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`__call__` of one configuration, in Python floats: the same operations, the same bits, at a
        tenth of the cost (each numpy call on six values costs microseconds; FK services and IK take this path)."""
        values, lower = self._lists
        step, last = self.step, len(values[0]) - 2
        errors, slopes = [], []
        for row, lo, v in zip(values, lower, q, strict=True):
            x = (v - lo) / step
            i = min(max(math.floor(x), 0), last)
            frac = x - i
            left, right = row[i], row[i + 1]
            errors.append(left + min(max(frac, 0.0), 1.0) * (right - left))
            slopes.append((right - left) / step if 0.0 <= frac <= 1.0 else 0.0)
        return np.array(errors), np.array(slopes)

    def weights(self, q: np.ndarray, joint: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For joint ``joint`` at angles ``q (B,)``: the two knots each angle falls between and their weights
        ``(B,)`` each, the map's value being linear in ``values``: ``w0 · v[i0] + w1 · v[i0 + 1]``."""
        i0, frac = self._knots(q, self.lower[joint])
        frac = np.clip(frac, 0.0, 1.0)
        return i0, 1.0 - frac, frac

    def manifest(self) -> dict:
        return {"unit": "rad", "lower": self.lower.tolist(), "step": self.step, "values": self.values.tolist()}

    @classmethod
    def from_manifest(cls, section: dict) -> JointMap:
        values = np.asarray(section["values"], dtype=float)
        lower = np.asarray(section["lower"], dtype=float)
        if values.ndim != 2 or len(lower) != len(values) or values.shape[1] < 2 or float(section["step"]) <= 0:
            raise ValueError("joint_map needs one row of at least two values per joint and a positive step")
        return cls(lower, float(section["step"]), values)


@dataclass(frozen=True, eq=False)
class ElasticChain:
    chain: Chain
    zero_offset: np.ndarray  # (n,) rad (m for prismatic joints)
    compliance: np.ndarray  # (n,) rad/Nm (m/N)
    bending: np.ndarray  # (n, 3) rad/Nm
    payload_mass: float = 0.0  # kg
    payload_com: np.ndarray = field(default_factory=lambda: np.zeros(3))  # in the tip frame
    cubic_ratio: float = 0.0
    torque_ref: float = 100.0
    joint_error: np.ndarray | None = None  # (n, K, 2) rad: sin and cos coefficients of harmonics 1 … K
    joint_map: JointMap | None = None
    cubic_compliance: np.ndarray | None = None  # (n,) rad/Nm³: the deflection's term in τ³ (load-dependent stiffness)
    signed_compliance: np.ndarray | None = None  # (n,) rad/Nm: the term in |τ| (stiffer one way than the other)
    gravity: np.ndarray = field(default_factory=lambda: GRAVITY.copy())  # m/s², base frame (wall, ceiling, tilt)
    backlash: np.ndarray | None = None  # (n,) rad: each joint's shift per unit of approach direction (approached)

    def approached(self, q: np.ndarray, directions: np.ndarray | None) -> np.ndarray:
        """Commanded joints ``(…, n)`` as the backlash leaves them, given the joints' approach directions
        ``(…, n)`` (:mod:`kinematics.approach`; None: unknown, no shift). The FK methods take joints shifted so: the
        directions are not a function of the joints, so the caller, who knows them, applies them."""
        if self.backlash is None or directions is None:
            return q
        return np.asarray(q, dtype=float) + self.backlash * np.asarray(directions, dtype=float)

    def corrected_joints(self, q: np.ndarray) -> np.ndarray:
        """Commanded joints ``(B, n)`` plus zero offsets and cyclic joint errors: what the rigid links reach."""
        q = np.asarray(q, dtype=float)
        out = q + self.zero_offset
        if self.has_joint_error:
            if q.ndim == 1 and self.joint_map is None:  # one pose, the IK's inner loop: compiled
                return out + fk_kernel.cyclic_errors(q, self._cyclic_coefficients)
            out = out + self._joint_errors(q, slopes=False)[0]
        return out

    @cached_property
    def _cyclic_coefficients(self) -> np.ndarray:
        """``joint_error`` as :func:`fk_kernel.cyclic_errors` takes it: contiguous float64 ``(n, K, 2)``."""
        return np.ascontiguousarray(self.joint_error, dtype=float)

    @cached_property
    def has_joint_error(self) -> bool:
        return (self.joint_error is not None and bool(np.any(self.joint_error))) or self.joint_map is not None

    @cached_property
    def _harmonics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The cyclic errors' coefficients as complex numbers, since ``a sin fq + b cos fq = Re((b − i a) e^{i fq})``
        and its slope is ``−Im(f (b − i a) e^{i fq})``: one exponential and two contractions instead of a sine,
        a cosine and eight products (a third less time, in a batch and for one pose alike). ``(i f, c, f c)``."""
        if self.joint_error is None:
            return None
        coef = np.asarray(self.joint_error, dtype=float)
        f = np.arange(1, coef.shape[1] + 1)
        c = coef[..., 1] - 1j * coef[..., 0]  # (n, K)
        return 1j * f, c, f * c

    def _joint_errors(self, q: np.ndarray, slopes: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The cyclic and mapped joint errors ``(..., n)`` at commanded ``q`` and their slopes ``d error / d q``
        (None unless ``slopes``)."""
        value, slope = np.zeros_like(q), np.zeros_like(q) if slopes else None
        if self._harmonics is not None:
            i_f, c, fc = self._harmonics
            turn = np.exp(q[..., None] * i_f)  # (..., n, K)
            value = value + np.einsum("...k,...k->...", turn, c).real
            if slopes:
                slope = slope - np.einsum("...k,...k->...", turn, fc).imag
        if self.joint_map is not None:
            mapped, mapped_slope = self.joint_map(q)
            value = value + mapped
            if slopes:
                slope = slope + mapped_slope
        return value, slope

    @classmethod
    def rigid(cls, chain: Chain, payload_mass: float = 0.0, payload_com: np.ndarray | None = None) -> ElasticChain:
        n = chain.dof
        com = np.zeros(3) if payload_com is None else np.asarray(payload_com, dtype=float)
        return cls(chain, np.zeros(n), np.zeros(n), np.zeros((n, 3)), float(payload_mass), com)

    @property
    def dof(self) -> int:
        return self.chain.dof

    @property
    def is_rigid(self) -> bool:
        """The chain's own FK, unchanged: no offsets, no deflections, no joint errors and no backlash (which
        shifts the joints wherever their approach directions are known)."""
        backlash = self.backlash is not None and bool(np.any(self.backlash))
        return not (np.any(self.zero_offset) or self.is_elastic or self.has_joint_error or backlash)

    @cached_property
    def is_elastic(self) -> bool:
        extra = (self.cubic_compliance, self.signed_compliance)
        return bool(np.any(self.compliance) or np.any(self.bending) or any(e is not None and np.any(e) for e in extra))

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        """Torques ``(B, n)`` (Nm) that gravity exerts about each joint axis (force along prismatic axes)."""
        frames = fk.joint_frames(self.chain, q)
        n = self.dof
        com = np.einsum("bkij,kj->bki", frames[:, :n, :3, :3], self.chain.segment_com) + frames[:, :n, :3, 3]
        tip = frames[:, n]
        payload = tip[:, :3, :3] @ self.payload_com + tip[:, :3, 3]
        com = np.concatenate([com, payload[:, None]], axis=1)
        force = np.append(self.chain.segment_mass, self.payload_mass)[:, None] * self.gravity  # (n + 1, 3)
        axes = np.einsum("bkij,kj->bki", frames[:, :n, :3, :3], self.chain.axes)
        # Moment about joint j of the loads beyond it: Σ_i≥j (c_i − o_j) × f_i = Σ c_i × f_i − o_j × Σ f_i
        moments = np.cross(com, force)[:, ::-1].cumsum(axis=1)[:, ::-1][:, :n]
        totals = force[::-1].cumsum(axis=0)[::-1][:n]
        moments = moments - np.cross(frames[:, :n, :3, 3], totals)
        torque = np.einsum("bki,bki->bk", moments, axes)
        if not self.chain.revolute.all():
            linear = np.einsum("bki,ki->bk", axes, totals)
            torque = np.where(self.chain.revolute, torque, linear)
        return torque

    def effective_joints(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint values the links really reach, and the gravity torques ``(B, n)`` (zeros when rigid)."""
        q_eff = self.corrected_joints(np.atleast_2d(q))
        if not self.is_elastic:
            return q_eff, np.zeros_like(q_eff)
        torque = self.gravity_torques(q_eff)
        return q_eff + self.deflection(torque), torque

    def deflection(self, torque: np.ndarray) -> np.ndarray:
        """Joint deflections ``(..., n)`` under the gravity torques ``(..., n)``: a spring that stiffens with
        load, ``c τ / (1 + r (τ/τ_ref)²)`` (the simulator's truth), plus the identified stage's ``c₃ τ³``
        (the same stiffening to first order; harmonic drives and cycloidal gears are softer near zero load)
        and ``c± |τ|`` (a joint stiffer under one sign of torque than the other: ``c + c±`` one way,
        ``c − c±`` the other)."""
        out = self.compliance * torque / (1.0 + self.cubic_ratio * (torque / self.torque_ref) ** 2)
        if self.cubic_compliance is not None:
            out = out + self.cubic_compliance * torque**3
        if self.signed_compliance is not None:
            out = out + self.signed_compliance * np.abs(torque)
        return out

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Tip poses ``(B, 4, 4)`` for commanded joints ``(B, n)``."""
        q = fk.check_joints(self.chain, q)
        if not self.is_elastic:
            return fk.fk(self.chain, self.corrected_joints(q))
        out = np.empty((len(q), 4, 4))
        for s in range(0, len(q), CHUNK):
            out[s : s + CHUNK] = self._frames(q[s : s + CHUNK])[1]
        return out

    def fk_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tip poses ``(B, 4, 4)`` and geometric Jacobians ``(B, 6, n)``.

        The Jacobian holds the deflections at their current values: it leaves out ``c ∂τ/∂q``, about 1e-3
        of the rigid terms for an industrial arm, which least squares on the exact poses does not need.
        It is taken with respect to the commanded joints (the cyclic joint errors' slopes are included).
        """
        q = fk.check_joints(self.chain, q)
        if not self.is_elastic:
            tips, jacs = fk.fk_and_jacobian(self.chain, self.corrected_joints(q))
        else:
            tips, jacs = np.empty((len(q), 4, 4)), np.empty((len(q), 6, self.dof))
            for s in range(0, len(q), CHUNK):
                motion, tips[s : s + CHUNK] = self._frames(q[s : s + CHUNK])
                jacs[s : s + CHUNK] = fk.jacobian_from_frames(self.chain, motion, tips[s : s + CHUNK])
        if self.has_joint_error:
            jacs = jacs * (1.0 + self._joint_errors(q)[1])[:, None, :]
        return tips, jacs

    def fk_single(self, q: np.ndarray) -> np.ndarray:
        """One pose ``(4, 4)`` for one configuration ``(n,)``."""
        if not self.is_elastic:
            return fk.fk_single(self.chain, self.corrected_joints(q))
        return self._single(np.asarray(q, dtype=float), jacobian=False)[0]

    def fk_and_jacobian_single(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One pose ``(4, 4)`` and its Jacobian ``(6, n)``, with the approximation of :meth:`fk_and_jacobian`."""
        q = np.asarray(q, dtype=float)
        if not self.is_elastic:
            tip, jac = fk.fk_and_jacobian_single(self.chain, self.corrected_joints(q))
            return tip, (jac * (1.0 + self._joint_errors(q)[1]) if self.has_joint_error else jac)
        tip, jac = self._single(q, jacobian=True)
        if self.has_joint_error:
            jac *= 1.0 + self._joint_errors(q)[1]
        return tip, jac

    @cached_property
    def _kernel_operands(self) -> fk_kernel.ElasticOperands:
        """:func:`fk_kernel.elastic_pose`'s operands after the joints, contiguous (unpacked into each call)."""
        mass = np.append(self.chain.segment_mass, self.payload_mass)
        zeros = np.zeros(self.dof)

        def c(a: np.ndarray | None) -> np.ndarray:
            return zeros if a is None else np.ascontiguousarray(a, dtype=float)

        return fk_kernel.ElasticOperands(
            *self.chain.kernel_operands,
            segment_com=c(self.chain.segment_com),
            mass=mass,
            beyond=np.cumsum(mass[::-1])[::-1][:-1],
            payload_com=c(self.payload_com),
            gravity=c(self.gravity),
            compliance=c(self.compliance),
            cubic_ratio=float(self.cubic_ratio),
            torque_ref=float(self.torque_ref),
            cubic_compliance=c(self.cubic_compliance),
            signed_compliance=c(self.signed_compliance),
            bending=c(self.bending),
            bends=bool(np.any(self.bending)),
        )

    @cached_property
    def pose_operands(self) -> tuple | None:
        """What ``model/pose_kernel.hybrid_pose`` takes of the stage after the joints: the zero offsets, the
        cyclic errors' coefficients ``(n, K, 2)`` (K = 0 without them), whether it is elastic, and
        :func:`fk_kernel.elastic_pose`'s operands; None with a joint error map (not compiled)."""
        if self.joint_map is not None:
            return None
        coefficients = self._cyclic_coefficients if self.joint_error is not None else np.zeros((self.dof, 0, 2))
        offset = np.ascontiguousarray(self.zero_offset, dtype=float)
        return offset, coefficients, self.is_elastic, tuple(self._kernel_operands)  # a plain tuple: one argument

    def _single(self, q: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
        """The tip ``(4, 4)`` and (zeros unless ``jacobian``) the Jacobian ``(6, n)`` of one configuration, before
        the joint errors' slopes: the compiled kernel (:func:`fk_kernel.elastic_pose`), where the batch code
        with a batch of one, or numpy written for one pose, would spend most of its time in numpy's overhead."""
        q_eff = np.ascontiguousarray(self.corrected_joints(q), dtype=float)
        return fk_kernel.elastic_pose(q_eff, *self._kernel_operands, jacobian)

    def _frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each joint's frame right after its motion, before bending, ``(B, n, 4, 4)``, and the tips."""
        q_eff, torque = self.effective_joints(q)
        a, b = self.chain.coefficients(q_eff)
        g = self.chain.generators
        local = g[None, :, 0] + a[..., None, None] * g[None, :, 1] + b[..., None, None] * g[None, :, 2]
        bend = exp_so3(torque[..., None] * self.bending)  # (B, n, 3, 3)
        motion = np.empty_like(local)
        t = local[:, 0]
        for k in range(self.dof):
            if k:
                t = t @ local[:, k]
            motion[:, k] = t
            t = t.copy()
            t[:, :3, :3] = t[:, :3, :3] @ bend[:, k]
        return motion, t @ self.chain.post


def bending_basis(chain: Chain) -> np.ndarray:
    """``(n, 2, 3)``: two unit axes perpendicular to each joint axis, in its frame (the ``u`` and ``v`` of
    bending). The truth bends about ``u``; the parametric stage fits both."""
    out = np.empty((chain.dof, 2, 3))
    for k, axis in enumerate(chain.axes):
        helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(axis, helper)
        u /= np.linalg.norm(u)
        out[k] = u, np.cross(axis, u)
    return out
