"""The ground-truth robot of the virtual cell: the URDF chain plus the effects an analytic model lacks.

Effects, each switchable in the robot YAML's ``truth`` section and drawn reproducibly from its seed:

- geometric: every joint origin (and the flange) is off by a small rigid transform, and every joint has
  a zero offset;
- gear: joint-angle periodic transmission errors at harmonics 1 and 2;
- compliance: gravity torques from the segment masses (URDF inertials) and the payload, turned into joint
  deflections by torsional springs that stiffen with load, ``δ = τ / (k (1 + c (τ/τ_ref)²))``;
- bending: a rotation about an axis perpendicular to each joint, proportional to the joint's torque.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain, bending_basis
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig
from hybrid_kinematics_ros.simulation.errors import SimulationError


def _small_transforms(rng: np.random.Generator, count: int, translation_m: float, rotation_rad: float) -> np.ndarray:
    """Random rigid transforms whose translation and rotation norms are about the given sizes."""
    out = np.tile(np.eye(4), (count, 1, 1))
    out[:, :3, 3] = rng.normal(0.0, translation_m / np.sqrt(3.0), (count, 3))
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, rotation_rad / np.sqrt(3.0), (count, 3))).as_matrix()
    return out


def _section(truth: dict[str, Any], name: str) -> dict[str, Any]:
    section = truth.get(name) or {}
    if not isinstance(section, dict):
        raise SimulationError(f"truth.{name} must be a mapping, got {section!r}")
    return section


def _per_joint(value: Any, n: int, field: str) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=float), (n,)) if np.ndim(value) == 0 else np.asarray(value, float)
    if arr.shape != (n,):
        raise SimulationError(f"{field} needs one value or {n} values, got {value!r}")
    return np.array(arr)


@dataclass(frozen=True)
class TrueRobot:
    """A seeded ground-truth robot. ``fk(q)`` maps commanded joints to the pose the robot really reaches.

    It is an :class:`ElasticChain` (perturbed geometry, zero offsets, stiffening compliance, bending) whose
    joints also carry gear errors: the parametric calibration stage can model all but the last two.
    """

    nominal: Chain
    elastic: ElasticChain
    gear_amplitude: np.ndarray  # (n, 2) rad, harmonics 1 and 2
    gear_phase: np.ndarray  # (n, 2) rad

    @classmethod
    def from_config(
        cls, cfg: RobotConfig, seed: int | None = None, enabled: dict[str, bool] | None = None
    ) -> TrueRobot:
        """Build from the YAML ``truth`` section; ``enabled`` overrides each effect's switch (tests use it)."""
        truth = cfg.truth
        chain = cfg.chain
        n = chain.dof
        rng = np.random.default_rng(truth.get("seed", 0) if seed is None else seed)

        def on(name: str) -> bool:
            if enabled is not None and name in enabled:
                return enabled[name]
            return bool(_section(truth, name).get("enabled", False))

        geo = _section(truth, "geometric")
        pre_delta = _small_transforms(
            rng, n + 1, 1e-3 * float(geo.get("translation_mm", 0.3)), np.radians(float(geo.get("rotation_deg", 0.03)))
        )
        zero = rng.normal(0.0, np.radians(float(geo.get("zero_offset_deg", 0.02))), n)
        actual = chain.with_geometry(chain.pre @ pre_delta[:n], chain.post @ pre_delta[n]) if on("geometric") else chain
        if not on("geometric"):
            zero = np.zeros(n)

        gear = _section(truth, "gear")
        amp1 = np.radians(_per_joint(gear.get("amplitude_deg", 0.005), n, "truth.gear.amplitude_deg"))
        # Random draws happen whatever the switches say, so one effect's switch never changes another's values.
        gear_amplitude = np.column_stack([amp1, 0.5 * amp1]) * rng.uniform(0.5, 1.0, (n, 2))
        gear_phase = rng.uniform(0.0, 2 * np.pi, (n, 2))
        if not on("gear"):
            gear_amplitude = np.zeros((n, 2))

        comp = _section(truth, "compliance")
        stiffness = _per_joint(comp.get("stiffness_nm_per_rad", 1e5), n, "truth.compliance.stiffness_nm_per_rad")
        if np.any(stiffness <= 0):
            raise SimulationError("truth.compliance.stiffness_nm_per_rad must be positive")
        compliance = 1.0 / stiffness if on("compliance") else np.zeros(n)

        bend = _section(truth, "bending")
        bending = _per_joint(bend.get("rad_per_nm", 1e-6), n, "truth.bending.rad_per_nm")
        if not on("bending"):
            bending = np.zeros(n)
        bending_axes = bending_basis(chain)[:, 0]

        elastic = ElasticChain(
            actual,
            zero,
            compliance,
            bending[:, None] * bending_axes,
            cfg.payload_mass,
            cfg.payload_com,
            cubic_ratio=float(comp.get("cubic_ratio", 0.0)),
            torque_ref=float(comp.get("torque_ref_nm", 100.0)),
            gravity=cfg.gravity,
        )
        return cls(nominal=chain, elastic=elastic, gear_amplitude=gear_amplitude, gear_phase=gear_phase)

    @property
    def actual(self) -> Chain:
        """The nominal chain with the perturbed joint origins and flange."""
        return self.elastic.chain

    def gear_error(self, q: np.ndarray) -> np.ndarray:
        harmonics = np.stack([q, 2.0 * q], axis=-1) + self.gear_phase
        return np.sum(self.gear_amplitude * np.sin(harmonics), axis=-1)

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        return self.elastic.gravity_torques(q)

    def effective_joints(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint values the links really reach (offsets, gear errors, deflections) and the gravity torques."""
        q = fk.check_joints(self.nominal, q)
        return self.elastic.effective_joints(q + self.gear_error(q))

    def fk(self, q: np.ndarray) -> np.ndarray:
        """True tip poses ``(B, 4, 4)`` for commanded joints ``(B, n)``."""
        q = fk.check_joints(self.nominal, q)
        return self.elastic.fk(q + self.gear_error(q))
