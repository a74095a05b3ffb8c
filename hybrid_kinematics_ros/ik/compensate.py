"""Trajectory compensation ("filtering the program"): joints planned on the URDF, corrected so that the
calibrated robot reaches the poses the planner meant.

A planner (MoveIt, a teach pendant program) computes joints with the URDF; sent to the real robot, they
land where the hybrid model says, millimetres from the plan. Each planned point's URDF pose becomes the
target of the hybrid IK, started from the planned joints (the URDF's exact answer, on the plan's branch)
for all points at once; a point that does not converge there is solved on its own, seeded by the previous
corrected point. The timing (``time_from_start``) is kept; velocities and accelerations get the derivative of the
correction added, so they stay consistent with the new positions under the plan's own time profile (zero
at rest stays zero where the correction is constant).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.solver import IKResult, IKSolver
from hybrid_kinematics_ros.model.hybrid import HybridModel

# A calibration corrects millimetres, which costs the joints milliradians. A corrected point further than
# this from its planned one has jumped to another IK branch or sits at a singularity, where the robot
# could not follow it in the planned time.
MAX_JOINT_CORRECTION_RAD = 0.05


@dataclass
class Compensation:
    """Corrected joints ``(N, n)`` (rad or m) with velocities and accelerations (``None`` when the plan had
    none and fewer than 2 / 3 points make them), per-point hybrid FK errors against the plan's URDF poses,
    and the first point that could not be corrected (``failed_index`` -1: none)."""

    positions: np.ndarray
    velocities: np.ndarray | None
    accelerations: np.ndarray | None
    position_error_mm: np.ndarray
    orientation_error_deg: np.ndarray
    in_calibrated_range: np.ndarray
    failed_index: int = -1
    message: str = "ok"

    @property
    def success(self) -> bool:
        return self.failed_index < 0


def _derivative(values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Second-order finite differences on the (possibly uneven) time grid."""
    if len(t) < 2:
        return np.zeros_like(values)
    return np.gradient(values, t, axis=0, edge_order=2 if len(t) > 2 else 1)


def compensate(
    solver: IKSolver,
    positions: np.ndarray,
    times: np.ndarray,
    velocities: np.ndarray | None = None,
    accelerations: np.ndarray | None = None,
    require_calibrated_range: bool = False,
    max_joint_correction_rad: float = MAX_JOINT_CORRECTION_RAD,
) -> Compensation:
    """Correct a joint trajectory planned on the URDF so that the hybrid model follows its poses.

    Args:
        positions: ``(N, n)`` planned joints, in the model's joint order.
        times: ``(N,)`` seconds from the start, strictly increasing.
        velocities, accelerations: ``(N, n)`` the plan's, or None (then they are differentiated from the
            corrected positions).
        require_calibrated_range: a corrected point outside the calibrated range fails (policy ``refuse``).

    Raises:
        IKError: a malformed trajectory (shapes, non-finite values, times not increasing).
    """
    model = solver.model
    q_plan, t = _checked(positions, times, (velocities, accelerations), model.chain.dof)
    targets = model.fk(q_plan, analytic=True)
    # the plan is the URDF model's exact IK of its own poses: the hybrid solve starts there (batched Newton
    # chord); a point it does not converge gets a full solve seeded by the previous corrected point
    results = solver.solve_trajectory(targets, seed=q_plan[0], start=q_plan)
    q = np.array([r.q if r.q is not None else q_plan[i] for i, r in enumerate(results)])
    pos = np.array([r.position_error_mm for r in results])
    rot = np.array([r.orientation_error_deg for r in results])
    inside = np.array([bool(r.in_calibrated_range) for r in results])
    failed, message = -1, "ok"
    for i, r in enumerate(results):
        why = _why_not(model, r, (q[i], q_plan[i]), require_calibrated_range, max_joint_correction_rad)
        if why:
            failed, message = i, f"point {i} {why}"
            break
    vel = acc = None
    if velocities is not None:
        vel = np.asarray(velocities, dtype=float) + _derivative(q - q_plan, t)
    elif len(t) >= 2:
        vel = _derivative(q, t)
    if accelerations is not None:
        acc = np.asarray(accelerations, dtype=float) + _derivative(_derivative(q - q_plan, t), t)
    elif vel is not None and len(t) >= 3:
        acc = _derivative(vel, t)
    return Compensation(q, vel, acc, pos, rot, inside, failed, message)


def _checked(
    positions: np.ndarray, times: np.ndarray, rates: tuple[np.ndarray | None, np.ndarray | None], n: int
) -> tuple[np.ndarray, np.ndarray]:
    """The planned positions ``(N, n)`` and times ``(N,)`` as arrays, or an :class:`IKError` naming what is
    malformed (with the velocities and accelerations, ``rates``, where given)."""
    q_plan = np.asarray(positions, dtype=float)
    t = np.asarray(times, dtype=float)
    if q_plan.ndim != 2 or q_plan.shape[1] != n or len(q_plan) == 0:
        raise IKError(f"trajectory positions must be (N, {n}) with N >= 1, got {q_plan.shape}")
    if t.shape != (len(q_plan),):
        raise IKError(f"{len(q_plan)} points but {t.size} times")
    for name, arr in zip(("velocities", "accelerations"), rates, strict=True):
        if arr is not None and np.shape(arr) != q_plan.shape:
            raise IKError(f"trajectory {name} must be {q_plan.shape} like the positions, got {np.shape(arr)}")
    if not (np.all(np.isfinite(q_plan)) and np.all(np.isfinite(t))):
        raise IKError("trajectory has NaN or infinite positions or times")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise IKError(f"time_from_start must increase: point {i} at {t[i]:.6f} s is not after {t[i - 1]:.6f} s")
    return q_plan, t


def _why_not(
    model: HybridModel,
    result: IKResult,
    corrected_and_planned: tuple[np.ndarray, np.ndarray],
    require_calibrated_range: bool,
    max_rad: float,
) -> str:
    """Why a point's corrected configuration cannot be run ("" if it can): no hybrid solution, outside the
    calibrated range where that is refused, or a correction beyond ``max_rad`` on some joint."""
    q, planned = corrected_and_planned
    if not result.success:
        if require_calibrated_range and not result.in_calibrated_range:
            return f"lies outside the calibrated range ({model.describe_outside(q)})"
        return f"cannot be corrected: {result.message or 'no hybrid IK solution within the tolerance'}"
    step = float(np.abs(q - planned).max())
    if step > max_rad:
        return (
            f"needs a joint correction of {step:.3f} rad (more than {max_rad} rad): "
            "a singularity or another IK branch, which the robot could not follow in the planned time"
        )
    return ""
