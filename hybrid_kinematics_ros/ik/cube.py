"""The ISO 9283 test cube as joint waypoints: its centre and eight corners around a tip pose, reached through
the URDF model's IK (the simulated cell's ``cube`` pattern)."""

from __future__ import annotations

import numpy as np

from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.model.hybrid import HybridModel


def cube_waypoints(chain: Chain, centre_q: np.ndarray, side_m: float = 0.3) -> np.ndarray:
    """ISO 9283 cube: centre and 8 corners around the tip pose at ``centre_q``, orientation kept."""
    solver = IKSolver(HybridModel.analytic_only(chain), IKOptions(timeout_s=0.5)).warm_up()
    centre = fk.fk_single(chain, centre_q)
    out = [np.asarray(centre_q, dtype=float)]
    half = side_m / 2
    for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
        target = centre.copy()
        target[:3, 3] += half * corner
        result = solver.solve(target, out[-1], analytic=True)
        if not result.success:
            raise IKError(f"cube corner {corner * half} m is not reachable from the centre; use a smaller side")
        out.append(result.q)
    return np.array(out)
