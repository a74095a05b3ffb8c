"""The hybrid model: analytic FK from the URDF, corrected by the residual nets of a model directory.

``p = p_model + Δp(q)`` and ``R = exp(ω(q)) · R_model`` (paper Fig. 2). Without nets it is the analytic
model, so nodes and IK use one type whether or not a calibration exists.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.nets import NumpyResidual
from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.model_dir import load_model_dir
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf


def _skew(w: np.ndarray) -> np.ndarray:
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return out


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for one rotation vector (scipy's batch machinery costs ~10 µs per call)."""
    theta = float(np.sqrt(w @ w))
    k = _skew(w)
    if theta < 1e-8:
        return np.eye(3) + k + 0.5 * (k @ k)
    return np.eye(3) + (np.sin(theta) / theta) * k + ((1.0 - np.cos(theta)) / theta**2) * (k @ k)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """``(B, 3, 3)``: maps d(ω) to the angular velocity of ``exp(ω)`` in the base frame."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _skew(w)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * k + b * (k @ k)


class HybridModel:
    def __init__(
        self,
        chain: Chain,
        nets: dict[str, torch.jit.ScriptModule] | None = None,
        manifest: dict[str, Any] | None = None,
        path: Path | None = None,
    ) -> None:
        self.chain = chain
        self.nets = dict(nets or {})
        self.manifest = dict(manifest or {})
        self.path = path
        self._fast = {kind: NumpyResidual.from_module(net) for kind, net in self.nets.items()}
        rng = self.manifest.get("trained_range")
        self.trained_lower = np.asarray(rng["lower"], dtype=float) if rng else chain.lower
        self.trained_upper = np.asarray(rng["upper"], dtype=float) if rng else chain.upper

    @classmethod
    def load(
        cls, path: str | Path, expect_urdf: str | None = None, expect_joint_names: tuple[str, ...] | None = None
    ) -> HybridModel:
        """Load a model directory; refuse it if it was trained for another URDF or other joints.

        Raises:
            DataError: missing, corrupt or mismatched files, with the file named.
        """
        files = load_model_dir(path)
        m = files.manifest
        chain = chain_from_urdf(files.urdf_text, m["base_link"], m["tip_link"])
        chain = chain.with_tool(np.asarray(m["tool"], dtype=float))
        chain = chain.with_limits(m["joint_limits"]["lower"], m["joint_limits"]["upper"])
        if tuple(m["joint_names"]) != chain.joint_names:
            raise DataError(
                f"{files.path}: model.json joints {m['joint_names']} differ from the URDF's chain "
                f"{list(chain.joint_names)}"
            )
        if expect_urdf is not None:
            expected = chain_from_urdf(expect_urdf, m["base_link"], m["tip_link"])
            if expected.urdf_sha256 != m["urdf_sha256"]:
                raise DataError(
                    f"{files.path} was trained for another URDF (sha256 {m['urdf_sha256'][:12]}…, "
                    f"given {expected.urdf_sha256[:12]}…); retrain or use the matching URDF"
                )
        if expect_joint_names is not None and tuple(expect_joint_names) != chain.joint_names:
            raise DataError(
                f"{files.path} was trained for joints {list(chain.joint_names)}, not {list(expect_joint_names)}"
            )
        return cls(chain, files.nets, m, Path(path))

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.chain.joint_names

    @property
    def has_orientation(self) -> bool:
        return "orientation" in self.nets

    def in_calibrated_range(self, q: np.ndarray) -> np.ndarray:
        """``(B,)`` True where every joint lies inside the range the nets were trained on."""
        q = np.atleast_2d(q)
        return np.all((q >= self.trained_lower - 1e-9) & (q <= self.trained_upper + 1e-9), axis=1)

    def residuals(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Δp, ω)``, each ``(B, 3)`` in m and rad; zeros where a net is absent."""
        qt = torch.as_tensor(np.atleast_2d(q), dtype=torch.float64)
        zeros = np.zeros((qt.shape[0], 3))
        with torch.no_grad():
            dp = self.nets["position"](qt).numpy() if "position" in self.nets else zeros
            w = self.nets["orientation"](qt).numpy() if "orientation" in self.nets else zeros
        return dp, w

    def correct(self, T: np.ndarray, dp: np.ndarray, w: np.ndarray) -> np.ndarray:
        out = np.array(T, dtype=float, copy=True)
        out[:, :3, 3] += dp
        if self.has_orientation:
            out[:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ out[:, :3, :3]
        return out

    def fk(self, q: np.ndarray, analytic: bool = False) -> np.ndarray:
        """Tip poses ``(B, 4, 4)``: hybrid, or the URDF model alone when ``analytic``."""
        q = fk.check_joints(self.chain, q)
        T = fk.fk(self.chain, q)
        if analytic or not self.nets:
            return T
        return self.correct(T, *self.residuals(q))

    def fk_single(self, q: np.ndarray, analytic: bool = False) -> np.ndarray:
        """One pose ``(4, 4)`` on the low-overhead path: numpy FK and, for MLP nets, numpy inference."""
        q = np.asarray(q, dtype=float)
        T = fk.fk_single(self.chain, q)
        if analytic or not self.nets:
            return T
        if not all(self._fast.values()):
            return self.correct(T[None], *self.residuals(q[None]))[0]
        if "position" in self._fast:
            T[:3, 3] += self._fast["position"](q)
        if "orientation" in self._fast:
            T[:3, :3] = _exp_so3(self._fast["orientation"](q)) @ T[:3, :3]
        return T

    def fk_and_jacobian(self, q: np.ndarray, analytic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(B, 4, 4)`` and the geometric Jacobian ``(B, 6, n)`` of the hybrid (or analytic) model.

        The nets' part comes from autograd through the TorchScript modules.
        """
        q = fk.check_joints(self.chain, q)
        T, J = fk.fk_and_jacobian(self.chain, q)
        if analytic or not self.nets:
            return T, J
        qt = torch.tensor(q, requires_grad=True)
        grads, values = {}, {}
        for kind, net in self.nets.items():
            out = net(qt)
            rows = [torch.autograd.grad(out[:, i].sum(), qt, retain_graph=i < 2)[0] for i in range(3)]
            grads[kind] = torch.stack(rows, dim=1).numpy()
            values[kind] = out.detach().numpy()
        zeros = np.zeros((len(q), 3))
        dp, w = values.get("position", zeros), values.get("orientation", zeros)
        hybrid = self.correct(T, dp, w)
        J = J.copy()
        if "position" in grads:
            J[:, :3] += grads["position"]
        if "orientation" in grads:
            r = Rotation.from_rotvec(w).as_matrix()
            # p = p_m + Δp is unchanged by the rotation; the angular part is ω_R = R ω_m + J_l(ω) dω/dq
            J[:, 3:] = r @ J[:, 3:] + left_jacobian_so3(w) @ grads["orientation"]
        return hybrid, J

    def fk_and_jacobian_single(self, q: np.ndarray, analytic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """One configuration: pose ``(4, 4)`` and geometric Jacobian ``(6, n)``, numpy throughout for MLP nets."""
        q = np.asarray(q, dtype=float)
        T, J = fk.fk_and_jacobian_single(self.chain, q)
        if analytic or not self.nets:
            return T, J
        if not all(self._fast.values()):
            T, J = self.fk_and_jacobian(q[None])
            return T[0], J[0]
        if "position" in self._fast:
            dp, ddp = self._fast["position"].value_and_jacobian(q)
            T[:3, 3] += dp
            J[:3] += ddp
        if "orientation" in self._fast:
            w, dw = self._fast["orientation"].value_and_jacobian(q)
            r = _exp_so3(w)
            T[:3, :3] = r @ T[:3, :3]
            J[3:] = r @ J[3:] + left_jacobian_so3(w) @ dw
        return T, J

    @classmethod
    def analytic_only(cls, chain: Chain) -> HybridModel:
        return cls(chain)
