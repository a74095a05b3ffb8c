"""From a classical (URDF-model) answer to the hybrid model's: refinement through the hybrid FK.

The paper's stage 2 is a bounded least-squares problem with the joints in a small box around the
classical answer ``q0`` and the hybrid FK in the cost. Here a projected Levenberg-Marquardt solves it with
Newton's chord method first (the hybrid pose, the URDF Jacobian: one hybrid FK per step), then with the
hybrid Jacobian. The two Jacobians differ by the derivative of a millimetre-sized correction, so each chord
step still cuts the error ~1000×, and costs one hybrid FK instead of the nets' Jacobians. It is several times
faster than scipy's ``least_squares`` on the same box (bench_ik, BENCHMARKS.md); scipy's solve stays in
:mod:`hybrid_kinematics_ros.ik.baselines`.

Near a singularity the hybrid answer can lie beyond the box; the box then moves, and damped LM on the
hybrid model over the whole joint range finishes (:meth:`HybridRefiner.unbounded`).
"""

from __future__ import annotations

import copy
import time

import numpy as np

from hybrid_kinematics_ros.ik.lm import LM, FkJac, Limits, project
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.se3 import error6_batch
from hybrid_kinematics_ros.model.hybrid import HybridModel

# From a classical answer Gauss-Newton converges in a handful of chord steps; a run that needs more than
# CHORD_ITERATIONS is stuck. GAUSS_NEWTON_DAMPING: q0 is close, so full steps from the start.
CHORD_ITERATIONS = 12
GAUSS_NEWTON_DAMPING = 1e-9
BRANCH_DAMPING = 1e-6  # the other branches' unbounded chord and hybrid LM
# Hybrid LM steps (each a hybrid Jacobian): at an exact singularity the error only halves per step, and the
# fallback branches need that many to converge there.
HYBRID_LM_ITERATIONS = 40
BOX_BUDGET_SHARE = 0.25  # of the per-solution budget, for each LM pass inside one box
# The box's LM aims at a thousandth of the success tolerances: its answer is then well inside them even
# where the float32 nets evaluate a pose slightly differently in a batch.
BOX_TOLERANCE_SHARE = 1e-3
# The solvers' own iterations stop at a tenth of the success tolerances.
INNER_TOLERANCE_SHARE = 0.1
# The closed forms' fixed point and the trajectories' chord steps, each step ~1000x nearer, take one step more
# where a converged answer is not yet within a tenth of that, so that answers sit well inside the tolerances
# (one hybrid FK more for the answers that need it).
POLISH_SHARE = 0.1
RECENTRED_BOXES = 1  # a box that ends on its edge moves to the new point once
BATCH_CHORD_STEPS = 8  # trajectories: chord steps on all poses at once before single solves take over


def chord(model: HybridModel) -> FkJac:
    """Newton's chord method: the hybrid pose with the URDF model's Jacobian."""
    return lambda q: (model.fk_single(q), model.fk_and_jacobian_single(q, analytic=True)[1])


class HybridRefiner:
    """The hybrid refinement of one model at given success tolerances (mm, deg) and box width (rad)."""

    def __init__(
        self,
        model: HybridModel,
        limits: Limits,
        position_tolerance_mm: float,
        orientation_tolerance_deg: float,
        width_rad: float,
        timeout_s: float,
    ) -> None:
        self.model = model
        self.limits = limits
        self.tolerances = (position_tolerance_mm, orientation_tolerance_deg)
        self.width_rad = width_rad
        self.timeout_s = timeout_s
        self.chord = chord(model)
        # where the solver's own iterations stop, in m and rad
        self.inner_tol = (
            INNER_TOLERANCE_SHARE * 1e-3 * position_tolerance_mm,
            float(np.radians(orientation_tolerance_deg)) * INNER_TOLERANCE_SHARE,
        )
        self.polish_tol = (POLISH_SHARE * self.inner_tol[0], POLISH_SHARE * self.inner_tol[1])

    def with_model(self, model: HybridModel) -> HybridRefiner:
        """This refinement over ``model``, another value of the same calibration (other condition values)."""
        clone = copy.copy(self)
        clone.model = model
        clone.chord = chord(model)
        return clone

    def errors(self, q: np.ndarray, target: np.ndarray, analytic: bool = False) -> tuple[float, float]:
        """Position (mm) and orientation (deg) errors of the model's pose at ``q``."""
        pos, rot = se3.pose_errors(self.model.fk_single(q, analytic=analytic)[None], target[None])
        return float(pos[0]), float(rot[0])

    def refine(self, target: np.ndarray, q0: np.ndarray, deadline: float = float("inf")) -> tuple[np.ndarray, dict]:
        """Bounded least squares through the hybrid FK in a box around ``q0``.

        Near a singularity the hybrid answer can lie outside the box; when the solve ends on the box's
        edge short of the tolerance, the box moves to the new point (RECENTRED_BOXES times at most).
        ``info`` carries ``errors`` (mm, deg) when the solve has just evaluated them at the answer.
        """
        q, info = self.box(target, q0, deadline)
        boxes = 1
        while boxes <= RECENTRED_BOXES and "errors" not in info and time.perf_counter() < deadline:
            pos, rot = self.errors(q, target)
            on_edge = np.abs(q - q0).max() >= self.width_rad * 0.999
            if not on_edge or (pos <= self.tolerances[0] and rot <= self.tolerances[1]):
                break
            q0 = q
            q, more = self.box(target, q0, deadline)
            info["nfev"] += more["nfev"]
            boxes += 1
        info["boxes"] = boxes
        return q, info

    def box_bounds(self, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``q0`` inside the limits, and the box around it (clipped to the limits)."""
        lower, upper, _ = self.limits
        q0 = np.clip(q0, lower, upper)
        return q0, np.maximum(lower, q0 - self.width_rad), np.minimum(upper, q0 + self.width_rad)

    def box(self, target: np.ndarray, q0: np.ndarray, deadline: float = float("inf")) -> tuple[np.ndarray, dict]:
        """One bounded solve in the box around ``q0``: projected LM with the chord Jacobian, then, near a
        singularity where the chord's approximation is too coarse, with the hybrid model's own."""
        q0, lo, hi = self.box_bounds(q0)
        tol_m = BOX_TOLERANCE_SHARE * self.tolerances[0] * 1e-3
        tol_rad = np.radians(self.tolerances[1]) * BOX_TOLERANCE_SHARE
        box = (lo, hi, np.zeros(len(q0), dtype=bool))  # clip to the box, never wrap by 2π
        used = 0
        for fk_jac in (self.chord, self.model.fk_and_jacobian_single):
            lm = LM(fk_jac, box, (tol_m, tol_rad), CHORD_ITERATIONS, GAUSS_NEWTON_DAMPING)
            q, ep, er, it = lm.solve(target, q0, min(time.perf_counter() + BOX_BUDGET_SHARE * self.timeout_s, deadline))
            used += it
            if ep <= tol_m and er <= tol_rad:
                return q, {"nfev": used, "status": 0, "method": "lm", "errors": (1e3 * ep, float(np.degrees(er)))}
            q0 = q
        # the answer beyond the box (near a singularity) no solver reaches in the same box; unbounded() can
        return q, {"nfev": used, "status": 3, "method": "lm"}

    def unbounded(
        self, target: np.ndarray, q: np.ndarray, deadline: float, chord_first: bool = False
    ) -> tuple[np.ndarray, float, float]:
        """Damped LM on the hybrid model over the whole joint range (the bounded boxes crawl near a
        singularity). ``chord_first``: the cheaper start of the fallback branches, chord steps (one hybrid FK
        each) with light damping before the hybrid Jacobian. Returns the joints and the errors (m, rad)."""
        tol_m, tol_rad = self.inner_tol
        hybrid = LM(self.model.fk_and_jacobian_single, self.limits, self.inner_tol, HYBRID_LM_ITERATIONS)
        if not chord_first:
            q, ep, er, _ = hybrid.solve(target, q, deadline)
            return q, ep, er
        chord = LM(self.chord, self.limits, self.inner_tol, CHORD_ITERATIONS, BRANCH_DAMPING)
        for lm in (chord, hybrid._replace(damping=BRANCH_DAMPING)):
            q, ep, er, _ = lm.solve(target, q, deadline)
            if ep <= tol_m and er <= tol_rad:
                break
        return q, ep, er

    def batch_chord(self, targets: np.ndarray, q: np.ndarray, conditions: np.ndarray | None = None) -> np.ndarray:
        """Newton's chord method on all poses at once through the batched hybrid FK; ``q`` ``(N, n)`` is
        updated in place; ``conditions`` ``(N, k)``: the nets' condition channels per pose (else the current
        values). Returns the errors ``(N, 2)`` (mm, deg) of the converged poses, inf elsewhere."""
        tol_m, tol_rad = self.inner_tol
        polish_m, polish_rad = self.polish_tol
        errors = np.full((len(targets), 2), np.inf)
        active = np.arange(len(targets))
        converged = np.zeros(len(targets), dtype=bool)  # within the inner tolerance once: one step more at most
        for step in range(BATCH_CHORD_STEPS):
            T = self.model.fk(q[active], conditions=None if conditions is None else conditions[active])
            e = error6_batch(targets[active], T)
            ep, er = np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)
            inside = (ep <= tol_m) & (er <= tol_rad)
            polished = (ep <= polish_m) & (er <= polish_rad)
            done = inside & (polished | converged[active] | (step == BATCH_CHORD_STEPS - 1))
            converged[active] |= inside
            errors[active[done]] = np.column_stack([1e3 * ep[done], np.degrees(er[done])])
            active, e = active[~done], e[~done]
            if not len(active):
                break
            _, J = self.model.fk_and_jacobian(q[active], analytic=True)
            jt = J.mT
            step = np.linalg.solve(jt @ J + 1e-12 * np.eye(J.shape[2]), (jt @ e[:, :, None]))[:, :, 0]
            q[active] = project(q[active] + step, *self.limits)
        return errors
