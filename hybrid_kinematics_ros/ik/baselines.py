"""The methods bench_ik compares ours against; nothing at run time uses them.

- The paper's stage 2 as published: scipy's bounded ``least_squares`` in the box around the classical
  answer, with the paper's eq. 2 (the 12 matrix elements, translation in mm) or our 6-vector (position in
  mm, rotation vector scaled to mm) as the cost (:func:`scipy_refine_solver`).
- Wang et al. [26] as the paper adapted it: analytic IK of a target compensated by the nets' error
  (:func:`wang_baseline`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.lm import joint_limits
from hybrid_kinematics_ros.ik.refine import HybridRefiner
from hybrid_kinematics_ros.ik.solver import IKOptions, IKResult, IKSolver, SolveRequest, compensated_target
from hybrid_kinematics_ros.kinematics.se3 import error6
from hybrid_kinematics_ros.model.hybrid import HybridModel

COSTS = ("pose6", "eq2")
SCIPY_EVALUATIONS = 60  # scipy's budget per box: up to 60 hybrid Jacobians
_EQ2_SCALE = np.array([[1.0, 1.0, 1.0, 1e3]] * 3)  # eq. 2's rows 1-3, translation in mm


def eq2_residual(target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Paper eq. 2 as a residual: the 12 differences of the top three rows, translation in mm. Its squared
    norm is the paper's cost."""
    return ((np.asarray(target) - np.asarray(T))[:3] * _EQ2_SCALE).ravel()


class ScipyRefiner(HybridRefiner):
    """The box solved by scipy's trust-region reflective ``least_squares``, as in the paper."""

    def __init__(self, *args: object, cost: str = "pose6", rotation_scale_mm: float = 1000.0) -> None:
        """``args`` as :class:`HybridRefiner`; ``rotation_scale_mm``: pose6's mm of residual per radian."""
        if cost not in COSTS:
            raise IKError(f"cost must be one of {', '.join(COSTS)}, got '{cost}'")
        super().__init__(*args)
        self.eq2 = cost == "eq2"
        self.scale = np.array([1e3, 1e3, 1e3, rotation_scale_mm, rotation_scale_mm, rotation_scale_mm])

    def residual(self, target: np.ndarray) -> tuple[Callable, Callable]:
        """The cost's residual (mm-scaled) of the joints, and its Jacobian, through the hybrid FK."""
        model, scale = self.model, self.scale

        def fun(q: np.ndarray) -> np.ndarray:
            T = model.fk_single(q)
            return eq2_residual(target, T) if self.eq2 else scale * error6(target, T)

        def jac(q: np.ndarray) -> np.ndarray:
            T, J = model.fk_and_jacobian_single(q)
            if not self.eq2:
                return -scale[:, None] * J
            d = np.empty((3, 4, len(q)))
            d[:, :3, :] = np.cross(J[3:, None, :], T[:3, :3, None], axis=0)  # ∂R/∂q_j = [ω_j]× R
            d[:, 3, :] = J[:3]
            return -(d * _EQ2_SCALE[..., None]).reshape(12, len(q))

        return fun, jac

    def box(self, target: np.ndarray, q0: np.ndarray, deadline: float = float("inf")) -> tuple[np.ndarray, dict]:
        q0, lo, hi = self.box_bounds(q0)
        fun, jac = self.residual(target)
        sol = least_squares(
            fun,
            q0,
            jac=jac,
            bounds=(lo, hi),
            method="trf",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=SCIPY_EVALUATIONS,
            x_scale=1.0,
        )
        return sol.x, {"nfev": int(sol.nfev), "status": int(sol.status)}


def scipy_refine_solver(
    model: HybridModel, options: IKOptions | None = None, cost: str = "pose6", rotation_scale_mm: float = 1000.0
) -> IKSolver:
    """Our solver with the paper's refinement: scipy's bounded least squares on ``cost`` ("pose6" or "eq2"),
    without the closed forms' fixed point, which would solve before the refinement is reached."""
    o = replace(options or IKOptions(), closed_form=False)
    limits = joint_limits(model.chain)
    tolerances = (o.position_tolerance_mm, o.orientation_tolerance_deg, o.refine_width_rad, o.timeout_s)
    refiner = ScipyRefiner(model, limits, *tolerances, cost=cost, rotation_scale_mm=rotation_scale_mm)
    return IKSolver(model, o, refiner).warm_up()


def wang_baseline(
    solver: IKSolver, target: np.ndarray, seed: np.ndarray | None = None, iterations: int = 1
) -> IKResult:
    """Wang et al. [26]: ``T_comp = T_target · (T_hybrid(q)⁻¹ · T_analytic(q))`` at the current answer, then
    analytic IK again, ``iterations`` times."""
    start = time.perf_counter()
    target, seed = solver.check(target, seed)
    deadline = start + solver.options.timeout_s * (iterations + 1)
    q, *_ = solver.classical(target, seed, deadline)
    for _ in range(iterations):
        q, *_ = solver.classical(compensated_target(solver.model, target, q), q, deadline)
    return solver.result(SolveRequest(target, seed, None, False, start, deadline), q, {"method": "wang"})
