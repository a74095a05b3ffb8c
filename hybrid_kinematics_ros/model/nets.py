"""The residual nets at run time: a compiled evaluator of a saved MLP and the joint-1 turn of its output.

A saved TorchScript net is self-contained (:mod:`hybrid_kinematics_ros.calibration.nets` builds and
trains it) and needs nothing from here to load; at batch size 1 the evaluator here is several times faster.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hybrid_kinematics_ros.kinematics.se3 import skew
from hybrid_kinematics_ros.model import mlp_kernel


class AxisTurn:
    """Turns by an angle about a fixed unit axis (Rodrigues), with the axis' matrices built once: the
    residual's joint-1 frame to the base frame. The numpy twin of ``ResidualNet._turn``, which the
    TorchScript file carries; building the constants per call would triple its cost on one pose."""

    def __init__(self, axis: np.ndarray) -> None:
        self.axis = np.asarray(axis, dtype=float)
        self.kx = skew(self.axis)  # k × r = kx @ r
        self.kk = np.outer(self.axis, self.axis)
        self._k = tuple(self.axis.tolist())

    def matrix(self, angle: np.ndarray | float) -> np.ndarray:
        """Rotation matrices ``(..., 3, 3)`` by ``angle`` (rad, scalar or ``(...)``)."""
        c, s = np.cos(angle)[..., None, None], np.sin(angle)[..., None, None]
        return c * np.eye(3) + s * self.kx + (1.0 - c) * self.kk

    def apply(self, r: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
        """Vectors ``r (..., 3)`` turned by ``angle`` (one per vector, or one for all); one vector by one angle
        as ``r cos + (k × r) sin + k (k · r)(1 − cos)``, without building the matrix."""
        if r.ndim == 1 and np.ndim(angle) == 0:  # in Python floats: faster than numpy for one vector
            c, s = math.cos(angle), math.sin(angle)
            (x, y, z), (kx, ky, kz) = r.tolist(), self._k
            along = (1.0 - c) * (kx * x + ky * y + kz * z)
            return np.array(
                (
                    c * x + s * (ky * z - kz * y) + along * kx,
                    c * y + s * (kz * x - kx * z) + along * ky,
                    c * z + s * (kx * y - ky * x) + along * kz,
                )
            )
        return (self.matrix(angle) @ r[..., None])[..., 0]


def to_joint1_frame(r: np.ndarray, q1: np.ndarray, axis: np.ndarray | None) -> np.ndarray:
    """Base-frame residuals ``(B, 3)`` into the joint-1 frame (what the net learns); None: no turn."""
    return r if axis is None else AxisTurn(axis).apply(r, -q1)


class FastResidual:
    """A compiled evaluator of a saved MLP residual net (:mod:`~hybrid_kinematics_ros.model.mlp_kernel`), for
    single configurations and small batches.

    At batch size 1 TorchScript spends most of a call on operator dispatch, numpy on a dozen small operations;
    the kernel does the whole net in one call. Only plain MLPs (Linear and activation layers),
    or ensembles of equally deep ones, qualify; :meth:`from_module` returns None for others, and callers then
    use the TorchScript module. Tests check it against TorchScript and its autograd.
    """

    def __init__(self, module: torch.jit.ScriptModule, stacks: list[list]) -> None:
        self.center = module.center.numpy().astype(np.float64)
        self.half_span = module.half_span.numpy().astype(np.float64)
        self.mean = module.target_mean.numpy().astype(np.float64)
        self.scale = module.target_scale.numpy().astype(np.float64)
        self.axis = module.axis.numpy()
        self.sincos = bool(module.sincos)  # ScriptModules keep plain attributes
        self.n_joints = int(getattr(module, "n_joints", len(self.center)))
        self.turn = bool(module.turn)
        self.members = len(stacks)  # one list of layers per ensemble member (one for a single net)
        self._packed = mlp_kernel.pack(stacks)
        self.turner = AxisTurn(self.axis)
        # the net as model/pose_kernel.hybrid_pose takes it: the kernel's operands, the turn's axis and whether
        # the residual turns with joint 1
        self.kernel_operands = (*self._args(), self.mean, np.ascontiguousarray(self.axis, dtype=np.float64), self.turn)

    @classmethod
    def from_module(cls, module: torch.nn.Module) -> FastResidual | None:
        """From a loaded TorchScript net or an eager :class:`ResidualNet`; None if not a plain MLP or an
        ensemble of equally deep ones."""
        body = module.body
        kind = getattr(body, "original_name", None) or type(body).__name__
        members = list(body.members.children()) if kind == "Ensemble" else [body]
        stacks = [cls._layers(member) for member in members]
        if any(stack is None for stack in stacks) or len({len(stack) for stack in stacks}) != 1:
            return None
        return cls(module, stacks)

    @staticmethod
    def _layers(body: torch.nn.Module) -> list | None:
        """``(activation, weight (in, out), bias)`` per Linear layer, or None if the body is not an MLP."""
        layers: list = []
        for child in body.children():
            kind = getattr(child, "original_name", None) or type(child).__name__
            if kind == "Linear":
                weight, bias = child.weight.detach().numpy().T, child.bias.detach().numpy()
                layers.append(["linear", weight, bias])
            elif kind in mlp_kernel.ACTIVATIONS and layers and layers[-1][0] == "linear":
                layers[-1][0] = kind
            else:
                return None
        return [tuple(layer) for layer in layers]

    def _args(self) -> tuple:
        return (self.center, self.half_span, self.n_joints, self.sincos, *self._packed, self.members, self.scale)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """Residuals ``(B, 3)`` of inputs ``q (B, k)``, or ``(3,)`` of one ``(k,)``."""
        q = np.asarray(q, dtype=np.float64)
        if q.ndim == 1:  # one configuration (the IK's inner loop): no reshaping
            r = mlp_kernel.mlp_values(np.ascontiguousarray(q)[None], *self._args(), self.mean)[0]
            return self.turner.apply(r, float(q[0])) if self.turn else r
        r = mlp_kernel.mlp_values(np.ascontiguousarray(q.reshape(-1, q.shape[-1])), *self._args(), self.mean)
        return self.turner.apply(r, q[..., 0]) if self.turn else r

    def value_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``(3,)`` and its derivative ``(3, k)`` for one input ``(k,)``; with condition columns the
        derivative covers them too."""
        q = np.ascontiguousarray(q, dtype=np.float64)
        local, dlocal = mlp_kernel.mlp_value_and_jacobian(q, *self._args(), self.mean)
        if not self.turn:
            return local, dlocal
        rot = self.turner.matrix(q[0])
        r = rot @ local
        d = rot @ dlocal
        d[:, 0] += self.turner.kx @ r  # d(rot r_local)/dq1 = k × (rot r_local)
        return r, d
