"""The closed forms' fixed point through the hybrid model (the solver's module docstring, 2.): the closed forms
solve the target moved by the hybrid correction at the current answer, round after round, until the correction
stops changing; then the hybrid pose is the target. Near the target a round is Newton's chord step on the URDF
Jacobian instead. Compiled arithmetic per round: :mod:`~hybrid_kinematics_ros.ik.round_kernel`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.ik import round_kernel
from hybrid_kinematics_ros.ik import seeds as seeding
from hybrid_kinematics_ros.ik.analytic import AnalyticIK
from hybrid_kinematics_ros.model.hybrid import HybridModel

# The hybrid corrections move a solution by milliradians and change little
# over that, so each round cuts the error by orders of magnitude; a round costs one hybrid FK.
FIXED_POINT_ROUNDS = 12
# A least-squares round (the compensated target beyond the URDF model's reach) that cuts the error by less than
# this has stalled: the branch does not reach the target (at the fold where it does, the error halves each round).
# The rule does not apply to exact rounds, which can rise before they fall.
STALLED = 0.9
# Within this of the target (m, rad) a round is a Newton step on the URDF Jacobian instead of a closed-form
# call and a compensated target: the step is microradians, over which the URDF model's curvature errs by
# 1e-10 m, below the polish tolerance, so both rounds converge alike and the step costs half.
LINEAR_M = LINEAR_RAD = 1e-5
# (Newton's steps on the hybrid Jacobian would save a round, but the nets' Jacobians cost more than the round.)
COARSE, PRECISE = "coarse", "precise"  # what a fixed point's round asks for


@dataclass(frozen=True)
class FixedPoint:
    """The fixed point over one ``model`` (its conditions and approach directions) with its ``closed_form``:
    rounds stop within ``tol`` (m, rad), after one round more where the answer is not yet within ``polish``
    (the refiner's ``polish_tol``); steps stay within ``lower`` … ``upper``."""

    model: HybridModel
    closed_form: AnalyticIK
    tol: tuple[float, float]
    polish: tuple[float, float]
    lower: np.ndarray
    upper: np.ndarray

    def one(
        self, target: np.ndarray, q0: np.ndarray, deadline: float, rounds: int = FIXED_POINT_ROUNDS
    ) -> tuple[np.ndarray, tuple[float, float] | None, bool]:
        """The hybrid solution from ``q0`` through the closed forms alone, each round on
        the branch nearest the last answer (near a singularity that can be another: every round is checked on
        the hybrid FK):
        ``q = IK(compensated_target(q))`` on the branch; at the fixed point hybrid(q) = target. Where the
        compensated target lies beyond the URDF model's reach, the round takes the closed forms' nearest
        least-squares answer instead.
        Returns the round nearest the target (``q0`` if none comes nearer), its hybrid errors (mm, deg), and
        whether it stalled beyond the branch's reach: after a least-squares round
        the error fell by less than STALLED, so the branch's nearest point to the target is found, and the
        branch has no hybrid solution here. It stops within ``tol``, after one round more where the answer is
        not yet within ``polish``."""
        return self.many(target, [q0], deadline, rounds)[0]  # one start: every round on fk_single

    def many(
        self, target: np.ndarray, starts: list[np.ndarray], deadline: float, rounds: int = FIXED_POINT_ROUNDS
    ) -> list[tuple[np.ndarray, tuple[float, float] | None, bool]]:
        """:meth:`one` from each of ``starts`` side by side, their rounds in step: the hybrid FK of the
        rounds before a Newton step (errors of a millimetre, then a micrometre) in one batch, a few times
        cheaper than one configuration at a time; the rounds after one, where the answer is judged against the
        polish tolerance, one at a time on the same path as :meth:`one` (a batch's float32 products differ
        by a nanometre)."""
        runs = [self._rounds(target, q, deadline, rounds) for q in starts]
        results: list = [None] * len(runs)
        pending = {i: next(run) for i, run in enumerate(runs)}  # each run's next (q, what) to evaluate
        while pending:
            coarse = [i for i, (_, what) in pending.items() if what == COARSE]
            poses = {}
            if len(coarse) > 1:
                poses = dict(zip(coarse, self.model.fk(np.array([pending[i][0] for i in coarse])), strict=True))
            asked, pending = pending, {}
            for i, (q, _) in asked.items():
                answer = poses[i] if i in poses else self.model.fk_single(q)
                try:
                    pending[i] = runs[i].send(answer)
                except StopIteration as done:
                    results[i] = done.value
        return results

    def _rounds(self, target: np.ndarray, q0: np.ndarray, deadline: float, rounds: int):
        """:meth:`one`'s rounds as a coroutine: yields ``(q, what)``, the configuration whose hybrid
        pose it needs next and how (COARSE; PRECISE after a Newton step, where the answer is judged against
        the polish tolerance), is sent that pose, and returns what :meth:`one` returns. The closed forms
        cut the error ~100× a round (the nets' slope is what they leave out); within LINEAR_M the rounds are
        Newton's chord steps on the URDF Jacobian, which cut it as much."""
        tol_m, tol_rad = self.tol
        polish_m, polish_rad = self.polish
        best, best_cost, best_errors, best_hybrid, q = q0, np.inf, None, None, q0
        least_squares = converged = stepped = False
        newton = True
        urdf = self.model.chain.kernel_operands
        ask = COARSE
        for round_ in range(rounds + 1):
            hybrid = yield q, ask
            # the error, and the compensated target the round needs unless it stops here, in one call
            e, moved = round_kernel.error_and_compensated(target, hybrid, np.ascontiguousarray(q), *urdf)
            ep, er = math.sqrt(e[:3] @ e[:3]), math.sqrt(e[3:] @ e[3:])
            cost = math.hypot(ep, er)  # m and rad, as LM weighs them
            stalled = least_squares and cost > STALLED * best_cost
            if cost < best_cost:
                best, best_cost, best_errors, best_hybrid = q, cost, (1e3 * ep, float(np.degrees(er))), hybrid
            elif stepped:  # the Newton step went uphill (a near-singular Jacobian): closed-form rounds from the best
                newton = False
                q, hybrid = best, best_hybrid
            if ep <= tol_m and er <= tol_rad:
                if converged or (ep <= polish_m and er <= polish_rad):
                    break
                converged = True  # one round more (POLISH_SHARE)
            if stalled:
                return best, best_errors, True
            if round_ == rounds or time.perf_counter() > deadline:
                break
            stepped = newton and ep < LINEAR_M and er < LINEAR_RAD
            if stepped:
                q_next = self.newton_step(q, e)
                if q_next is not None:
                    q, ask = q_next, PRECISE
                    continue
                stepped = False
            q_next = self.closed_form.nearest(moved, q)
            least_squares = q_next is None
            if least_squares:  # beyond the URDF model's reach: its nearest answer on this branch
                near_answers = self.closed_form.approximations(moved, q, seeding.NEAR_M, seeding.NEAR_RAD)
                q_next = near_answers[0] if len(near_answers) else None
            if q_next is None:
                break
            q, ask = q_next, COARSE
        return best, best_errors, False

    def newton_step(self, q: np.ndarray, e: np.ndarray) -> np.ndarray | None:
        """``q`` moved by Newton's chord step for the hybrid error ``e`` (6,) on the URDF model's Jacobian at
        ``q``, within the limits; None where it is singular. Compiled (the closed forms' chains have six joints,
        so the Jacobian is square)."""
        urdf = self.model.chain.kernel_operands
        q_next = round_kernel.chord_step(np.ascontiguousarray(q), e, *urdf, self.lower, self.upper)
        return q_next if len(q_next) else None
