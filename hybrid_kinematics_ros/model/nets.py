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

from hybrid_kinematics_ros.kinematics.se3 import skew


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
        if r.ndim == 1 and np.ndim(angle) == 0:  # in Python floats: 1.5 µs, where numpy's products cost 5
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


def _silu_and_slope(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sig = expit(x)
    y = x * sig
    return y, sig + y * (1.0 - sig)  # d(x σ(x))/dx = σ + x σ (1 − σ)


def _tanh_and_slope(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.tanh(x)
    return y, 1.0 - y * y


class NumpyResidual:
    """A numpy evaluator of a saved MLP residual net, for single configurations.

    At batch size 1 TorchScript spends ~50 µs per call on operator dispatch; these few numpy products take
    a few µs. Only plain MLPs (Linear and activation layers) qualify; :meth:`from_module` returns None for
    others, and callers then use the TorchScript module. Tests check it against TorchScript.
    """

    # each activation: its value, and its value with its slope (for the Jacobian)
    _ACT: ClassVar[dict] = {
        "ReLU": (lambda x: np.maximum(x, 0.0), lambda x: (np.maximum(x, 0.0), (x > 0).astype(x.dtype))),
        "SiLU": (lambda x: x * expit(x), _silu_and_slope),
        "Tanh": (np.tanh, _tanh_and_slope),
    }

    def __init__(self, module: torch.jit.ScriptModule, stacks: list[list]) -> None:
        self.center = module.center.numpy()
        self.half_span = module.half_span.numpy()
        self.mean = module.target_mean.numpy()
        self.scale = module.target_scale.numpy()
        self.axis = module.axis.numpy()
        self.sincos = bool(module.sincos)  # ScriptModules keep plain attributes
        self.n_joints = int(getattr(module, "n_joints", len(self.center)))
        self.turn = bool(module.turn)
        self.stacks = stacks  # one list of layers per ensemble member (one for a single net)
        self.turner = AxisTurn(self.axis)

    @classmethod
    def from_module(cls, module: torch.nn.Module) -> NumpyResidual | None:
        """From a loaded TorchScript net or an eager :class:`ResidualNet`; None if not a plain MLP or an
        ensemble of them."""
        body = module.body
        kind = getattr(body, "original_name", None) or type(body).__name__
        members = list(body.members.children()) if kind == "Ensemble" else [body]
        stacks = [cls._layers(member) for member in members]
        return None if any(stack is None for stack in stacks) else cls(module, stacks)

    @classmethod
    def _layers(cls, body: torch.nn.Module) -> list | None:
        layers: list = []
        for child in body.children():
            kind = getattr(child, "original_name", None) or type(child).__name__
            if kind == "Linear":
                # float32 as in the net: the weights' memory traffic dominates the cost at batch size 1
                weight, bias = child.weight.detach().numpy().T.copy(), child.bias.detach().numpy().copy()
                layers.append(("linear", weight, bias))
            elif kind in cls._ACT:
                layers.append(("act", *cls._ACT[kind]))
            else:
                return None
        return layers

    def __call__(self, q: np.ndarray) -> np.ndarray:
        x = (q - self.center) / self.half_span
        if self.sincos:
            joints = q[..., : self.n_joints]
            x = np.concatenate([x, np.sin(joints), np.cos(joints)], axis=-1)
        x = x.astype(np.float32)
        out = []
        for layers in self.stacks:
            y = x
            for kind, a, b in layers:
                y = y @ a + b if kind == "linear" else a(y)
            out.append(y)
        r = (out[0].astype(np.float64) if len(out) == 1 else np.mean(out, axis=0, dtype=np.float64)) * self.scale
        r += self.mean
        return self.turner.apply(r, q[..., 0]) if self.turn else r

    def value_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``(3,)`` and its derivative ``(3, n)`` for one input ``(n,)``; with condition columns the
        derivative covers them too. Reverse mode: the three outputs' gradients go back through each layer
        as one ``(3, width)`` product (forward mode carries a row per input feature, 18 for six joints with
        their sines and cosines), and through the features by the chain rule without building their
        Jacobian: 91 → 65 µs for a UR10's 256×3 net."""
        x = (q - self.center) / self.half_span
        if self.sincos:
            joints = q[: self.n_joints]
            sin, cos = np.sin(joints), np.cos(joints)
            x = np.concatenate([x, sin, cos])
        x = x.astype(np.float32)
        outs, grads = [], []
        for layers in self.stacks:
            y, slopes = x, []
            for kind, a, b in layers:
                if kind == "linear":
                    y = y @ a + b
                else:
                    y, slope = b(y)
                    slopes.append(slope)
            g = np.eye(len(y), dtype=np.float32)  # d(outputs)/d(outputs), then back through each layer
            for kind, a, _ in reversed(layers):
                g = g @ a.T if kind == "linear" else g * slopes.pop()
            outs.append(y)
            grads.append(g)
        single = len(outs) == 1
        out = outs[0].astype(np.float64) if single else np.mean(outs, axis=0, dtype=np.float64)
        grad = grads[0].astype(np.float64) if single else np.mean(grads, axis=0, dtype=np.float64)
        grad *= self.scale[:, None]
        local = out * self.scale + self.mean
        k = len(q)
        dlocal = grad[:, :k] / self.half_span  # (3, n): the features' chain rule, (q − centre) / half span first
        if self.sincos:
            n = self.n_joints
            dlocal[:, :n] += grad[:, k : k + n] * cos - grad[:, k + n :] * sin
        if not self.turn:
            return local, dlocal
        rot = self.turner.matrix(q[0])
        r = rot @ local
        d = rot @ dlocal
        d[:, 0] += self.turner.kx @ r  # d(rot r_local)/dq1 = k × (rot r_local)
        return r, d
