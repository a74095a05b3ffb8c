"""The residual nets at run time: a numpy evaluator of a saved MLP and the joint-1 turn of its output.

A saved TorchScript net is self-contained (:mod:`hybrid_kinematics_ros.calibration.nets` builds and
trains it) and needs nothing from here to load; at batch size 1 the numpy evaluator here is ~10× faster.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch
from scipy.special import expit


def to_joint1_frame(r: np.ndarray, q1: np.ndarray, axis: np.ndarray | None) -> np.ndarray:
    """Base-frame residuals ``(B, 3)`` into the joint-1 frame: the inverse of ``ResidualNet.to_base``."""
    if axis is None:
        return r
    k = np.broadcast_to(axis, r.shape)
    c, s = np.cos(-q1)[:, None], np.sin(-q1)[:, None]
    return r * c + np.cross(k, r) * s + k * np.sum(k * r, axis=1, keepdims=True) * (1.0 - c)


def _silu_grad(x: np.ndarray) -> np.ndarray:
    sig = expit(x)
    return sig * (1.0 + x * (1.0 - sig))


class NumpyResidual:
    """A numpy evaluator of a saved MLP residual net, for single configurations.

    At batch size 1 TorchScript spends ~50 µs per call on operator dispatch; these few numpy products take
    a few µs. Only plain MLPs (Linear and activation layers) qualify; :meth:`from_module` returns None for
    others, and callers then use the TorchScript module. Tests check it against TorchScript.
    """

    _ACT: ClassVar[dict] = {
        "ReLU": (lambda x: np.maximum(x, 0.0), lambda x: (x > 0).astype(x.dtype)),
        "SiLU": (lambda x: x * expit(x), lambda x: _silu_grad(x)),
        "Tanh": (np.tanh, lambda x: 1.0 - np.tanh(x) ** 2),
    }

    def __init__(self, module: torch.jit.ScriptModule, layers: list) -> None:
        self.center = module.center.numpy()
        self.half_span = module.half_span.numpy()
        self.mean = module.target_mean.numpy()
        self.scale = module.target_scale.numpy()
        self.axis = module.axis.numpy()
        self.sincos = bool(module.sincos)  # ScriptModules keep plain attributes
        self.n_joints = int(getattr(module, "n_joints", len(self.center)))
        self.turn = bool(module.turn)
        self.layers = layers
        k = self.axis
        self.kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])  # k × r = kx @ r
        self.kk = np.outer(k, k)

    @classmethod
    def from_module(cls, module: torch.nn.Module) -> NumpyResidual | None:
        """From a loaded TorchScript net or an eager :class:`ResidualNet`; None if not a plain MLP."""
        layers: list = []
        for child in module.body.children():
            kind = getattr(child, "original_name", None) or type(child).__name__
            if kind == "Linear":
                # float32 as in the net: the weights' memory traffic dominates the cost at batch size 1
                weight, bias = child.weight.detach().numpy().T.copy(), child.bias.detach().numpy().copy()
                layers.append(("linear", weight, bias))
            elif kind in cls._ACT:
                layers.append(("act", *cls._ACT[kind]))
            else:
                return None
        return cls(module, layers)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        x = (q - self.center) / self.half_span
        if self.sincos:
            joints = q[..., : self.n_joints]
            x = np.concatenate([x, np.sin(joints), np.cos(joints)], axis=-1)
        x = x.astype(np.float32)
        for kind, a, b in self.layers:
            x = x @ a + b if kind == "linear" else a(x)
        return self._to_base(x.astype(np.float64) * self.scale + self.mean, q)

    def _rotation(self, q1: float) -> np.ndarray:
        c, s = math.cos(q1), math.sin(q1)
        return c * np.eye(3) + s * self.kx + (1.0 - c) * self.kk

    def _to_base(self, r: np.ndarray, q: np.ndarray) -> np.ndarray:
        if not self.turn:
            return r
        if r.ndim == 1:
            return self._rotation(q[0]) @ r
        c, s = np.cos(q[:, :1]), np.sin(q[:, :1])
        return r * c + (r @ self.kx.T) * s + (r @ self.kk) * (1.0 - c)

    def value_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``(3,)`` and its derivative ``(3, n)`` for one input ``(n,)`` (forward mode); with
        condition columns the derivative covers them too."""
        x = (q - self.center) / self.half_span
        jac = np.diag(1.0 / self.half_span)  # (inputs, features): row j is d(features)/d(q_j)
        if self.sincos:
            joints = q[: self.n_joints]
            x = np.concatenate([x, np.sin(joints), np.cos(joints)])
            trig = np.zeros((len(q), 2 * self.n_joints))
            trig[: self.n_joints] = np.concatenate([np.diag(np.cos(joints)), np.diag(-np.sin(joints))], axis=1)
            jac = np.concatenate([jac, trig], axis=1)
        x = x.astype(np.float32)
        jac = jac.astype(np.float32)
        for kind, a, b in self.layers:
            if kind == "linear":
                x, jac = x @ a + b, jac @ a
            else:
                x, jac = a(x), jac * b(x)
        local = x.astype(np.float64) * self.scale + self.mean
        dlocal = (jac.astype(np.float64) * self.scale).T  # (3, n)
        if not self.turn:
            return local, dlocal
        rot = self._rotation(q[0])
        r = rot @ local
        d = rot @ dlocal
        d[:, 0] += self.kx @ r
        return r, d
