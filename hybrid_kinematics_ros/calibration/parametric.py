"""The parametric stage: identify an elasto-geometric model from the pairs, before the residual nets.

Parameters (all small, starting from the nominal URDF):

- zero offsets of every joint;
- joint compliances against the gravity torques computed from the URDF inertials and the payload;
- link bending: a rotation per Nm of joint torque about the two axes perpendicular to each joint axis;
- a small rigid transform (x, y, z, rx, ry, rz) of every joint origin and of the flange.

Many of these are not identifiable from end-effector poses (a zero offset is the same as turning the joint
origin about the joint axis; parallel axes leave some translations free). Identifiability is decided by
QR with column pivoting of the scaled identification Jacobian; the free combinations are fixed at zero and
reported, with the parameters each one is equivalent to. The rest is fitted by scipy's ``least_squares``
with a robust loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain, bending_basis

ORIENTATION_LENGTH = 1.0  # m per rad: weighs orientation residuals against position residuals
RANK_TOLERANCE = 1e-6  # pivots below this fraction of the largest are unidentifiable
ROBUST_SCALE = 1e-3  # m: residuals well above this are down-weighted (soft L1)
# Scaled unit of each kind of parameter, in SI: what one unit of the optimiser's variable means.
SCALE = {"zero": 1e-3, "compliance": 1e-4, "bending": 1e-6, "translation": 1e-3, "rotation": 1e-3}
UNITS = {"zero": "rad", "compliance": "rad/Nm", "bending": "rad/Nm", "translation": "m", "rotation": "rad"}


@dataclass(frozen=True)
class Parameter:
    name: str
    kind: str
    index: int  # joint (zero, compliance, bending) or frame (translation, rotation; n is the flange)
    component: int


def parameter_list(chain: Chain) -> list[Parameter]:
    """Every candidate parameter, in the order pivoting prefers when two are equivalent (earlier wins)."""
    names = chain.joint_names
    out = [Parameter(f"zero offset {j}", "zero", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"compliance {j}", "compliance", k, 0) for k, j in enumerate(names)]
    out += [Parameter(f"bending {j} {c}", "bending", k, i) for k, j in enumerate(names) for i, c in enumerate("uv")]
    frames = [f"origin {j}" for j in names] + ["flange"]
    for k, frame in enumerate(frames):
        out += [Parameter(f"{frame} {c}", "translation", k, i) for i, c in enumerate("xyz")]
        out += [Parameter(f"{frame} r{c}", "rotation", k, i) for i, c in enumerate("xyz")]
    return out


def build_model(
    chain: Chain, params: list[Parameter], values: np.ndarray, payload_mass: float, payload_com: np.ndarray
) -> ElasticChain:
    """The elastic chain for parameter ``values`` in SI units (one per entry of ``params``)."""
    n = chain.dof
    zero, compliance, bend_uv = np.zeros(n), np.zeros(n), np.zeros((n, 2))
    delta = np.zeros((n + 1, 6))
    for p, v in zip(params, values, strict=True):
        if p.kind == "zero":
            zero[p.index] = v
        elif p.kind == "compliance":
            compliance[p.index] = v
        elif p.kind == "bending":
            bend_uv[p.index, p.component] = v
        else:
            delta[p.index, p.component + (3 if p.kind == "rotation" else 0)] = v
    moved = se3.from_rotvec(delta[:, :3], delta[:, 3:])
    geometry = chain.with_geometry(chain.pre @ moved[:n], chain.post @ moved[n])
    bending = np.einsum("kc,kci->ki", bend_uv, bending_basis(chain))
    return ElasticChain(geometry, zero, compliance, bending, float(payload_mass), np.asarray(payload_com, float))


def pose_residuals(
    model: ElasticChain, q: np.ndarray, T: np.ndarray, position_only: bool, target: np.ndarray | None = None
) -> np.ndarray:
    """``(N, 3)`` or ``(N, 6)``: measured minus modelled position (m), then rotation (rad × 1 m).

    Position-only: ``T`` holds measured points at ``target`` (m, tip frame; None: the tip itself).
    """
    pred = model.fk(q)
    if position_only:
        return T[:, :3, 3] - se3.point_at(pred, target)
    dp = T[:, :3, 3] - pred[:, :3, 3]
    w = se3.rotvec(T[:, :3, :3] @ np.swapaxes(pred[:, :3, :3], 1, 2))
    return np.concatenate([dp, ORIENTATION_LENGTH * w], axis=1)


@dataclass
class ParametricResult:
    model: ElasticChain
    params: list[Parameter]
    values: np.ndarray  # SI, zero where unidentifiable
    rigid_values: np.ndarray  # the best fit without compliance and bending: what a URDF can carry
    identifiable: np.ndarray  # bool per parameter
    reasons: dict[str, str]  # unidentifiable parameter name -> why
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    position_only: bool

    def manifest(self) -> dict[str, Any]:
        m = self.model
        return {
            "payload": {"mass": m.payload_mass, "com": m.payload_com.tolist()},
            "position_only": self.position_only,
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "parameters": [
                {
                    "name": p.name,
                    "kind": p.kind,
                    "index": p.index,
                    "component": p.component,
                    "unit": UNITS[p.kind],
                    "value": float(v),
                    "rigid_value": float(r),
                    "identifiable": bool(ok),
                    **({"reason": self.reasons[p.name]} if p.name in self.reasons else {}),
                }
                for p, v, r, ok in zip(self.params, self.values, self.rigid_values, self.identifiable, strict=True)
            ],
        }


def model_from_manifest(chain: Chain, section: dict[str, Any], rigid: bool = False) -> ElasticChain:
    """Rebuild the identified elastic chain from ``model.json``'s ``parametric`` section.

    ``rigid``: the geometry-only fit instead (zero offsets and joint origins; what a URDF can carry).
    """
    try:
        params = [Parameter(p["name"], p["kind"], int(p["index"]), int(p["component"])) for p in section["parameters"]]
        values = np.array([float(p["rigid_value" if rigid else "value"]) for p in section["parameters"]])
        payload = section["payload"]
        return build_model(chain, params, values, float(payload["mass"]), np.asarray(payload["com"], float))
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"model.json: the parametric section is malformed ({exc!r})") from exc


def _rms(res: np.ndarray) -> dict[str, float]:
    out = {"position_mm": float(1e3 * np.sqrt(np.mean(np.sum(res[:, :3] ** 2, axis=1))))}
    if res.shape[1] == 6:
        out["orientation_deg"] = float(np.degrees(np.sqrt(np.mean(np.sum(res[:, 3:] ** 2, axis=1)))))
    return out


def identify(
    chain: Chain,
    q: np.ndarray,
    T: np.ndarray,
    payload_mass: float = 0.0,
    payload_com: np.ndarray | None = None,
    position_only: bool = False,
    max_pairs: int = 5000,
    seed: int = 0,
    target: np.ndarray | None = None,
) -> ParametricResult:
    """Identify the elasto-geometric parameters from joints ``q (N, n)`` and measured base-frame poses ``T``.

    Position-only: ``T`` holds the measured target points and ``target`` (m, ``(3,)`` or ``(N, 3)``) their
    offset in the tip frame, which makes the flange's rotation observable.

    At most ``max_pairs`` pairs (drawn reproducibly) enter the fit: a few thousand pin down the ~80
    parameters far below the tracker noise, and the cost grows with the count.
    """
    com = np.zeros(3) if payload_com is None else np.asarray(payload_com, dtype=float)
    if len(q) < 20:
        raise CalibrationError(f"only {len(q)} pairs: the parametric stage needs at least 20")
    pick = np.random.default_rng(seed).permutation(len(q))[:max_pairs]
    q_fit, T_fit = q[pick], T[pick]
    if target is not None and np.ndim(target) == 2:  # one offset per pair (several tracker stations)
        target = np.asarray(target)[pick]
    params = parameter_list(chain)
    scale = np.array([SCALE[p.kind] for p in params])

    def residual(z: np.ndarray, active: np.ndarray) -> np.ndarray:
        values = np.zeros(len(params))
        values[active] = z * scale[active]
        model = build_model(chain, params, values, payload_mass, com)
        return pose_residuals(model, q_fit, T_fit, position_only, target).ravel()

    everything = np.ones(len(params), dtype=bool)
    r0 = residual(np.zeros(len(params)), everything)
    step = 1e-3
    jac = np.empty((len(r0), len(params)))
    for i in range(len(params)):
        z = np.zeros(len(params))
        z[i] = step
        jac[:, i] = (residual(z, everything) - r0) / step
    active, reasons = _identifiable(jac, params, position_only)

    def solve(subset: np.ndarray, start: np.ndarray):
        return least_squares(
            residual, start, args=(subset,), loss="soft_l1", f_scale=ROBUST_SCALE, x_scale="jac", max_nfev=30
        )

    fit = solve(active, np.zeros(int(active.sum())))
    values = np.zeros(len(params))
    values[active] = fit.x * scale[active]
    model = build_model(chain, params, values, payload_mass, com)
    # The same without compliance and bending, for a URDF export: the geometry then absorbs what it can.
    geometric = active & np.array([p.kind not in ("compliance", "bending") for p in params])
    rigid_values = np.zeros(len(params))
    rigid_values[geometric] = solve(geometric, values[geometric] / scale[geometric]).x * scale[geometric]
    width = 3 if position_only else 6
    return ParametricResult(
        model=model,
        params=params,
        values=values,
        rigid_values=rigid_values,
        identifiable=active,
        reasons=reasons,
        rms_before=_rms(r0.reshape(-1, width)),
        rms_after=_rms(fit.fun.reshape(-1, width)),
        position_only=position_only,
    )


def _identifiable(jac: np.ndarray, params: list[Parameter], position_only: bool) -> tuple[np.ndarray, dict]:
    """Which parameters to fit, and why the others are not identifiable.

    Columns are taken in the order of ``params`` (Gram-Schmidt, i.e. QR in that order): a column that
    adds less than ``RANK_TOLERANCE`` of its norm to the span of those already kept depends on them, so
    of two equivalent parameters the earlier, more meaningful one (a zero offset, say) is kept.
    """
    norms = np.linalg.norm(jac, axis=0)
    what = "positions" if position_only else "poses"
    reasons: dict[str, str] = {}
    basis = np.zeros((jac.shape[0], 0))
    kept: list[int] = []
    for j, p in enumerate(params):
        if norms[j] <= RANK_TOLERANCE * norms.max():
            reasons[p.name] = f"does not change the measured {what}"
            continue
        col = jac[:, j] / norms[j]
        for _ in range(2):  # re-orthogonalise once: classical Gram-Schmidt loses orthogonality otherwise
            col = col - basis @ (basis.T @ col)
        if np.linalg.norm(col) > RANK_TOLERANCE:
            basis = np.column_stack([basis, col / np.linalg.norm(col)])
            kept.append(j)
            continue
        coef = np.linalg.lstsq(jac[:, kept], jac[:, j], rcond=None)[0]  # in the scaled units of each
        top = np.argsort(-np.abs(coef))[:3]
        terms = ", ".join(f"{coef[i]:+.3g} × {params[kept[i]].name}" for i in top if abs(coef[i]) > 1e-3)
        reasons[p.name] = f"same effect as {terms}"
    active = np.zeros(len(params), dtype=bool)
    active[kept] = True
    return active, reasons
