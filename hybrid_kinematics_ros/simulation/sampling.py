"""Joint samples for calibration and test sets."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.simulation.errors import SimulationError


def joint_range(chain: Chain, fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The working range, shrunk about its middle to ``fraction`` of its width (continuous joints: ±π)."""
    if not 0.0 < fraction <= 1.0:
        raise SimulationError(f"range fraction must be in (0, 1], got {fraction}")
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * fraction
    return mid - half, mid + half


def sample_joints(chain: Chain, count: int, rng: np.random.Generator, fraction: float = 1.0) -> np.ndarray:
    """Pseudo-uniform joints ``(count, n)`` over the (reduced) working range."""
    if count < 1:
        raise SimulationError(f"the number of samples must be positive, got {count}")
    lo, hi = joint_range(chain, fraction)
    return rng.uniform(lo, hi, (count, chain.dof))
