"""The parametric stage as the served model rebuilds it from ``model.json``: its parameters and the
elastic chain they give. :mod:`hybrid_kinematics_ros.calibration.parametric` identifies them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import GRAVITY, ElasticChain, JointMap, bending_basis
from hybrid_kinematics_ros.model.errors import ModelError


@dataclass(frozen=True)
class Parameter:
    name: str
    kind: str
    index: int  # joint (elastic kinds, zero, harmonic) or frame (translation, rotation; n is the flange)
    component: int  # harmonic: 2 (f - 1) for sin(f q), 2 (f - 1) + 1 for cos(f q)


def build_model(
    chain: Chain,
    params: list[Parameter],
    values: np.ndarray,
    payload_mass: float,
    payload_com: np.ndarray,
    joint_map: JointMap | None = None,
    gravity: np.ndarray | None = None,
) -> ElasticChain:
    """The elastic chain for parameter ``values`` in SI units (one per entry of ``params``), and the joint
    error map if there is one. ``gravity``: m/s² in the base frame (None: −9.81 along z)."""
    n = chain.dof
    zero, compliance, cubic, signed, backlash = (np.zeros(n) for _ in range(5))
    bend_uv = np.zeros((n, 2))
    delta = np.zeros((n + 1, 6))
    k_max = max((p.component // 2 + 1 for p in params if p.kind == "harmonic"), default=0)
    cyclic = np.zeros((n, k_max, 2))
    for p, v in zip(params, values, strict=True):
        if p.kind == "harmonic":
            cyclic[p.index, p.component // 2, p.component % 2] = v
        elif p.kind == "zero":
            zero[p.index] = v
        elif p.kind == "compliance":
            compliance[p.index] = v
        elif p.kind == "cubic":
            cubic[p.index] = v
        elif p.kind == "signed":
            signed[p.index] = v
        elif p.kind == "backlash":
            backlash[p.index] = v
        elif p.kind == "bending":
            bend_uv[p.index, p.component] = v
        else:
            delta[p.index, p.component + (3 if p.kind == "rotation" else 0)] = v
    moved = se3.from_rotvec(delta[:, :3], delta[:, 3:])
    geometry = chain.with_geometry(chain.pre @ moved[:n], chain.post @ moved[n])
    bending = np.einsum("kc,kci->ki", bend_uv, bending_basis(chain))
    return ElasticChain(
        geometry,
        zero,
        compliance,
        bending,
        float(payload_mass),
        np.asarray(payload_com, float),
        joint_error=cyclic if np.any(cyclic) else None,
        joint_map=joint_map,
        cubic_compliance=cubic if np.any(cubic) else None,
        signed_compliance=signed if np.any(signed) else None,
        backlash=backlash if np.any(backlash) else None,
        gravity=GRAVITY.copy() if gravity is None else np.asarray(gravity, dtype=float),
    )


def model_from_manifest(chain: Chain, section: dict[str, Any], rigid: bool = False) -> ElasticChain:
    """Rebuild the identified elastic chain from ``model.json``'s ``parametric`` section.

    ``rigid``: the geometry-only fit instead (zero offsets and joint origins; what a URDF can carry, so
    without the joint error map).
    """
    try:
        params = [Parameter(p["name"], p["kind"], int(p["index"]), int(p["component"])) for p in section["parameters"]]
        values = np.array([float(p["rigid_value" if rigid else "value"]) for p in section["parameters"]])
        payload = section["payload"]
        joint_map = None if rigid or "joint_map" not in section else JointMap.from_manifest(section["joint_map"])
        if joint_map is not None and len(joint_map.lower) != chain.dof:
            raise ValueError(f"joint_map has {len(joint_map.lower)} joints, the chain {chain.dof}")
        gravity = payload.get("gravity")  # a section without a gravity vector: a floor mount
        return build_model(
            chain, params, values, float(payload["mass"]), np.asarray(payload["com"], float), joint_map, gravity
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"model.json: the parametric section is malformed ({exc!r})") from exc
