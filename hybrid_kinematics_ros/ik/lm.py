"""The damped least-squares core every IK stage runs: Levenberg-Marquardt on the 6-vector pose error, projected
onto the joint limits, with the rules that end a run which will not reach the target (a stall, a floor).

Which FK and Jacobian it runs on (the URDF model, the hybrid model, or the hybrid pose with the URDF
Jacobian) is the caller's choice, passed as one function. On the URDF model (:class:`ChainFkJac`) the same
loop runs compiled (``ik/lm_kernel.py``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from hybrid_kinematics_ros.ik import lm_kernel
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import Chain

FkJac = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
Limits = tuple[np.ndarray, np.ndarray, np.ndarray]  # lower, upper, revolute (bool)

# Hand-set: LM converges in a handful of steps from a good basin, so a run still STALL_COST ((m or rad)²)
# away after STALL_ITERATIONS steps is stuck and another seed is cheaper.
STALL_ITERATIONS = 12
STALL_COST = 1e-6
# A floor, not a solution (a target just beyond the model's reach; test_lm_stops_on_a_floor_beyond_reach):
# FLOOR_STEPS steps in a row that each keep more than FLOOR_RATIO of the cost, within STALL_COST of the target.
FLOOR_RATIO, FLOOR_STEPS = 0.98, 3
# A crawl (next to a wrist singularity LM from a table seed can creep towards the target for its whole
# iteration budget, and the restarts that would converge never run): near the target (cost under STALL_COST),
# a window of CRAWL_WINDOW steps that does not cut the cost CRAWL_GAIN times. Newton at an exact singularity
# halves the error per step (10⁶ in cost per window); a gain of 2 lets slow but steady runs through (chosen
# by bench_ik_arms, BENCHMARKS.md).
CRAWL_WINDOW, CRAWL_GAIN = 10, 2.0
# Marquardt's damping schedule: divide on a good step, multiply on a bad one, give up past LAMBDA_MAX.
LAMBDA_DOWN, LAMBDA_UP, LAMBDA_MIN, LAMBDA_MAX = 5.0, 8.0, 1e-12, 1e8
# the rules above as the compiled loop takes them (lm_kernel.lm_steps)
_CONSTANTS = np.array(
    [
        STALL_ITERATIONS,
        STALL_COST,
        CRAWL_WINDOW,
        CRAWL_GAIN,
        FLOOR_RATIO,
        FLOOR_STEPS,
        LAMBDA_DOWN,
        LAMBDA_UP,
        LAMBDA_MIN,
        LAMBDA_MAX,
    ],
    dtype=float,
)


def joint_limits(chain: Chain) -> Limits:
    """The chain's limits for the solvers: an unlimited joint gets ±2π (every angle, once)."""
    lower = np.where(np.isfinite(chain.lower), chain.lower, -2 * np.pi)
    upper = np.where(np.isfinite(chain.upper), chain.upper, 2 * np.pi)
    return lower, upper, chain.revolute


def turned(d: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """Joint differences ``d`` (``(..., n)``) with the revolute ones taken to within half a turn."""
    return np.where(revolute, (d + np.pi) % (2 * np.pi) - np.pi, d)


def wrap(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """Revolute joints past a limit wrapped by 2π where that lands inside; the rest as they are."""
    two_pi = 2.0 * np.pi
    q = np.where(revolute & (q > upper) & (q - two_pi >= lower), q - two_pi, q)
    return np.where(revolute & (q < lower) & (q + two_pi <= upper), q + two_pi, q)


def project(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """Into the limits: wrap revolute joints by 2π where that lands inside, clip the rest."""
    return np.clip(wrap(q, lower, upper, revolute), lower, upper)


class ChainFkJac:
    """A chain's URDF pose and Jacobian of one configuration, as :class:`LM`'s ``fk_jac``, which then runs
    its compiled loop (``ik/lm_kernel.py``) on the chain's kernel operands."""

    def __init__(self, chain: Chain) -> None:
        self.chain = chain
        self.operands = chain.kernel_operands

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return fk.fk_and_jacobian_single(self.chain, q)


# iterations per compiled call: the deadline is checked between calls (a few µs an iteration)
LM_CHUNK = 16


class LM(NamedTuple):
    """Levenberg-Marquardt on the pose error through ``fk_jac``, projected onto ``limits``
    ``(lower, upper, revolute)``: it stops within ``tol`` (m, rad) or after ``max_iterations``, and gives up
    early when it stalls far from the target, or when the cost settles on a floor above the tolerance (within a
    millimetre, a few steps that each gain under 2 %). ``damping`` is the starting λ: small when the seed is
    known to be close (Gauss-Newton steps at once). A variant is ``lm._replace(max_iterations=...)``."""

    fk_jac: FkJac
    limits: Limits
    tol: tuple[float, float]
    max_iterations: int
    damping: float = 1e-3

    def solve(
        self, target: np.ndarray, seed: np.ndarray, deadline: float, stop_crawl: bool = False
    ) -> tuple[np.ndarray, float, float, int]:
        """The joints from ``seed``, the position (m) and rotation (rad) errors, and the iterations used; none
        after ``deadline`` (``time.perf_counter``). ``stop_crawl``: also give up on a crawl (CRAWL_WINDOW), when
        other seeds are cheaper than waiting."""
        if isinstance(self.fk_jac, ChainFkJac):
            return self._compiled(target, seed, deadline, stop_crawl)
        return self._python(target, seed, deadline, stop_crawl)

    def _compiled(
        self, target: np.ndarray, seed: np.ndarray, deadline: float, stop_crawl: bool
    ) -> tuple[np.ndarray, float, float, int]:
        """The same loop compiled, LM_CHUNK iterations a call: the deadline between calls (a past one runs none)."""
        lower, upper, revolute = (np.ascontiguousarray(a) for a in self.limits)
        q = np.array(seed, dtype=float)
        state = np.array([self.damping, 0.0, 0.0, 0.0, 0.0, 0.0])
        target = np.ascontiguousarray(target, dtype=float)
        (tol_m, tol_rad), max_iterations = self.tol, self.max_iterations
        steps = 0 if time.perf_counter() > deadline else LM_CHUNK
        while True:
            e = lm_kernel.lm_steps(
                target, q, state, steps, lower, upper, revolute, tol_m, tol_rad, max_iterations, stop_crawl,
                _CONSTANTS, *self.fk_jac.operands,
            )  # fmt: skip
            if state[5] == lm_kernel.DONE or time.perf_counter() > deadline:
                return q, math.sqrt(e[:3] @ e[:3]), math.sqrt(e[3:] @ e[3:]), int(state[1])
            steps = LM_CHUNK

    def _python(
        self, target: np.ndarray, seed: np.ndarray, deadline: float, stop_crawl: bool
    ) -> tuple[np.ndarray, float, float, int]:
        """The loop in numpy, on any other ``fk_jac`` (the hybrid model's, the chord's)."""
        lower, upper, revolute = self.limits
        tol_m, tol_rad = self.tol
        q = project(seed, lower, upper, revolute)
        T, J = self.fk_jac(q)
        e = se3.error6(target, T)
        cost = e @ e
        lam = self.damping
        iterations = slow = 0
        window_cost = cost
        while iterations < self.max_iterations:
            if np.sqrt(e[:3] @ e[:3]) <= tol_m and np.sqrt(e[3:] @ e[3:]) <= tol_rad:
                break
            if time.perf_counter() > deadline or (iterations >= STALL_ITERATIONS and cost > STALL_COST):
                break
            if stop_crawl and iterations and iterations % CRAWL_WINDOW == 0:
                if cost < STALL_COST and cost * CRAWL_GAIN > window_cost:
                    break
                window_cost = cost
            iterations += 1
            jtj = J.T @ J
            step = np.linalg.solve(jtj + lam * (np.diag(np.diag(jtj)) + 1e-9 * np.eye(len(q))), J.T @ e)
            q_new = project(q + step, lower, upper, revolute)
            T_new, J_new = self.fk_jac(q_new)
            e_new = se3.error6(target, T_new)
            cost_new = e_new @ e_new
            if cost_new < cost:
                # a floor, not a solution: the target lies beyond this model's reach here, or in a local minimum
                slow = slow + 1 if cost_new > FLOOR_RATIO * cost and cost_new < STALL_COST else 0
                q, T, J, e, cost = q_new, T_new, J_new, e_new, cost_new
                lam = max(lam / LAMBDA_DOWN, LAMBDA_MIN)
                if slow >= FLOOR_STEPS:
                    break
            else:
                lam = lam * LAMBDA_UP
                if lam >= LAMBDA_MAX:
                    break
        return q, float(np.sqrt(e[:3] @ e[:3])), float(np.sqrt(e[3:] @ e[3:])), iterations
