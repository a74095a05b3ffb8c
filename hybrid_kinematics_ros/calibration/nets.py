"""Residual networks: joints in radians in, a residual 3-vector in SI units out.

Everything a caller needs is inside the module, so a saved TorchScript file is self-contained:
min-max normalisation of the joints, optional ``sin``/``cos`` features, the network, de-standardisation
of the output, and (optionally) turning the residual from a frame that rotates with joint 1 back into
the base frame. Gravity does not change when the robot turns about a vertical joint 1, so in that frame
the residual hardly depends on ``q1`` and is easier to learn.

Condition channels (temperature, say) are extra input columns after the joints: min-max normalised like
them, without ``sin``/``cos`` features. The input is then ``(B, n + k)``; :class:`HybridModel` appends the
current values. A net can be built to ignore some of them (``ignored``: their half span is infinite, so they
enter as exactly zero), which is how the training ladder tries a net without a channel it was offered, and
:meth:`ResidualNet.drop_inputs` then takes a channel that no net uses out of the input.

An ensemble (``members`` > 1) averages the standardised outputs of several bodies of the same
architecture, trained from different seeds: on a few thousand noisy real pairs one net's error on unseen
poses depends on its seed, and the average of a few depends on it much less.

Architectures are named: the paper's ``D1``, ``D4``, ``D4w``, ``D4W`` (ReLU MLPs) and ``Rw``, ``Rd``
(ResNets of dense and identity blocks after Chen et al.), and ``mlp:WxD[:act]`` for plain MLPs.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass

import numpy as np
import torch
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


class Ensemble(nn.Module):
    """The mean of several bodies' outputs."""

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = [member(x) for member in self.members]
        return torch.stack(out).mean(dim=0)


def _input_layers(body: nn.Module) -> list[nn.Linear]:
    """The linear layers that read a body's features: an MLP's first, each member's in an ensemble, a ResNet's
    first block's main path and projection shortcut."""
    if isinstance(body, Ensemble):
        return [layer for member in body.members for layer in _input_layers(member)]
    first = body[0]
    if isinstance(first, nn.Linear):
        return [first]
    if isinstance(first, _ResBlock) and isinstance(first.shortcut, nn.Sequential):
        return [first.main[0], first.shortcut[0]]
    raise CalibrationError(f"cannot take inputs out of a body that starts with {type(first).__name__}")


@dataclass(frozen=True)
class InputSpan:
    """A net's input columns: each normalised over ``lower`` … ``upper``; the first ``n_joints`` (None: all)
    are joints, the rest condition channels; ``ignored``: condition columns the net does not read (they
    normalise to exactly zero)."""

    lower: np.ndarray
    upper: np.ndarray
    n_joints: int | None = None
    ignored: tuple[int, ...] = ()


class ResidualNet(nn.Module):
    """Joints ``(B, n)`` rad (any float dtype), then any condition columns, to a residual ``(B, 3)`` float64
    in m or rad. ``inputs``: its input columns (:class:`InputSpan`); ``target``: the residuals' mean and scale
    (m or rad), which the body's output is standardised by."""

    def __init__(
        self,
        arch: str,
        inputs: InputSpan,
        target: tuple[np.ndarray, np.ndarray],
        sincos: bool = True,
        joint1_axis: np.ndarray | None = None,
        members: int = 1,
    ) -> None:
        super().__init__()
        lower, upper, ignored = np.asarray(inputs.lower), np.asarray(inputs.upper), inputs.ignored
        n_in = len(lower)
        n = n_in if inputs.n_joints is None else inputs.n_joints
        self.n_joints = n
        if any(not n <= c < n_in for c in ignored):
            raise CalibrationError(f"ignored input columns {list(ignored)}: only condition columns ({n}-{n_in - 1})")
        span = np.maximum(upper - lower, 1e-9)
        span[list(ignored)] = np.inf  # (x - centre) / inf = 0: the column cannot change the output
        self.register_buffer("center", torch.tensor(0.5 * (upper + lower), dtype=torch.float64))
        self.register_buffer("half_span", torch.tensor(0.5 * span, dtype=torch.float64))
        self.register_buffer("target_mean", torch.tensor(target[0], dtype=torch.float64))
        self.register_buffer("target_scale", torch.tensor(target[1], dtype=torch.float64))
        axis = np.zeros(3) if joint1_axis is None else np.asarray(joint1_axis, dtype=float)
        self.register_buffer("axis", torch.tensor(axis, dtype=torch.float64))
        self.sincos = sincos
        self.turn = joint1_axis is not None
        width = n_in + 2 * n if sincos else n_in
        self.body = (
            build_body(arch, width) if members == 1 else Ensemble([build_body(arch, width) for _ in range(members)])
        )

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

    def _turn(self, r: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Residuals from the joint-1 frame into the base frame: the torch twin of ``model.nets.AxisTurn``."""
        if not self.turn:
            return r
        q1 = q[:, 0:1].to(torch.float64)
        k = self.axis.expand_as(r)
        kxr = torch.cross(k, r, dim=1)
        return r * torch.cos(q1) + kxr * torch.sin(q1) + k * (k * r).sum(1, keepdim=True) * (1.0 - torch.cos(q1))

    @torch.jit.ignore
    def drop_inputs(self, columns: tuple[int, ...]) -> None:
        """Take condition columns the net ignores (``ignored`` at construction) out of its input, in place: the
        input is then ``(B, n + k - len(columns))``, and every output is unchanged, since those columns entered
        the first layers as exactly zero."""
        columns = tuple(sorted(set(columns)))
        if not columns:
            return
        span = self.half_span.numpy()
        if any(c < self.n_joints or c >= len(span) or np.isfinite(span[c]) for c in columns):
            raise CalibrationError(f"input columns {list(columns)}: only condition columns the net ignores can go")
        keep = [c for c in range(len(span)) if c not in columns]
        features = keep + list(range(len(span), len(span) + (2 * self.n_joints if self.sincos else 0)))
        with torch.no_grad():
            for layer in _input_layers(self.body):
                layer.weight = nn.Parameter(layer.weight[:, features].clone())
                layer.in_features = len(features)
        self.center = self.center[keep].clone()
        self.half_span = self.half_span[keep].clone()

    @torch.jit.ignore
    def silence(self) -> None:
        """Correct nothing: every output exactly zero (the scale and mean of the output are zeroed)."""
        with torch.no_grad():
            self.target_scale.zero_()
            self.target_mean.zero_()

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        r = self.body(self.features(q)).to(torch.float64) * self.target_scale + self.target_mean
        return self._turn(r, q)
