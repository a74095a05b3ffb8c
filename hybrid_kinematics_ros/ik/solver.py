"""Inverse kinematics through the hybrid model (paper section 3, Fig. 3), and past it.

1. A classical iterative IK on the analytic chain (Levenberg-Marquardt with the analytic Jacobian, joint
   limits enforced) from a seed; the seed decides which solution is found. If the seed fails, restarts
   follow within the time budget from a table of configurations whose poses lie nearest the target (a
   k-d tree over 4,096 quasi-random configurations, built once), then from random ones.
2. The hybrid refinement: bounded least squares with the joints in a small box around the classical
   answer ``q0``; the cost compares the target with the **hybrid** FK. By default a projected
   Levenberg-Marquardt solves it with Newton's chord method (the hybrid pose, the URDF Jacobian: one
   hybrid FK per step), then with the hybrid Jacobian; ``refine="scipy"`` is the paper's scipy
   ``least_squares``, with either the paper's eq. 2 (12 matrix elements, translation in mm) or a 6-vector
   (position in mm, rotation vector scaled to mm). Near a singularity the hybrid answer can lie beyond
   the box; damped LM on the hybrid model over the whole joint range then finishes.
3. When the seed's branch has no hybrid solution near it (near a singularity the nets' tenths of a
   millimetre move the solution by tenths of a radian, or the target lies just beyond the URDF model's
   reach), the other analytic branches follow: classical answers from the table's nearest
   configurations, each finished by unbounded LM on the hybrid model, until one reaches the target or
   the budget ends. A near miss at a near-singular configuration first restarts along the Jacobian's
   weak direction, where the hybrid near-solutions form a valley with local minima.

Several solutions come from several seeds, deduplicated modulo 2π on revolute joints (keeping the
representative nearest the seed) and ordered by distance to the seed. Every result says whether it
reached the target; a miss is never returned as a success.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.stats import qmc

from hybrid_kinematics_ros.calibration.hybrid import HybridModel
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.kinematics import fk, se3

FkJac = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class IKOptions:
    position_tolerance_mm: float = 1e-4  # success thresholds on the hybrid-FK error
    orientation_tolerance_deg: float = 1e-4
    refine_width_rad: float = 0.02  # half width of the box around q0 (paper: "a small interval")
    cost: str = "pose6"  # "pose6" or "eq2"
    rotation_scale_mm: float = 1000.0  # pose6: mm of residual per radian of rotation error
    max_iterations: int = 100  # classical stage, per seed
    timeout_s: float = 0.05  # per solution, restarts included
    restarts: bool = True
    seed_table: bool = True  # restart from the configurations whose poses lie nearest the target
    # box refinement: "lm" (projected LM, chord then exact Jacobian), "lm+scipy" (then scipy's least_squares
    # if LM misses inside the box), or "scipy" (the paper's bounded least squares alone)
    refine: str = "lm"
    require_calibrated_range: bool = False  # True: a solution outside the trained range fails


@dataclass
class IKResult:
    success: bool
    q: np.ndarray | None
    position_error_mm: float = float("inf")
    orientation_error_deg: float = float("inf")
    message: str = ""
    seconds: float = 0.0
    in_calibrated_range: bool = True
    stats: dict = field(default_factory=dict)


def _log_so3(r: np.ndarray) -> np.ndarray:
    """Rotation vector of one rotation matrix; accurate near zero, scipy near π."""
    skew = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = 0.5 * np.sqrt(skew @ skew)
    c = 0.5 * (np.trace(r) - 1.0)
    angle = np.arctan2(s, c)
    if angle < 1e-9:
        return 0.5 * skew
    if angle > 3.0:
        return se3.rotvec(r[None])[0]
    return angle / (2.0 * s) * skew


def _error6(target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``[p_t − p; log(R_t Rᵀ)]`` in m and rad, base frame."""
    return np.concatenate([target[:3, 3] - T[:3, 3], _log_so3(target[:3, :3] @ T[:3, :3].T)])


def project(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """Into the limits: wrap revolute joints by 2π where that lands inside, clip the rest."""
    two_pi = 2.0 * np.pi
    q = np.where(revolute & (q > upper) & (q - two_pi >= lower), q - two_pi, q)
    q = np.where(revolute & (q < lower) & (q + two_pi <= upper), q + two_pi, q)
    return np.clip(q, lower, upper)


TABLE_SIZE = 4096
TABLE_RESTARTS = 16
ROTATION_LENGTH = 0.3  # m: weight of the rotation matrix entries against the position in the table metric


def _pose_features(T: np.ndarray) -> np.ndarray:
    """``(B, 12)``: position and scaled rotation entries; Euclidean distance ~ pose distance."""
    return np.concatenate([T[:, :3, 3], ROTATION_LENGTH * T[:, :3, :3].reshape(-1, 9)], axis=1)


NEAR_M, NEAR_RAD = 5e-3, 1e-2  # a URDF-model answer this close to a hybrid target is the hybrid one's basin
STALL_ITERATIONS = 12  # LM converges in a handful of steps from a good basin; a slow run is stuck
STALL_COST = 1e-6  # (m or rad)²: still this far after STALL_ITERATIONS means another seed is cheaper
FLOOR_RATIO, FLOOR_STEPS = 0.98, 3  # steps gaining under 2 % each, this many in a row: a floor
BRANCH_RAD = 1e-2  # classical answers closer than this on every joint are one branch
SEARCH_SHARE = 0.5  # of a solve_many request's total budget, for the seed search; refinement gets the rest
CLASSICAL_SHARE = 0.5  # of the budget, for the seed's classical stage; the other branches get the rest
VALLEY_MM, VALLEY_SINGULAR = 0.1, 1e-2  # a near miss (mm) at a near-singular Jacobian (smallest singular value)
VALLEY_STEPS_RAD = (-0.7, 0.7, -1.2, 1.2)  # along the weak direction; a local minimum there is this far off
HYBRID_LM_ITERATIONS = 40  # at ~0.27 ms per hybrid Jacobian; enough to halve the error 40 times


def lm_solve(
    fk_jac: FkJac,
    target: np.ndarray,
    seed: np.ndarray,
    limits: tuple[np.ndarray, np.ndarray, np.ndarray],
    tol_m: float,
    tol_rad: float,
    max_iterations: int,
    deadline: float,
    damping: float = 1e-3,
) -> tuple[np.ndarray, float, float, int]:
    """Levenberg-Marquardt on the pose error, projected onto the joint limits.

    ``limits`` is ``(lower, upper, revolute)``. Returns the joints, the position (m) and rotation (rad)
    errors, and the iterations used. Gives up early when it stalls far from the target, or when the cost
    settles on a floor above the tolerance (within a millimetre, a few steps that each gain under 2 %).
    """
    lower, upper, revolute = limits
    q = project(seed, lower, upper, revolute)
    T, J = fk_jac(q)
    e = _error6(target, T)
    cost = e @ e
    lam = damping
    iterations = slow = 0
    while iterations < max_iterations:
        if np.sqrt(e[:3] @ e[:3]) <= tol_m and np.sqrt(e[3:] @ e[3:]) <= tol_rad:
            break
        if time.perf_counter() > deadline or (iterations >= STALL_ITERATIONS and cost > STALL_COST):
            break
        iterations += 1
        jtj = J.T @ J
        step = np.linalg.solve(jtj + lam * (np.diag(np.diag(jtj)) + 1e-9 * np.eye(len(q))), J.T @ e)
        q_new = project(q + step, lower, upper, revolute)
        T_new, J_new = fk_jac(q_new)
        e_new = _error6(target, T_new)
        cost_new = e_new @ e_new
        if cost_new < cost:
            # a floor, not a solution: the target lies beyond this model's reach here, or in a local minimum
            slow = slow + 1 if cost_new > FLOOR_RATIO * cost and cost_new < STALL_COST else 0
            q, T, J, e, cost = q_new, T_new, J_new, e_new, cost_new
            lam = max(lam / 5.0, 1e-12)
            if slow >= FLOOR_STEPS:
                break
        else:
            lam = lam * 8.0
            if lam >= 1e8:
                break
    return q, float(np.sqrt(e[:3] @ e[:3])), float(np.sqrt(e[3:] @ e[3:])), iterations


class IKSolver:
    """IK of a :class:`HybridModel` (hybrid, or analytic with ``analytic=True``)."""

    def __init__(self, model: HybridModel, options: IKOptions | None = None) -> None:
        self.model = model
        self.options = options or IKOptions()
        if self.options.cost not in ("pose6", "eq2"):
            raise IKError(f"cost must be 'pose6' or 'eq2', got '{self.options.cost}'")
        if self.options.refine not in ("lm", "lm+scipy", "scipy"):
            raise IKError(f"refine must be 'lm', 'lm+scipy' or 'scipy', got '{self.options.refine}'")
        chain = model.chain
        self.lower = np.where(np.isfinite(chain.lower), chain.lower, -2 * np.pi)
        self.upper = np.where(np.isfinite(chain.upper), chain.upper, 2 * np.pi)
        self.limits = (self.lower, self.upper, chain.revolute)
        # a tenth of the success tolerances, in m and rad: where the solver's own iterations stop
        o = self.options
        self.inner_tol = (1e-4 * o.position_tolerance_mm, float(np.radians(o.orientation_tolerance_deg)) * 0.1)
        self._analytic = lambda q: model.fk_and_jacobian_single(q, analytic=True)
        # Newton's chord method: the hybrid pose with the URDF model's Jacobian. The two Jacobians differ
        # by the derivative of a millimetre-sized correction, so each step still cuts the error ~1000×,
        # and a step costs one hybrid FK instead of the nets' Jacobians.
        self._chord = lambda q: (model.fk_single(q), model.fk_and_jacobian_single(q, analytic=True)[1])
        self._rng = np.random.default_rng(0)
        # deterministic spread seeds for several solutions, and the restart table
        sampler = qmc.Halton(d=chain.dof, seed=0)
        self.spread = qmc.scale(sampler.random(64), self.lower, self.upper)
        self.table = qmc.scale(sampler.random(TABLE_SIZE), self.lower, self.upper)
        self._tree = cKDTree(_pose_features(fk.fk(chain, self.table)))

    # ------------------------------------------------------------------ checks
    def _check(self, target: np.ndarray, seed: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        target = np.asarray(target, dtype=float)
        if target.shape != (4, 4) or not np.all(np.isfinite(target)):
            raise IKError("the target must be a finite 4x4 homogeneous matrix")
        r = target[:3, :3]
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise IKError("the target's rotation is not orthonormal")
        dof = self.model.chain.dof
        seed = self.model.chain.mid_limits() if seed is None else np.asarray(seed, dtype=float)
        if seed.shape != (dof,) or not np.all(np.isfinite(seed)):
            raise IKError(f"the seed must have {dof} finite joint values, got {seed.shape}")
        return target, seed

    def errors(self, q: np.ndarray, target: np.ndarray, analytic: bool = False) -> tuple[float, float]:
        pos, rot = se3.pose_errors(self.model.fk_single(q, analytic=analytic)[None], target[None])
        return float(pos[0]), float(rot[0])

    # ------------------------------------------------------------------ stages
    def classical(self, target: np.ndarray, seed: np.ndarray, deadline: float):
        """Stage 1 from one seed, then restarts while time remains (if enabled)."""
        o = self.options
        fk_jac = self._analytic
        tol_m, tol_rad = self.inner_tol
        best = None
        attempt_seed = seed
        attempts = 0
        nearest = iter(self.nearest_seeds(target, TABLE_RESTARTS) if o.seed_table else ())
        while True:
            attempts += 1
            q, ep, er, _ = lm_solve(
                fk_jac, target, attempt_seed, self.limits, tol_m, tol_rad, o.max_iterations, deadline
            )
            if best is None or ep + er < best[1] + best[2]:
                best = (q, ep, er)
            if ep <= tol_m and er <= tol_rad:
                break
            if not o.restarts or time.perf_counter() > deadline:
                break
            attempt_seed = next(nearest, None)
            if attempt_seed is None:
                attempt_seed = self._rng.uniform(self.lower, self.upper)
        return best[0], best[1], best[2], attempts

    def nearest_seeds(self, target: np.ndarray, k: int) -> np.ndarray:
        """The ``k`` table configurations whose (analytic) poses lie nearest ``target``."""
        _, index = self._tree.query(_pose_features(target[None])[0], k=k)
        return self.table[np.atleast_1d(index)]

    def refine(
        self, target: np.ndarray, q0: np.ndarray, recentre: int = 1, deadline: float = float("inf")
    ) -> tuple[np.ndarray, dict]:
        """Stage 2: bounded least squares through the hybrid FK in a box around ``q0``.

        Near a singularity the hybrid answer can lie outside the box; when the solve ends on the box's
        edge short of the tolerance, the box moves to the new point (at most ``recentre`` times).
        """
        q, info = self._refine_box(target, q0, deadline)
        boxes = 1
        while boxes <= recentre and "errors" not in info and time.perf_counter() < deadline:
            pos, rot = self.errors(q, target)
            on_edge = np.abs(q - q0).max() >= self.options.refine_width_rad * 0.999
            if not on_edge or (
                pos <= self.options.position_tolerance_mm and rot <= self.options.orientation_tolerance_deg
            ):
                break
            q0 = q
            q, more = self._refine_box(target, q0, deadline)
            info["nfev"] += more["nfev"]
            boxes += 1
        info["boxes"] = boxes
        return q, info

    def _refine_box(
        self, target: np.ndarray, q0: np.ndarray, deadline: float = float("inf")
    ) -> tuple[np.ndarray, dict]:
        """One bounded solve in the box around ``q0``.

        The same bounded problem is first handed to our projected Levenberg-Marquardt (about 10× less
        overhead per step than scipy's trust-region reflective): with the chord Jacobian, then, near a
        singularity where the chord's approximation is too coarse, with the hybrid model's own. scipy's
        ``least_squares`` takes over when both miss the tolerance, so the paper's solver stays the reference.
        """
        o = self.options
        q0 = np.clip(q0, self.lower, self.upper)
        lo = np.maximum(self.lower, q0 - o.refine_width_rad)
        hi = np.minimum(self.upper, q0 + o.refine_width_rad)
        if o.refine in ("lm", "lm+scipy") and o.cost == "pose6":
            tol_m, tol_rad = 1e-3 * o.position_tolerance_mm * 1e-3, np.radians(o.orientation_tolerance_deg) * 1e-3
            box = (lo, hi, np.zeros(len(q0), dtype=bool))  # clip to the box, never wrap by 2π
            used = 0
            for fk_jac in (self._chord, self.model.fk_and_jacobian_single):
                q, ep, er, it = lm_solve(
                    fk_jac,
                    target,
                    q0,
                    box,
                    tol_m,
                    tol_rad,
                    12,  # Gauss-Newton steps converge in a handful from the classical answer; else it is stuck
                    min(time.perf_counter() + 0.25 * o.timeout_s, deadline),
                    damping=1e-9,  # q0 is close: Gauss-Newton steps from the start
                )
                used += it
                if ep <= tol_m and er <= tol_rad:
                    errors = (1e3 * ep, float(np.degrees(er)))
                    return q, {"nfev": used, "status": 0, "method": "lm", "errors": errors}
                q0 = q
            if o.refine == "lm" or np.any((q <= lo + 1e-12) | (q >= hi - 1e-12)):
                # scipy costs up to 60 hybrid Jacobians here; the answer beyond the box (near a
                # singularity) it cannot reach in the same box anyway; the caller's unbounded LM can
                return q, {"nfev": used, "status": 3, "method": "lm"}
            q0 = q  # scipy goes on from there
        model = self.model
        scale = np.array([1e3, 1e3, 1e3, o.rotation_scale_mm, o.rotation_scale_mm, o.rotation_scale_mm])
        mm = np.ones((3, 4))
        mm[:, 3] = 1e3

        if o.cost == "pose6":

            def fun(q):
                return scale * _error6(target, model.fk_single(q))

            def jac(q):
                return -scale[:, None] * model.fk_and_jacobian_single(q)[1]
        else:

            def fun(q):
                return ((target - model.fk_single(q))[:3] * mm).ravel()

            def jac(q):
                T, J = model.fk_and_jacobian_single(q)
                d = np.empty((3, 4, len(q)))
                for j in range(len(q)):
                    w = J[3:, j]
                    wx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
                    d[:, :3, j] = wx @ T[:3, :3]
                    d[:, 3, j] = J[:3, j]
                return -(d * mm[..., None]).reshape(12, len(q))

        q_start = np.clip(q0, lo, hi)
        sol = least_squares(
            fun,
            q_start,
            jac=jac,
            bounds=(lo, hi),
            method="trf",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=60,
            x_scale=1.0,
        )
        return sol.x, {"nfev": int(sol.nfev), "status": int(sol.status)}

    # ------------------------------------------------------------------ API
    def solve(self, target: np.ndarray, seed: np.ndarray | None = None, analytic: bool = False) -> IKResult:
        """One solution, the one the seed leads to. If that branch has no hybrid solution near it, the other
        analytic branches follow, from the restart table's configurations nearest the target, while the time
        budget lasts."""
        start = time.perf_counter()
        target, seed = self._check(target, seed)
        o = self.options
        deadline = start + o.timeout_s
        stats = {"attempts": 0, "refinements": 0}
        # a share of the budget: a target the URDF model cannot reach exactly (near the edge of its
        # workspace) makes every classical attempt fail, yet the hybrid stages solve it from there
        q0, _, _, attempts = self.classical(target, seed, start + CLASSICAL_SHARE * o.timeout_s)
        stats["attempts"] += attempts
        best = self._from_branch(target, q0, analytic, start, deadline, stats)
        if best.success or not o.restarts:
            return best
        # the other branches (module docstring, 3.); one shifted by 2π on a joint is another hybrid problem (the
        # nets see raw joint values), so branches count as different unless their joints are equal
        tried = [q0]
        tol_m, tol_rad = self.inner_tol
        seeds = self.nearest_seeds(target, 2 * TABLE_RESTARTS) if o.seed_table else np.empty((0, len(seed)))
        valley = self._valley_seeds(best) if not analytic else []
        for i in itertools.count():
            if time.perf_counter() > deadline:
                break
            if valley:  # straight to the hybrid LM: these start next to a hybrid near-solution
                result = self._other_branch(target, valley.pop(0), analytic, start, deadline, stats)
                stats["valley"] = stats.get("valley", 0) + 1
            else:
                s = seeds[i] if i < len(seeds) else self._rng.uniform(self.lower, self.upper)
                q0, ep, er, _ = lm_solve(
                    self._analytic, target, s, self.limits, tol_m, tol_rad, o.max_iterations, deadline
                )
                stats["attempts"] += 1
                if ep > NEAR_M or er > NEAR_RAD or any(np.abs(q0 - t).max() < BRANCH_RAD for t in tried):
                    continue
                tried.append(q0)
                result = self._other_branch(target, q0, analytic, start, deadline, stats)
                if not analytic:
                    valley = self._valley_seeds(result)
            if result.position_error_mm < best.position_error_mm:
                best = result
            if result.success:
                break
        best.stats["branches"] = len(tried)
        best.seconds = time.perf_counter() - start
        return best

    def _valley_seeds(self, result: IKResult) -> list[np.ndarray]:
        """Restarts along the weak direction of the hybrid Jacobian from a near miss at a near-singular
        configuration. There the hybrid near-solutions form a valley (at a wrist singularity, joints 4 and 6
        trade off), and LM settles in a local minimum of it tenths of a radian from the solution."""
        if result.q is None or result.position_error_mm > VALLEY_MM:
            return []
        _, sv, vt = np.linalg.svd(self.model.fk_and_jacobian_single(result.q)[1])
        if sv[-1] > VALLEY_SINGULAR:
            return []
        return [project(result.q + step * vt[-1], *self.limits) for step in VALLEY_STEPS_RAD]

    def _other_branch(
        self, target: np.ndarray, q0: np.ndarray, analytic: bool, start: float, deadline: float, stats: dict
    ) -> IKResult:
        """A cheaper :meth:`_from_branch` for the fallback branches: unbounded LM with the chord Jacobian
        (one hybrid FK per step), then with the hybrid one. At an exact singularity the error only halves
        per step; the floor and stall rules stop the runs that make no progress."""
        if analytic or not self.model.is_corrected:
            return self._result(q0, target, analytic, start, dict(stats))
        tol_m, tol_rad = self.inner_tol
        q = q0
        for fk_jac, iterations in ((self._chord, 12), (self.model.fk_and_jacobian_single, HYBRID_LM_ITERATIONS)):
            q, ep, er, _ = lm_solve(fk_jac, target, q, self.limits, tol_m, tol_rad, iterations, deadline, damping=1e-6)
            if ep <= tol_m and er <= tol_rad:
                break
        return self._result(q, target, analytic, start, dict(stats))

    def _from_branch(
        self, target: np.ndarray, q0: np.ndarray, analytic: bool, start: float, deadline: float, stats: dict
    ) -> IKResult:
        """The hybrid solution near the classical answer ``q0``: the box refinement, then, if that misses,
        damped LM on the hybrid model over the whole joint range (the bounded boxes crawl near a singularity)."""
        q, errors = q0, None
        corrected = not analytic and self.model.is_corrected
        if corrected:
            q, info = self.refine(target, q0)
            errors = info.pop("errors", None)
            stats["refinements"] += 1
            stats.update(info)
        result = self._result(q, target, analytic, start, dict(stats), errors)
        if not result.success and corrected:
            q, *_ = lm_solve(
                self.model.fk_and_jacobian_single,
                target,
                q,
                self.limits,
                *self.inner_tol,
                HYBRID_LM_ITERATIONS,
                deadline,
            )
            stats["hybrid_lm"] = stats.get("hybrid_lm", 0) + 1
            result = self._result(q, target, analytic, start, dict(stats))
        return result

    def _result(
        self,
        q: np.ndarray,
        target: np.ndarray,
        analytic: bool,
        start: float,
        stats: dict,
        errors: tuple[float, float] | None = None,
    ) -> IKResult:
        """``errors`` (mm, deg) when the solver has just evaluated them at ``q`` with the same model."""
        o = self.options
        pos, rot = errors if errors is not None else self.errors(q, target, analytic)
        inside = bool(self.model.in_calibrated_range(q)[0])
        ok = pos <= o.position_tolerance_mm and rot <= o.orientation_tolerance_deg
        if ok and not inside and o.require_calibrated_range and not analytic:
            bounds = zip(self.model.joint_names, q, self.model.trained_lower, self.model.trained_upper, strict=True)
            outside = [n for n, v, lo, hi in bounds if not lo <= v <= hi]
            message = f"the solution lies outside the calibrated joint range ({', '.join(outside)})"
            ok = False
        elif ok:
            message = "solved"
        else:
            message = (
                f"no solution within tolerance: best error {pos:.3g} mm / {rot:.3g} deg "
                "(target unreachable, or no convergence within the iteration and time budget)"
            )
        return IKResult(ok, q, pos, rot, message, time.perf_counter() - start, inside, stats)

    def solve_many(
        self,
        target: np.ndarray,
        seed: np.ndarray | None = None,
        max_solutions: int = 8,
        extra_seeds: list[np.ndarray] | None = None,
        analytic: bool = False,
        deadline: float | None = None,
    ) -> list[IKResult]:
        """Up to ``max_solutions`` distinct solutions, nearest to the seed first. Empty if none reached.

        ``deadline`` (``time.perf_counter()`` time) bounds the whole request: the per-seed budget
        (``timeout_s``) alone lets 65 seeds and the refinements add up to seconds. The seed search gets
        the first half of the time left, refinement the rest; solutions not refined by then are dropped.
        """
        start = time.perf_counter()
        target, seed = self._check(target, seed)
        seeds = [seed, *(extra_seeds or []), *self.spread]
        found: list[np.ndarray] = []
        o = self.options
        tol_m, tol_rad = 1e-3 * o.position_tolerance_mm, np.radians(o.orientation_tolerance_deg)
        end = float("inf") if deadline is None else deadline
        search_end = start + SEARCH_SHARE * (end - start)
        for s in seeds:
            now = time.perf_counter()
            if now > search_end:
                break
            seed_deadline = min(now + o.timeout_s, search_end)
            q, ep, er, _ = lm_solve(
                self._analytic, target, s, self.limits, tol_m * 0.1, tol_rad * 0.1, o.max_iterations, seed_deadline
            )
            if ep > tol_m or er > tol_rad:
                continue
            q = self._nearest_equivalent(q, seed)
            if not any(self._same(q, f) for f in found):
                found.append(q)
        found.sort(key=lambda q: float(np.linalg.norm(q - seed)))
        results = []
        for q0 in found[:max_solutions]:
            if time.perf_counter() > end:
                break
            q, stats = (q0, {}) if analytic or not self.model.is_corrected else self.refine(target, q0, deadline=end)
            result = self._result(q, target, analytic, start, stats, stats.pop("errors", None))
            if result.success:
                results.append(result)
        return results

    def _nearest_equivalent(self, q: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """Shift revolute joints by multiples of 2π towards the seed, staying inside the limits."""
        out = q.copy()
        rev = self.model.chain.revolute
        for j in np.flatnonzero(rev):
            k = np.round((seed[j] - q[j]) / (2 * np.pi))
            for shift in (k, k - np.sign(k)) if k else (0,):
                cand = q[j] + 2 * np.pi * shift
                if self.lower[j] - 1e-12 <= cand <= self.upper[j] + 1e-12:
                    out[j] = cand
                    break
        return out

    def _same(self, a: np.ndarray, b: np.ndarray, tol: float = 1e-3) -> bool:
        d = a - b
        rev = self.model.chain.revolute
        d[rev] = (d[rev] + np.pi) % (2 * np.pi) - np.pi
        return bool(np.all(np.abs(d) < tol))

    def solve_trajectory(
        self, targets: np.ndarray, seed: np.ndarray | None = None, start: np.ndarray | None = None
    ) -> list[IKResult]:
        """A sequence of targets, each seeded by the previous answer (the first by ``seed``).

        Two passes instead of one hybrid solve per pose: the URDF model's IK along the path, each pose from
        the answer before it (a few cheap iterations), then Newton's chord method on all poses at once
        through the batched hybrid FK. Poses that do not converge there get a full :meth:`solve`. Each
        result's ``seconds`` is the batch's time per pose.

        ``start`` ``(N, n)``: the URDF model's answers are known already (a trajectory planned on the URDF
        is its own URDF IK), so the first pass is skipped.
        """
        initial = start
        start = time.perf_counter()
        targets = np.asarray(targets, dtype=float)
        if targets.ndim != 3 or targets.shape[1:] != (4, 4):
            raise IKError(f"trajectory targets must be (N, 4, 4), got {targets.shape}")
        o = self.options
        tol_m, tol_rad = self.inner_tol
        n = len(targets)
        q = np.empty((n, self.model.chain.dof))
        if initial is not None:
            q[:] = np.asarray(initial, dtype=float).reshape(q.shape)
        prev = None if seed is None else np.asarray(seed, dtype=float)
        if prev is None and n and initial is None:  # no seed: the first pose's full solve picks the branch
            prev = self.solve(targets[0]).q
        for i, target in enumerate(targets if initial is None else ()):
            target, from_q = self._check(target, prev)
            # the path's own extrapolation saves a step or two; the previous answer if that goes astray
            for start_q in ((2.0 * q[i - 1] - q[i - 2]) if i >= 2 else from_q, from_q):
                q[i], ep, er, _ = lm_solve(
                    self._analytic, target, start_q, self.limits, tol_m, tol_rad, 30, time.perf_counter() + o.timeout_s
                )
                if ep < NEAR_M and er < NEAR_RAD and np.abs(q[i] - from_q).max() < 0.5:
                    break
            prev = q[i]
        errors = np.full((n, 2), np.inf)
        active = np.arange(n)
        for _ in range(8):
            T = self.model.fk(q[active])
            e = np.concatenate(
                [targets[active, :3, 3] - T[:, :3, 3], se3.rotvec(targets[active, :3, :3] @ T[:, :3, :3].mT)], axis=1
            )
            ep, er = np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)
            done = (ep <= tol_m) & (er <= tol_rad)
            errors[active[done]] = np.column_stack([1e3 * ep[done], np.degrees(er[done])])
            active, e = active[~done], e[~done]
            if not len(active):
                break
            _, J = self.model.fk_and_jacobian(q[active], analytic=True)
            jt = J.mT
            step = np.linalg.solve(jt @ J + 1e-12 * np.eye(J.shape[2]), (jt @ e[:, :, None]))[:, :, 0]
            q[active] = project(q[active] + step, *self.limits)
        results = []
        for i in range(n):
            if np.isfinite(errors[i, 0]):
                result = self._result(q[i], targets[i], False, start, {"method": "batch chord"}, tuple(errors[i]))
            else:
                result = self.solve(targets[i], q[i - 1] if i else seed)
            results.append(result)
        per_pose = (time.perf_counter() - start) / max(n, 1)
        for result in results:
            result.seconds = per_pose
        return results

    def wang_baseline(self, target: np.ndarray, seed: np.ndarray | None = None, iterations: int = 1) -> IKResult:
        """Wang et al. [26] as the paper adapted it: analytic IK of a target compensated by the nets' error.

        ``T_comp = T_target · (T_hybrid(q)⁻¹ · T_analytic(q))`` at the current answer, then analytic IK again.
        For comparison only.
        """
        start = time.perf_counter()
        target, seed = self._check(target, seed)
        deadline = start + self.options.timeout_s * (iterations + 1)
        q, *_ = self.classical(target, seed, deadline)
        for _ in range(iterations):
            T_h = self.model.fk_single(q)
            T_a = self.model.fk_single(q, analytic=True)
            compensated = target @ se3.inverse(T_h) @ T_a
            q, *_ = self.classical(compensated, q, deadline)
        return self._result(q, target, False, start, {"method": "wang"})
