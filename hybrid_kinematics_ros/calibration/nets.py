"""Residual networks: joints in radians in, a residual 3-vector in SI units out.

Everything a caller needs is inside the module, so a saved TorchScript file is self-contained:
min-max normalisation of the joints, optional ``sin``/``cos`` features, the network, de-standardisation
of the output, and (optionally) turning the residual from a frame that rotates with joint 1 back into
the base frame. Gravity does not change when the robot turns about a vertical joint 1, so in that frame
the residual hardly depends on ``q1`` and is easier to learn.

Condition channels (temperature, say) are extra input columns after the joints: min-max normalised like
them, without ``sin``/``cos`` features. The input is then ``(B, n + k)``; :class:`HybridModel` appends the
current values.

Architectures are named: the paper's ``D1``, ``D4``, ``D4w``, ``D4W`` (ReLU MLPs) and ``Rw``, ``Rd``
(ResNets of dense and identity blocks after Chen et al.), and ``mlp:WxD[:act]`` for plain MLPs.
"""

from __future__ import annotations

import itertools
import math
import re
from typing import ClassVar

import numpy as np
import torch
from scipy.special import expit
from torch import nn

from hybrid_kinematics_ros.calibration.errors import CalibrationError

PAPER_DENSE = {
    "D1": [5000],
    "D4": [3500, 2500, 1500, 750],
    "D4w": [5000, 3000, 1000, 500],
    "D4W": [6000, 3000, 1500, 1000],
}
PAPER_RESNET = {"Rw": [700, 500, 200], "Rd": [500, 200, 100, 70, 30]}
ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "tanh": nn.Tanh, "gelu": nn.GELU}
ARCHITECTURES = (*PAPER_DENSE, *PAPER_RESNET, "mlp:WxD[:relu|silu|tanh|gelu]")


def _mlp(sizes: list[int], out: int, act: type[nn.Module]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in itertools.pairwise(sizes):
        layers += [nn.Linear(a, b), act()]
    layers.append(nn.Linear(sizes[-1], out))
    return nn.Sequential(*layers)


class _ResBlock(nn.Module):
    """Three dense layers with batch norm; a projection shortcut for a dense block, identity otherwise."""

    def __init__(self, width_in: int, width: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Linear(width_in, width),
            nn.BatchNorm1d(width),
            nn.ReLU(),
            nn.Linear(width, width),
            nn.BatchNorm1d(width),
            nn.ReLU(),
            nn.Linear(width, width),
            nn.BatchNorm1d(width),
        )
        self.shortcut = (
            nn.Sequential(nn.Linear(width_in, width), nn.BatchNorm1d(width)) if width_in != width else nn.Identity()
        )
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.main(x) + self.shortcut(x))


def _resnet(n_in: int, widths: list[int], out: int) -> nn.Sequential:
    blocks: list[nn.Module] = []
    width_in = n_in
    for w in widths:
        # a component: one dense block (projection shortcut) then two identity blocks
        blocks += [_ResBlock(width_in, w), _ResBlock(w, w), _ResBlock(w, w)]
        width_in = w
    blocks.append(nn.Linear(width_in, out))
    return nn.Sequential(*blocks)


def build_body(arch: str, n_in: int, out: int = 3) -> nn.Module:
    if arch in PAPER_DENSE:
        return _mlp([n_in, *PAPER_DENSE[arch]], out, nn.ReLU)
    if arch in PAPER_RESNET:
        return _resnet(n_in, PAPER_RESNET[arch], out)
    match = re.fullmatch(r"mlp:(\d+)x(\d+)(?::(\w+))?", arch)
    if match:
        width, depth, act = int(match[1]), int(match[2]), match[3] or "silu"
        if act not in ACTIVATIONS or width < 1 or depth < 1:
            raise CalibrationError(f"architecture '{arch}': activation must be one of {sorted(ACTIVATIONS)}")
        return _mlp([n_in] + [width] * depth, out, ACTIVATIONS[act])
    raise CalibrationError(f"unknown architecture '{arch}'; choose one of {', '.join(ARCHITECTURES)}")


class ResidualNet(nn.Module):
    """Joints ``(B, n)`` rad (any float dtype), then any condition columns, to a residual ``(B, 3)`` float64
    in m or rad. ``lower``/``upper`` span every input column; ``n_joints`` says how many are joints."""

    def __init__(
        self,
        arch: str,
        lower: np.ndarray,
        upper: np.ndarray,
        target_mean: np.ndarray,
        target_scale: np.ndarray,
        sincos: bool = True,
        joint1_axis: np.ndarray | None = None,
        n_joints: int | None = None,
    ) -> None:
        super().__init__()
        n_in = len(lower)
        n = n_in if n_joints is None else n_joints
        self.n_joints = n
        span = np.maximum(np.asarray(upper) - np.asarray(lower), 1e-9)
        self.register_buffer("center", torch.tensor(0.5 * (np.asarray(upper) + np.asarray(lower)), dtype=torch.float64))
        self.register_buffer("half_span", torch.tensor(0.5 * span, dtype=torch.float64))
        self.register_buffer("target_mean", torch.tensor(target_mean, dtype=torch.float64))
        self.register_buffer("target_scale", torch.tensor(target_scale, dtype=torch.float64))
        axis = np.zeros(3) if joint1_axis is None else np.asarray(joint1_axis, dtype=float)
        self.register_buffer("axis", torch.tensor(axis, dtype=torch.float64))
        self.sincos = sincos
        self.turn = joint1_axis is not None
        self.body = build_body(arch, n_in + 2 * n if sincos else n_in)

    def features(self, q: torch.Tensor) -> torch.Tensor:
        # features in float64, then the float32 network: no quantisation of large joint values
        q64 = q.to(torch.float64)
        x = (q64 - self.center) / self.half_span
        if self.sincos:
            joints = q64[:, : self.n_joints]
            x = torch.cat([x, torch.sin(joints), torch.cos(joints)], dim=1)
        return x.to(torch.float32)

    @torch.jit.ignore
    def standardised(self, q: torch.Tensor) -> torch.Tensor:
        """The raw network output: the residual in the turning frame, standardised. Training fits this."""
        return self.body(self.features(q))

    @torch.jit.ignore
    def to_base(self, r: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Turn residuals from the joint-1 frame into the base frame (eager helper for tests)."""
        return self._turn(r, q)

    def _turn(self, r: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        if not self.turn:
            return r
        q1 = q[:, 0:1].to(torch.float64)
        k = self.axis.expand_as(r)
        kxr = torch.cross(k, r, dim=1)
        return r * torch.cos(q1) + kxr * torch.sin(q1) + k * (k * r).sum(1, keepdim=True) * (1.0 - torch.cos(q1))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        r = self.body(self.features(q)).to(torch.float64) * self.target_scale + self.target_mean
        return self._turn(r, q)


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
