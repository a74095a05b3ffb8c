"""A laser tracker: measures a flange-mounted target in its own frame, with Gaussian noise.

``T_meas = T_base_tracker⁻¹ · T_tip · T_flange_target · noise``. With both frames at identity (the
default), measurements are tip poses in the robot's base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import transform_from_xyz_rpy


@dataclass(frozen=True)
class Tracker:
    """Noise is a per-axis standard deviation: position in m, orientation (rotation vector) in rad."""

    position_noise: float = 15e-6
    orientation_noise: float = np.radians(0.001)
    base_to_tracker: np.ndarray = field(default_factory=lambda: np.eye(4))
    flange_to_target: np.ndarray = field(default_factory=lambda: np.eye(4))
    frame_id: str = ""  # empty: the robot's base link (both frames at identity)

    @classmethod
    def from_config(cls, tracker: dict[str, Any], noise: bool = True) -> Tracker:
        frames = "base_to_tracker" in tracker or "flange_to_target" in tracker
        return cls(
            position_noise=1e-3 * float(tracker.get("position_noise_mm", 0.015)) if noise else 0.0,
            orientation_noise=np.radians(float(tracker.get("orientation_noise_deg", 0.001))) if noise else 0.0,
            base_to_tracker=transform_from_xyz_rpy(tracker.get("base_to_tracker"), "tracker.base_to_tracker"),
            flange_to_target=transform_from_xyz_rpy(tracker.get("flange_to_target"), "tracker.flange_to_target"),
            frame_id="tracker" if frames else "",
        )

    def measure(self, tip: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Measured target poses ``(B, 4, 4)`` in the tracker frame for true tip poses ``(B, 4, 4)``."""
        out = se3.inverse(self.base_to_tracker) @ np.asarray(tip) @ self.flange_to_target
        count = len(out)
        noise = np.tile(np.eye(4), (count, 1, 1))
        noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, self.orientation_noise, (count, 3))).as_matrix()
        out = out @ noise
        out[:, :3, 3] += rng.normal(0.0, self.position_noise, (count, 3))
        return out
