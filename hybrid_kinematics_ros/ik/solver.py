"""Inverse kinematics through the hybrid model (paper section 3, Fig. 3), and past it: the solver that
composes the parts, with ``solve``, ``solve_many`` and ``solve_trajectory``.

1. The URDF model's IK. A chain with closed forms (most industrial arms: a spherical wrist, three parallel
   axes; :mod:`~hybrid_kinematics_ros.ik.analytic`) gets every analytic branch at once, exact near
   singularities too, and the branch nearest the seed is the classical answer. Otherwise, or where the
   closed forms give nothing (exactly at a singularity, where the branches form a continuum), a classical
   iterative IK (:mod:`~hybrid_kinematics_ros.ik.lm`, joint limits enforced) runs from the seed, which
   decides which solution is found. If the seed fails, restarts follow within the time budget from the
   table's configurations nearest the target, then from random ones (:mod:`~hybrid_kinematics_ros.ik.seeds`).
   A hybrid target can lie just beyond the URDF model's reach (a UR arm's wrist a fraction of a millimetre
   inside the cylinder its shoulder offset leaves around axis 1, an elbow stretched past the URDF's reach):
   the closed forms then give no exact branch, and since they give every one, no restart would; their
   least-squares answers (the URDF model's nearest) start the hybrid stages instead, each branch first by
   the fixed point of 2., nearest the seed first.
2. The hybrid refinement around the classical answer. With closed forms, first a fixed point on the classical
   answer's branch: the closed forms solve the target moved by the hybrid correction at the current answer (the
   URDF pose to the hybrid pose), until the correction stops changing; then the hybrid pose is the target. Each
   round cuts the error ~100× (what it leaves out is the nets' slope); a round near the target is Newton's chord
   step on the URDF Jacobian, which cuts it as much for half the cost: about four hybrid FKs a solution
   (:mod:`~hybrid_kinematics_ros.ik.fixed_point`). A round
   whose moved target is beyond the URDF model's reach takes its least-squares answer; when such rounds stop
   cutting the error, the branch cannot reach the target, and 3. follows at once. One solution starts with this
   fixed point on the branch nearest the seed alone; only where it fails are the other branches computed and
   checked. What the fixed point leaves goes to bounded LM through the hybrid FK in a box
   (:mod:`~hybrid_kinematics_ros.ik.refine`).
   Near a singularity of the URDF model its chord Jacobian loses rank and the fixed point wanders along the
   singular valley: a root search along that valley and those of the other closed-form branches follows
   (:mod:`~hybrid_kinematics_ros.ik.valley`), right after the seed's fixed point. Where that stalled beyond its
   branch's reach, the search comes after the other branches' fixed points instead, and only if none solves
   (another branch is then the likelier answer, and far cheaper to try).
   A target beyond the URDF model's reach (no exact branch) gets the same search from the least-squares answers,
   after cheaper tries on the nearest one: the restarts along its weak direction that 3. would try later, then
   the fixed point, then LM, on its few copies shifted by 2π (the nets see raw joint values, and can reach
   further on another copy). Where the URDF model reaches the target only past a joint limit, its answers
   clipped into the limits and polished there take the least-squares answers' place; no exact branch within the
   limits means no restart of the URDF model's LM finds one, so the classical stage gets a tenth of the budget
   instead of half, and the table's restarts alone, none random.
3. When the seed's branch has no hybrid solution near it (near a singularity the nets' tenths of a
   millimetre move the solution by tenths of a radian, or the target lies just beyond the URDF model's
   reach), the other analytic branches follow: the closed forms' other branches, nearest the seed first,
   then classical answers from the table's nearest configurations, each finished by unbounded LM on the
   hybrid model, until one reaches the target or the budget ends; one whose fixed point misses next to a
   singularity has the valley through it searched before its LM (once per point). A near miss at a near-singular
   configuration first restarts along the Jacobian's weak direction (once per near miss), where the hybrid
   near-solutions form a valley with local minima. Before the seed's branch goes past its fixed point, the
   other closed-form branches get a few fixed-point rounds each (near a wrist singularity the seed's fixed
   point wanders among the members of a continuum, where the others converge in a few rounds): one that solves
   waits in reserve, and is the answer, said so, if the seed's branch finds nothing within the budget.
4. A model whose nets take the joints' approach directions (:mod:`~hybrid_kinematics_ros.kinematics.approach`)
   is refined with the directions the robot arrives in when it moves from the seed (where it is) to the
   solution, not with the last ones it moved in: the sign of each joint's move, the current direction for
   a joint that does not move. A trajectory's poses arrive from the pose before. As the solution fixes the
   directions and the directions move the solution, a refinement that changes a sign runs once more.

Several solutions come from several seeds, deduplicated modulo 2π on revolute joints (keeping the
representative nearest the seed) and ordered by distance to the seed. Every result says whether it
reached the target; a miss is never returned as a success. The methods we compare against are in
:mod:`~hybrid_kinematics_ros.ik.baselines`.

Redundant arms (7 joints) are solved, not refused. Every LM step is the damped least-squares correction, the
smallest joint motion that reduces the pose error, so the answer keeps the seed's position along the
self-motion: the null-space choice is "near the seed", with no further objective. A model without
corrections (or ``analytic=True``) has no hybrid stages: its classical stage gets the whole budget.
"""

from __future__ import annotations

import copy
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from hybrid_kinematics_ros.ik import seeds as seeding
from hybrid_kinematics_ros.ik.analytic import AnalyticIK, turns
from hybrid_kinematics_ros.ik.errors import IKError
from hybrid_kinematics_ros.ik.fixed_point import FIXED_POINT_ROUNDS, FixedPoint
from hybrid_kinematics_ros.ik.lm import LM, ChainFkJac, joint_limits
from hybrid_kinematics_ros.ik.refine import HybridRefiner
from hybrid_kinematics_ros.ik.valley import valley_starts, warm_up
from hybrid_kinematics_ros.kinematics import approach, se3
from hybrid_kinematics_ros.kinematics.se3 import error6
from hybrid_kinematics_ros.model.hybrid import COMPILED_ROWS, HybridModel

# Budget shares. CLASSICAL_SHARE: a target the URDF model cannot reach exactly (near the edge of its
# workspace) makes every classical attempt fail, yet the hybrid stages solve it from there, so the seed's
# classical stage gets half and the other branches the rest. SEARCH_SHARE: solve_many's seed search gets the
# first half of the request's time, the refinements the rest (unbounded, its seeds would add up to seconds).
CLASSICAL_SHARE = 0.5
SEARCH_SHARE = 0.5
NO_BRANCH_SHARE = 0.1  # the classical stage's where the closed forms give no branch within the limits (solve)
# Trajectories: URDF-model LM steps per pose from the previous answer (a few suffice), and the joint
# jump beyond which the path's extrapolation has gone to another branch.
PATH_ITERATIONS = 30
PATH_JUMP_RAD = 0.5
PROBE_ROUNDS = 4  # the other branches' rounds while the seed's branch is not solved (where they converge: 3)
# Of the budget, still left, for the search along a singular valley (ik/valley.py); the search stops at the
# deadline itself. A larger share would skip it for targets it finds quickly once the other strategies have
# run (chosen by bench_ik_singular, BENCHMARKS.md).
VALLEY_SHARE = 0.2
RESTART_SHARE = 0.05  # of the budget, for each restart beyond the URDF model's reach before the valley search
COPY_PROBES = 4  # copies of a near miss beyond the URDF model's reach tried before the valley search
POLISH_ITERATIONS = 12  # LM steps on a least-squares answer beyond a fold (6-9 reach the URDF model's nearest point)
# A probe's fixed point that ends this near the target (mm) has stalled at a fold of the URDF model, where its
# rounds only halve the error, or converges slowly next to a double singularity, where they cut it by a fifth:
# LM on the hybrid model finishes in a few steps (such stalls end up to a few hundredths of a millimetre away).
NEAR_MISS_MM = 5e-2
# Starts this near each other (rad, every joint) give the same fixed point and the same LM run, which a solve does
# not repeat: the closed forms' nearest branch and its polished copy differ by 1e-8 to 2e-6 rad, and two branches
# that merge at a fold (an RX160's elbow stretched) end their fixed points at the same point to 1e-10 rad.
SAME_START_RAD = 1e-5
SINGULAR = 1e-6  # the URDF Jacobian's smallest singular value (m or rad per rad) at a singular target's answer
OTHER_BRANCH = "on another branch than the seed's, which found no solution within the budget"  # said with it


def _same_start(q: np.ndarray, starts: list[np.ndarray]) -> bool:
    """``q`` lies within SAME_START_RAD of one of ``starts`` in every joint."""
    return any(np.abs(q - s).max() < SAME_START_RAD for s in starts)


def pose_problem(target: np.ndarray) -> str | None:
    """What is wrong with a target pose ``(4, 4)``, or None: it must be finite, and its rotation orthonormal
    (to 1e-6) with determinant +1. In Python floats: numpy's checks would cost a noticeable share of a request."""
    finite = "the target must be a finite 4x4 homogeneous matrix"
    if target.shape != (4, 4):
        return finite
    v = target.ravel().tolist()
    if not all(map(math.isfinite, v)):
        return finite
    a, b, c, _, d, e, f, _, g, h, i, _ = v[:12]
    rows = (a * a + b * b + c * c - 1.0, d * d + e * e + f * f - 1.0, g * g + h * h + i * i - 1.0)
    cross = (a * d + b * e + c * f, a * g + b * h + c * i, d * g + e * h + f * i)
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if max(map(abs, rows + cross)) > 1e-6 or det < 0:
        return "the target's rotation is not orthonormal"
    return None


def compensated_target(
    model: HybridModel, target: np.ndarray, q: np.ndarray, hybrid: np.ndarray | None = None
) -> np.ndarray:
    """Wang et al.'s compensated target ``T_target · T_hybrid(q)⁻¹ · T_URDF(q)``: where the URDF model must go
    for the hybrid model to reach the target, if the correction at ``q`` held there (``hybrid``: T_hybrid(q),
    when known)."""
    hybrid = model.fk_single(q) if hybrid is None else hybrid
    return target @ se3.inverse(hybrid) @ model.fk_single(q, analytic=True)


@dataclass(frozen=True)
class IKOptions:
    position_tolerance_mm: float = 1e-4  # success thresholds on the hybrid-FK error
    orientation_tolerance_deg: float = 1e-4
    refine_width_rad: float = 0.02  # half width of the box around q0 (paper: "a small interval")
    max_iterations: int = 100  # classical stage, per seed
    timeout_s: float = 0.05  # per solution, restarts included
    require_calibrated_range: bool = False  # True: a solution outside the trained range fails
    arrive_from_seed: bool = True  # approach-direction models: the directions of the move from the seed (4.)
    closed_form: bool = True  # False: the iterative solver alone, without the closed forms (baselines, benches)
    valley: bool = True  # False: no root search along a singular valley (ik/valley.py; benches compare)


@dataclass(frozen=True)
class SolveRequest:
    """One solve: the ``target`` pose, the ``seed`` it starts from, where the robot comes from (``origin``; None:
    the caller did not say, 4.), the URDF model alone (``analytic``), when it started (``start``,
    ``time.perf_counter``) and its ``deadline``. Each stage takes it; ``stats``, the trace of what ran, travels
    beside it."""

    target: np.ndarray
    seed: np.ndarray
    origin: np.ndarray | None
    analytic: bool
    start: float
    deadline: float

    def until(self, deadline: float) -> SolveRequest:
        """The same request with another deadline (a stage's share of the budget)."""
        return replace(self, deadline=deadline)


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


class IKSolver:
    """IK of a :class:`HybridModel` (hybrid, or analytic with ``analytic=True``).

    ``refiner``: another hybrid refinement (the baselines'); by default projected LM in a box.
    """

    def __init__(
        self, model: HybridModel, options: IKOptions | None = None, refiner: HybridRefiner | None = None
    ) -> None:
        self.model = model
        self.options = o = options or IKOptions()
        self.limits = joint_limits(model.chain)
        self.lower, self.upper, _ = self.limits
        self.refiner = refiner or HybridRefiner(
            model, self.limits, o.position_tolerance_mm, o.orientation_tolerance_deg, o.refine_width_rad, o.timeout_s
        )
        self.inner_tol = self.refiner.inner_tol
        # LM on the URDF model, compiled (ChainFkJac), within the inner tolerances
        self.urdf_lm = LM(ChainFkJac(model.chain), self.limits, self.inner_tol, o.max_iterations)
        self.seeds = seeding.SeedTable(model, self.lower, self.upper)
        self.closed_form = AnalyticIK.of(model.chain) if o.closed_form else None  # None: iterative only
        self.path = f"closed form ({self.closed_form.family})" if self.closed_form else "iterative"
        self._last_rank: tuple[bytes, bool] | None = None  # see _rank_lost
        self._mid = model.chain.mid_limits()  # the seed of a request without one
        self._fixed_point = (
            FixedPoint(model, self.closed_form, self.inner_tol, self.refiner.polish_tol, self.lower, self.upper)
            if self.closed_form is not None
            else None
        )

    def warm_up(self) -> IKSolver:
        """Load the compiled kernels (LM, the fixed point's round, the URDF model's pose, the valley trace's step)
        and the model's batched paths now, or on a fresh checkout compile them (a few seconds, once per
        machine), so that no first request spends its budget on them: an LM step, one solve off the middle of
        the limits, a chord step. The URDF pose is what a near-singular request checks its branches with, and no
        regular solve calls it: loaded there, it would take half a first such request's budget. A server calls
        this once before it answers; the kernels stay loaded for every solver of the process. Returns the
        solver."""
        model = self.model
        target = model.fk_single(self._mid + 0.025 * (self.upper - self.lower))  # finite: ±2π where unlimited
        model.fk_single(self._mid, analytic=True)
        # and the batched hybrid FK's two paths (compiled up to COMPILED_ROWS rows, TorchScript beyond), which the
        # valley search and the side-by-side fixed points take: the first call of each is slow enough to make a
        # first valley search's answer late
        for rows in (2, COMPILED_ROWS + 1):
            model.fk(np.tile(self._mid, (rows, 1)))
        self.urdf_lm._replace(max_iterations=1).solve(target, self._mid, float("inf"))
        if self.closed_form is not None:
            self.solve(target, self._mid)
            self._fixed_point.newton_step(self._mid, np.zeros(6))  # a solve may end before its chord steps
            if model.chain.dof == 6:  # and the valley trace's step (valley.warm_up)
                warm_up(model, self._mid)
        return self

    def with_model(self, model: HybridModel) -> IKSolver:
        """This solver over ``model``, another value of the same calibration (its condition values or approach
        directions): the tables and kernels are shared, nothing is rebuilt."""
        if model is self.model:
            return self
        clone = copy.copy(self)
        clone.model = model
        clone.refiner = self.refiner.with_model(model)
        if self._fixed_point is not None:
            clone._fixed_point = replace(self._fixed_point, model=model)
        return clone

    def _approaching(self, directions: np.ndarray | None) -> IKSolver:
        """This solver over the model with the approach ``directions`` (None: the model's own)."""
        return self.with_model(self.model.with_approach(directions))

    def branches(self, target: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """The closed forms' branches within the limits, nearest the seed first; none without closed forms."""
        if self.closed_form is None:
            return np.empty((0, self.model.chain.dof))
        return self.closed_form.branches(target, seed)

    def check(self, target: np.ndarray, seed: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The request as arrays, or an :class:`IKError` saying what is wrong with it."""
        dof = self.model.chain.dof
        if dof not in (6, 7):
            c = self.model.chain
            raise IKError(
                f"IK needs a chain of 6 or 7 joints; {c.base_link} -> {c.tip_link} has {dof}: choose another tip link"
            )
        target = np.asarray(target, dtype=float)
        problem = pose_problem(target)
        if problem is not None:
            raise IKError(problem)
        seed = self._mid.copy() if seed is None else np.asarray(seed, dtype=float)
        if seed.shape != (dof,) or not np.isfinite(seed).all():
            raise IKError(f"the seed must have {dof} finite joint values, got {seed.shape}")
        return target, seed

    def classical(
        self,
        target: np.ndarray,
        seed: np.ndarray,
        deadline: float,
        restarts: int = seeding.TABLE_RESTARTS,
        branches: np.ndarray | None = None,
        continuum: bool = True,
        table_only: bool = False,
    ) -> tuple[np.ndarray, float, float, int]:
        """Stage 1: the joints, the errors (m, rad), the attempts. With closed forms, the branch nearest the seed
        (``branches``, when the caller has them); where the target has a branch at a singularity, LM from the
        seed too, and the nearer of the two. Otherwise, or when the closed forms give nothing, LM from the
        seed, then restarts while time remains, from the ``restarts`` table configurations nearest the
        target, then random ones. ``continuum``: False where the hybrid stages follow, whose valley search
        walks the continuum itself (LM crawls there, for half the budget). ``table_only``: no random
        restarts after the table's (where none can succeed: the best answer of a few is as good)."""
        tol_m, tol_rad = self.inner_tol
        branches = self.branches(target, seed) if branches is None else branches
        for q in branches[:1]:  # nearest the seed; exact, or polished on our FK in a step
            e = error6(target, self.model.fk_single(q, analytic=True))
            ep, er = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
            if ep > tol_m or er > tol_rad:
                q, ep, er, _ = self.urdf_lm.solve(target, q, deadline)
            if ep <= tol_m and er <= tol_rad:
                if not continuum or not (self._rank_lost(q) or self.closed_form.singular(target)):
                    return q, ep, er, 1
                # a branch at a singularity has no closed-form answer: its continuum's member nearest the seed
                # comes from LM, and wins if nearer than the closed forms' nearest
                q2, ep2, er2, _ = self.urdf_lm.solve(target, seed, deadline)
                near = ep2 <= tol_m and er2 <= tol_rad and np.linalg.norm(q2 - seed) < np.linalg.norm(q - seed)
                return (q2, ep2, er2, 2) if near else (q, ep, er, 2)
        best = None
        attempt_seed = seed
        attempts = 0
        nearest = iter(self.seeds.nearest(target, restarts))
        while True:
            attempts += 1
            # the caller's seed runs its course: it decides the branch
            q, ep, er, _ = self.urdf_lm.solve(target, attempt_seed, deadline, stop_crawl=attempts > 1)
            if best is None or ep + er < best[1] + best[2]:
                best = (q, ep, er)
            if (ep <= tol_m and er <= tol_rad) or time.perf_counter() > deadline:
                break
            attempt_seed = next(nearest, None)
            if attempt_seed is None:
                if table_only:
                    break
                attempt_seed = self.seeds.random()
        return best[0], best[1], best[2], attempts

    def solve(self, target: np.ndarray, seed: np.ndarray | None = None, analytic: bool = False) -> IKResult:
        """One solution, the one the seed leads to (with closed forms, the branch nearest the seed). If that branch
        has no hybrid solution near it, the other branches follow while the time budget lasts: the closed
        forms' others, then those from the restart table's configurations nearest the target."""
        start = time.perf_counter()
        given = seed is not None
        target, seed = self.check(target, seed)
        origin = seed if given else None  # where the robot comes from, if the caller said (4.)
        o = self.options
        deadline = start + o.timeout_s
        stats = {"attempts": 0, "refinements": 0, "path": self.path}
        restarted: list[np.ndarray] = []  # the weak-direction restarts run already (3.), none twice
        req = SolveRequest(target, seed, origin, analytic, start, deadline)
        urdf_only = analytic or not self.model.is_corrected
        missed = None  # the nearest branch's fixed point that missed: the search below starts from it again
        lm_starts: list[np.ndarray] = []  # where a near miss's LM has run (_near_miss_lm)
        if urdf_only:
            found = self._nearest_exact(req, stats)
        else:
            found, missed = self._nearest_fixed_point(req, stats)
        if found is not None:
            return found
        closed = self.branches(target, seed)
        if urdf_only:
            # no hybrid stages to keep time for, and the branch search would only rerun the same URDF-model LM
            # from the same table seeds: the classical stage gets the whole budget and all of those seeds
            restarts = 2 * seeding.TABLE_RESTARTS
            q, _, _, stats["attempts"] = self.classical(target, seed, deadline, restarts, closed)
            return self._singular(self.result(req, q, stats))
        near = self._beyond_reach(target, seed, closed)
        nearest_miss = None  # beyond the URDF model's reach: the branch's fixed point that came nearest
        if len(near):  # the closed forms are complete: no URDF-model restart would find an exact branch
            found, nearest_miss = self._near_branches(req, stats, near, restarted)
            if found is not None:
                return self._singular(found)
            q0 = nearest_miss.q  # the refinements go on from the branch that came nearest
        else:
            # closed forms that give no branch within the limits are complete: no restart of the URDF model's LM
            # finds one, and its nearest point within them comes from the first few (more would take the time
            # the valley search needs)
            complete = self.closed_form is not None and not len(closed)
            share = NO_BRANCH_SHARE if complete else CLASSICAL_SHARE
            q0, _, _, attempts = self.classical(
                target, seed, start + share * o.timeout_s, branches=closed, continuum=False, table_only=complete
            )
            stats["attempts"] += attempts
        reserve = refine = None
        if len(closed) > 1:  # the seed's fixed point first: if it fails, the other branches' wait in reserve
            found, reserve, refine, q0 = self._seed_branch(req, stats, q0, closed, missed, lm_starts)
            if found is not None:
                return self._singular(found)
        best = self._from_branch(req, q0, stats, refine)
        if best.success:
            return self._singular(best)
        if reserve is not None:  # the seed's branch found nothing in the budget: another branch's answer
            reserve.seconds = time.perf_counter() - start
            reserve.stats["other_branch"] = True
            reserve = self._singular(reserve)
            reserve.message += f"; {OTHER_BRANCH}"
            return reserve
        return self._fallback(req, stats, best, q0, (closed, near), nearest_miss, restarted)

    def _near_branches(
        self, req: SolveRequest, stats: dict, near: np.ndarray, restarted: list[np.ndarray]
    ) -> tuple[IKResult | None, IKResult]:
        """A target beyond the URDF model's reach (``near``: its least-squares answers, nearest the seed first).
        The hybrid model reaches it on some of these branches only (the edge of its workspace moved by the
        corrections): the cheap fixed point on each first; then, from the one that came nearest, the cheaper
        tries before the valley search: its weak-direction restarts (four short LM runs), its copies shifted by
        2π (the order chosen by bench_ik_singular, BENCHMARKS.md), and the valleys. The answer found (else None)
        and the branch's fixed point that came nearest."""
        stats["beyond_urdf_reach"] = True
        nearest_miss = None
        for q in near:
            result = self._from_branch(req, q, stats, IKSolver._fixed_point_only)
            if result.success:
                return result, result
            if nearest_miss is None or result.position_error_mm < nearest_miss.position_error_mm:
                nearest_miss = result
        found = self._weak_restarts(req, nearest_miss, stats, restarted)
        if found is None:
            found = self._copies(req, nearest_miss.q, stats, restarted)
        if found is None:
            found = self._valley(req, nearest_miss.q, stats, near=near)
        return found, nearest_miss

    def _seed_branch(
        self,
        req: SolveRequest,
        stats: dict,
        q0: np.ndarray,
        closed: np.ndarray,
        missed: tuple[np.ndarray, IKResult] | None,
        lm_starts: list[np.ndarray],
    ) -> tuple[IKResult | None, IKResult | None, Callable[..., IKResult], np.ndarray]:
        """The seed's branch ``q0`` among several closed-form ``closed`` ones: its fixed point (``missed``'s
        verdict where it ran already) and LM from a near miss; then the valley search and the other branches'
        fixed points, which wait in reserve. Where the seed's fixed point stalled beyond its branch's reach,
        those first, and the valleys only if they found nothing: another branch's cheap fixed point is then the
        likelier answer, and the valleys could take the whole budget (where no other branch reaches, the
        solution lies on a valley). The answer found (else None), the other branches' answer in reserve, the
        refinement the seed's branch goes on with, and the configuration it goes on from (the fixed point's
        answer, which it does not repeat)."""
        if missed is not None and _same_start(missed[0], [q0]):  # the same fixed point: its miss, not a second run
            first = missed[1]
        else:
            first = self._from_branch(req, q0, stats, IKSolver._fixed_point_only)
        first = self._near_miss_lm(req, first, lm_starts)
        refine = functools.partial(IKSolver._refine_branch, fixed=first, valley=False)
        if first.success:
            return first, None, refine, first.q
        reserve = None
        beyond = first.stats.get("beyond_branch_reach")
        if beyond:
            reserve = self._reserve(req, first, q0, closed, stats, lm_starts)
        if reserve is None:
            valley = functools.partial(IKSolver._valley_only, nearest=q0)
            found = self._from_branch(req, first.q, stats, valley)
            if found.success:
                return found, reserve, refine, first.q
        if not beyond:
            reserve = self._reserve(req, first, q0, closed, stats, lm_starts)
        return None, reserve, refine, first.q

    def _fallback(
        self,
        req: SolveRequest,
        stats: dict,
        best: IKResult,
        q0: np.ndarray,
        exact_and_near: tuple[np.ndarray, np.ndarray],
        nearest_miss: IKResult | None,
        restarted: list[np.ndarray],
    ) -> IKResult:
        """The other branches (module docstring, 3.), while the budget lasts: the weak-direction restarts of the
        misses, the URDF model's nearest answers beyond its reach, then LM from the closed forms' branches, their
        copies shifted by 2π and the restart table's configurations. ``best``: the seed's branch's answer so far;
        ``exact_and_near``: the closed forms' exact branches and those beyond the URDF model's reach."""
        closed, near = exact_and_near
        tried = [q0]
        copies = self._branch_copies(req, np.vstack([closed, near]), nearest_miss, restarted)
        table = self.seeds.nearest(req.target, 2 * seeding.TABLE_RESTARTS)
        # (start, whether LM on the hybrid model follows a fixed point that stalls beyond the branch's reach: on
        # a copy, the nets' reach is what differs, and the hybrid Jacobian is what finds it)
        starts = iter([(q, False) for q in closed] + [(q, True) for q in copies] + [(q, False) for q in table])
        seeded: list[np.ndarray] = []  # the near misses whose weak-direction restarts are queued or run
        valleys: list[np.ndarray] = []  # the fallback points whose valleys were searched (_other_branch)

        def restarts_of(result: IKResult) -> list[np.ndarray]:
            """The restarts along ``result``'s weak direction, none twice from one near miss: near a singularity
            many fallback starts' fixed points end on the same few near misses."""
            if req.analytic or not seeding.is_new_branch(result.q, seeded):
                return []
            restarts = seeding.valley_seeds(self.model, result.q, result.position_error_mm, self.limits)
            if restarts:
                seeded.append(result.q)
            return restarts

        valley = restarts_of(best)
        # beyond the URDF model's reach, the nearest miss's restarts ran before the valley search, and the
        # refinement since then ends next to it: those that finished are not run again; those cut short by their
        # share run again here, with the time left
        valley = [q for q in valley if seeding.is_new_branch(q, restarted)]
        others = [q for q in near[1:] if seeding.is_new_branch(q, tried)]
        while True:
            if time.perf_counter() > req.deadline:
                break
            if valley:  # straight to the hybrid LM: these start next to a hybrid near-solution
                result = self._other_branch(req, valley.pop(0), stats)
                stats["valley"] = stats.get("valley", 0) + 1
            elif others:  # the URDF model's nearest answers of the other branches, beyond its reach
                q0 = others.pop(0)
                tried.append(q0)
                result = self._other_branch(req, q0, stats)
                valley = restarts_of(result)
            else:
                s, copy = next(starts, (None, False))
                q0 = self._urdf_branch(req, self.seeds.random() if s is None else s, tried, stats)
                if q0 is None:
                    continue
                tried.append(q0)
                result = self._other_branch(req, q0, stats, copy, valleys)
                if not result.success:
                    valley = restarts_of(result)
            if result.position_error_mm < best.position_error_mm:
                best = result
            if result.success:
                break
        best.stats["branches"] = len(tried)
        best.seconds = time.perf_counter() - req.start
        return self._singular(best)

    def _urdf_branch(self, req: SolveRequest, s: np.ndarray, tried: list[np.ndarray], stats: dict) -> np.ndarray | None:
        """The URDF model's LM answer from ``s``, if it reaches the target and lies on a branch not yet
        ``tried``; None otherwise."""
        q, ep, er, _ = self.urdf_lm.solve(req.target, s, req.deadline)
        stats["attempts"] += 1
        if ep > seeding.NEAR_M or er > seeding.NEAR_RAD or not seeding.is_new_branch(q, tried):
            return None
        return q

    def _branch_copies(
        self, req: SolveRequest, branches: np.ndarray, nearest_miss: IKResult | None, restarted: list[np.ndarray]
    ) -> list[np.ndarray]:
        """The ``branches``' copies shifted by 2π, nearest the seed first, each new branch once: another problem
        for the nets (an elbow stretched a few micrometres beyond one copy's reach can lie within another's).
        Beyond the URDF model's reach, the copies of the branch that came nearest (``nearest_miss``) go first:
        where no copy of the seed's reaches, the nets' reach on another copy of that branch is what differs (an
        RX160's stretched elbow). The branches and the ``restarted`` configurations were tried already."""
        copies = turns(branches, self.lower, self.upper)
        copies = copies[np.argsort(np.linalg.norm(copies - req.seed, axis=1), kind="stable")]
        if nearest_miss is not None:
            mine = turns(nearest_miss.q[None], self.lower, self.upper)
            copies = np.vstack([mine[np.argsort(np.linalg.norm(mine - req.seed, axis=1), kind="stable")], copies])
        unique: list[np.ndarray] = [*branches, *restarted]
        kept = []
        for q in copies:
            if seeding.is_new_branch(q, unique):
                unique.append(q)
                kept.append(q)
        return kept

    def _restarts(
        self,
        req: SolveRequest,
        starts: list[np.ndarray],
        mark: str,
        stats: dict,
        restarted: list[np.ndarray],
        lm_beyond: bool = False,
    ) -> IKResult | None:
        """Beyond the URDF model's reach, before the valley search: each of ``starts`` finished by
        :meth:`_other_branch` (``lm_beyond``: LM past a stalled fixed point too) within RESTART_SHARE of the
        budget. The first that reaches the target, with ``stats[mark]`` set (how it was found), else None. A start
        that finished within its share is added to ``restarted``, for the fallback loop to skip; one cut short
        gets the time that loop has left."""
        if req.analytic:
            return None
        for q in starts:
            now = time.perf_counter()
            if now > req.deadline:
                break
            # each a slice of the budget: those that solve do so quickly, and the others can crawl along a
            # continuum (a wrist straight) for longer than the valley search after them needs
            until = min(req.deadline, now + RESTART_SHARE * self.options.timeout_s)
            result = self._other_branch(req.until(until), q, stats, lm_beyond)
            if time.perf_counter() < until:
                restarted.append(q)
            if result.success:
                result.stats[mark] = True
                return result
        return None

    def _weak_restarts(
        self, req: SolveRequest, miss: IKResult, stats: dict, restarted: list[np.ndarray]
    ) -> IKResult | None:
        """The restarts along the weak direction of a near miss (``seeds.valley_seeds``, as the fallback loop
        of 3. has them), by :meth:`_restarts`."""
        if req.analytic:
            return None
        starts = seeding.valley_seeds(self.model, miss.q, miss.position_error_mm, self.limits)
        stats["valley"] = stats.get("valley", 0) + len(starts)
        return self._restarts(req, starts, "weak_restart", stats, restarted)

    def _copies(self, req: SolveRequest, q: np.ndarray, stats: dict, restarted: list[np.ndarray]) -> IKResult | None:
        """The copies of a near miss ``q`` shifted by 2π, the COPY_PROBES nearest it, by :meth:`_restarts` with
        LM past a stall: where the branch's fixed point stalls beyond its reach, the nets' reach on another
        copy is what differs (they see raw joint values)."""
        copies = turns(q[None], self.lower, self.upper)
        copies = copies[np.argsort(np.linalg.norm(copies - q, axis=1), kind="stable")]
        copies = [c for c in copies if seeding.is_new_branch(c, [q])][:COPY_PROBES]
        return self._restarts(req, copies, "copy", stats, restarted, True)

    def _reserve(
        self,
        req: SolveRequest,
        first: IKResult,
        q0: np.ndarray,
        closed: np.ndarray,
        stats: dict,
        lm_starts: list[np.ndarray],
    ) -> IKResult | None:
        """The seed's branch ``q0`` was not solved by its fixed point (``first``; near a wrist singularity it
        wanders among the members of a continuum): the other closed-form branches' fixed points, PROBE_ROUNDS
        each, nearest the seed first, and the whole fixed point of a branch its probe leaves undecided (neither
        converged nor stalled: otherwise its copies would be skipped, where an RX160's stretched elbow can have
        its solution). Once every branch's fixed point has run, LM from the near misses among them that did not
        stall (:meth:`_near_miss_lm`, in the same order): a further branch's fixed point is cheaper than the nearer
        branches' LM, and often solves where that fails. Then, where fixed points stalled beyond their branch's
        reach (an elbow stretched to the URDF model's reach), the copies of those branches shifted by 2π, the
        nearest miss's first: the nets see raw joint values, so another copy can reach micrometres further, where
        LM from the stalled misses fails. Last, LM from the stalled near misses, which solves less often. The
        first that solves waits in reserve while the seed's branch gets the budget. ``lm_starts``:
        :meth:`_near_miss_lm`'s."""
        tried = [q0]
        misses: list[IKResult] = []  # the branches' fixed points that missed, for _near_miss_lm in their order
        stalled = [(first.position_error_mm, q0)] if first.stats.get("beyond_branch_reach") else []
        probe = functools.partial(IKSolver._fixed_point_only, rounds=PROBE_ROUNDS)  # converging ones take 3
        for q in closed:
            if time.perf_counter() > req.deadline or not seeding.is_new_branch(q, tried):
                continue
            tried.append(q)
            result = self._from_branch(req, q, stats, probe)
            if not result.success and not result.stats.get("beyond_branch_reach"):
                # undecided after its probe: the rest of its fixed point says whether it converges or stalls
                result = self._from_branch(req, result.q, stats, IKSolver._fixed_point_only)
            if result.success:
                return result
            misses.append(result)
            if result.stats.get("beyond_branch_reach"):
                stalled.append((result.position_error_mm, q))
        for result in [m for m in misses if not m.stats.get("beyond_branch_reach")]:  # after every fixed point
            result = self._near_miss_lm(req, result, lm_starts)
            if result.success:
                return result
        for _, branch in sorted(stalled, key=lambda miss: miss[0]):
            for q in turns(branch[None], self.lower, self.upper):
                if time.perf_counter() > req.deadline or not seeding.is_new_branch(q, tried):
                    continue
                tried.append(q)  # the whole fixed point: a copy that reaches converges more slowly there
                result = self._from_branch(req, q, stats, IKSolver._fixed_point_only)
                if result.success:
                    return result
        for result in [m for m in misses if m.stats.get("beyond_branch_reach")]:
            result = self._near_miss_lm(req, result, lm_starts)
            if result.success:
                return result
        return None

    def _near_miss_lm(self, req: SolveRequest, result: IKResult, starts: list[np.ndarray]) -> IKResult:
        """A fixed point's ``result`` that missed by less than NEAR_MISS_MM has stalled at a fold of the URDF model
        (or where its Jacobian loses rank, next to the solution), where its rounds only halve the error: LM on the
        hybrid model from there, which finishes in a few steps. The seed's own fixed point gets it too: next to a
        singularity (a UR10 with the wrist centre on axis 1) it can stall micrometres from the solution, which LM
        reaches at once, where the search would go on to the other branches' copies and valleys.
        ``result`` itself otherwise, and where LM ran from the same start already (``starts``, the solve's: added
        to)."""
        if result.success or result.position_error_mm >= NEAR_MISS_MM or _same_start(result.q, starts):
            return result
        starts.append(result.q)
        solver = self._approaching(self._arrival(req.origin, result.q))
        q, *_ = solver.refiner.unbounded(req.target, result.q, req.deadline)
        return solver.result(req, q, dict(result.stats, hybrid_lm=1))

    def _nearest_exact(self, req: SolveRequest, stats: dict) -> IKResult | None:
        """The URDF model's answer for one IK-Geo call and one checked branch: the first of the closed forms'
        branches (:meth:`AnalyticIK.nearest_checked`), when our FK takes it to within the inner tolerance and
        the target is singular on none of its branches. None otherwise: the whole classical stage follows
        (at a singularity it looks for the continuum's member nearest the seed). The same answer as that
        stage's, for a fraction of its time (bench_ik_singular, TRAC-IK's protocol: BENCHMARKS.md)."""
        if self.closed_form is None:
            return None
        found = self.closed_form.nearest_checked(req.target, req.seed)
        if found is None:
            return None
        q, e, jac = found
        ep, er = math.sqrt(e[:3] @ e[:3]), math.sqrt(e[3:] @ e[3:])
        tol_m, tol_rad = self.inner_tol
        if ep > tol_m or er > tol_rad or self._rank_lost(q, jac) or self.closed_form.singular(req.target):
            return None
        stats["attempts"] = 1
        return self.result(req, q, stats, (1e3 * ep, float(np.degrees(er))))

    def _nearest_fixed_point(
        self, req: SolveRequest, stats: dict
    ) -> tuple[IKResult | None, tuple[np.ndarray, IKResult] | None]:
        """The hybrid answer for one IK-Geo call: the closed forms' fixed point from their branch nearest the
        seed (:meth:`AnalyticIK.nearest`), where it converges, as on nearly every target. None otherwise,
        and the whole search follows (from the same branch first). The same answer as the search's, without
        checking every other branch first (faster: BENCHMARKS.md). Second: the branch and its fixed point's
        verdict where that missed (the search's first step, which it then need not repeat), else None."""
        if self.closed_form is None:
            return None, None
        q = self.closed_form.nearest(req.target, req.seed)  # checked on the hybrid FK: a miss fails there
        if q is None:
            return None, None
        stats["attempts"] = 1
        result = self._from_branch(req, q, stats, IKSolver._fixed_point_only)
        return (self._singular(result), None) if result.success else (None, (q, result))

    def _beyond_reach(self, target: np.ndarray, seed: np.ndarray, closed: np.ndarray) -> np.ndarray:
        """Where the closed forms give no exact branch within the limits: their least-squares answers within
        NEAR_M / NEAR_RAD of the target (a hybrid target just beyond the URDF model's reach), nearest the seed
        first; else none. Every classical restart there fails, and would take half the budget."""
        if self.closed_form is None or len(closed):
            return np.empty((0, self.model.chain.dof))
        near = self.closed_form.approximations(target, seed, seeding.NEAR_M, seeding.NEAR_RAD)
        if len(near):
            return near
        # beyond a fold of the URDF model (a wrist straight, q5 = 0), IK-Geo's least-squares wrist misses: a
        # few LM steps on the URDF model from each answer find its nearest point; so do they from the answers
        # past a joint limit, clipped into it (the nearest point within the limits)
        polished = []
        polish = self.urdf_lm._replace(max_iterations=POLISH_ITERATIONS)
        past_limits = self.closed_form.clipped(target, seed)
        for q in [*self.closed_form.approximations(target, seed, np.inf, np.inf), *past_limits]:
            q, ep, er, _ = polish.solve(target, q, float("inf"))
            if ep < seeding.NEAR_M and er < seeding.NEAR_RAD:
                polished.append(q)
        return np.array(polished).reshape(-1, self.model.chain.dof)

    def _rank_lost(self, q: np.ndarray, jac: np.ndarray | None = None) -> bool:
        """The URDF Jacobian at ``q`` (``jac``, when the caller has it) has lost rank: ``q`` is at a
        singularity. The classical stage asks, and then the verdict on the same answer: the last ``q``'s is
        kept (one assignment, as in ``_answers``)."""
        key = np.asarray(q, dtype=float).tobytes()
        last = self._last_rank
        if last is not None and last[0] == key:
            return last[1]
        if jac is None:
            jac = self.model.fk_and_jacobian_single(q, analytic=True)[1]
        # |det J| = Π σᵢ ≤ σ_min · σ_maxⁿ⁻¹ and σ_max ≤ ‖J‖_F: a determinant this far from zero proves σ_min
        # above SINGULAR for a third of an SVD's cost (a square Jacobian; nearly every answer is regular)
        n = jac.shape[1]
        regular = n == 6 and abs(np.linalg.det(jac)) > SINGULAR * float(np.vdot(jac, jac)) ** ((n - 1) / 2)
        lost = not regular and bool(np.linalg.svd(jac, compute_uv=False)[-1] < SINGULAR)
        self._last_rank = (key, lost)
        return lost

    def _singular(self, result: IKResult) -> IKResult:
        """Says so when a solved target is singular for the URDF model at the answer (its Jacobian has lost
        rank): there the solutions of that branch form a continuum, and the answer is the member the solver
        reached from the seed, near it."""
        if not result.success:
            return result
        if self._rank_lost(result.q):
            result.stats["singular"] = True
            result.message = (
                "solved; the target is singular (its solutions form a continuum): this one is the nearest the seed"
            )
        return result

    def _arrival(self, origin: np.ndarray | None, q: np.ndarray) -> np.ndarray | None:
        """The approach directions of a move from ``origin`` to ``q`` (4.); None: keep the current ones
        (no origin, or a model whose nets do not take directions)."""
        current = self.model.approach
        if origin is None or current is None or not self.options.arrive_from_seed:
            return None
        return approach.arrival_directions(origin, q, current)

    def _other_branch(
        self,
        req: SolveRequest,
        q0: np.ndarray,
        stats: dict,
        lm_beyond: bool = False,
        valleys: list[np.ndarray] | None = None,
    ) -> IKResult:
        """A cheaper :meth:`_from_branch` for the fallback branches: unbounded LM with the chord Jacobian (one
        hybrid FK per step), then with the hybrid one. At an exact singularity the error only halves per step; the
        floor and stall rules stop the runs that make no progress. ``lm_beyond``: LM follows a fixed point
        that stalled beyond the branch's reach too. ``valleys``: the solve's fallback points whose valleys
        were tried (appended to); the valley through a fixed point that missed, none of them, is searched
        before LM (:meth:`_valley_rows`; nothing to search where the point is not near a singularity, or
        without closed forms, where the solver searches no valleys). Once per point: restarts that end on one
        fixed point would trace its valley again. A restart's URDF answer with the wrist straight next to two
        limits can stall LM in the wrist's valley, where the valley through it holds the solution."""
        if req.analytic or not self.model.is_corrected:
            return self.result(req, q0, dict(stats))
        solver = self._approaching(self._arrival(req.origin, q0))
        q0, errors, beyond = solver.fixed_point(req.target, q0, req.deadline)
        result = solver.result(req, q0, dict(stats), errors)
        if result.success or (beyond and not lm_beyond):
            return result
        if valleys is not None and seeding.is_new_branch(q0, valleys) and solver.closed_form is not None:
            valleys.append(q0)  # where nothing was searched (not singular, too late), it would not be again
            found = solver._valley_rows(req, q0[None], stats)
            if found is not None:
                return found
        q, *_ = solver.refiner.unbounded(req.target, q0, req.deadline, chord_first=True)
        return solver.result(req, q, dict(stats))

    def _from_branch(
        self, req: SolveRequest, q0: np.ndarray, stats: dict, refine: Callable[..., IKResult] | None = None
    ) -> IKResult:
        """:meth:`_refine_branch` (or ``refine``, a function of the solver, the request, ``q0`` and the stats)
        over the model with the directions of the move from the request's origin (4.): once more if the
        refinement moved a joint to the other side of the origin."""
        refine = refine or IKSolver._refine_branch
        directions = self._arrival(req.origin, q0)
        result = refine(self._approaching(directions), req, q0, stats)
        if directions is None:
            return result
        again = self._arrival(req.origin, result.q)
        if not np.array_equal(again, directions):
            directions = again
            result = refine(self._approaching(directions), req, result.q, stats)
        result.stats["approach"] = directions.tolist()
        return result

    def fixed_point(
        self, target: np.ndarray, q0: np.ndarray, deadline: float, rounds: int = FIXED_POINT_ROUNDS
    ) -> tuple[np.ndarray, tuple[float, float] | None, bool]:
        """The closed forms' fixed point from ``q0`` (:meth:`FixedPoint.one`; ``q0`` with no errors without
        closed forms)."""
        return self.fixed_points(target, [q0], deadline, rounds)[0]

    def fixed_points(
        self, target: np.ndarray, starts: list[np.ndarray], deadline: float, rounds: int = FIXED_POINT_ROUNDS
    ) -> list[tuple[np.ndarray, tuple[float, float] | None, bool]]:
        """The closed forms' fixed points from each of ``starts`` side by side (:meth:`FixedPoint.many`)."""
        if self.closed_form is None:
            return [(q, None, False) for q in starts]
        return self._fixed_point.many(target, starts, deadline, rounds)

    def _fixed_point_only(
        self, req: SolveRequest, q0: np.ndarray, stats: dict, rounds: int = FIXED_POINT_ROUNDS
    ) -> IKResult:
        """The closed forms' fixed point alone (``rounds`` at most), stopped where it stalls: the cheap first
        try of a branch."""
        q, errors, beyond = self.fixed_point(req.target, q0, req.deadline, rounds)
        stats = dict(stats, method="closed-form fixed point")
        if beyond:
            stats["beyond_branch_reach"] = True
        return self.result(req, q, stats, errors)

    def _valley_only(
        self, req: SolveRequest, q0: np.ndarray, stats: dict, nearest: np.ndarray | None = None
    ) -> IKResult:
        """The root search along the singular valleys alone (:meth:`_valley`; a miss where it finds nothing)."""
        found = self._valley(req, q0, stats, nearest)
        return found if found is not None else self.result(req, q0, dict(stats))

    def _refine_branch(
        self, req: SolveRequest, q0: np.ndarray, stats: dict, fixed: IKResult | None = None, valley: bool = True
    ) -> IKResult:
        """The hybrid solution near the classical answer ``q0``: the closed forms' fixed point, then the box
        refinement, then, if that misses, damped LM on the hybrid model over the whole joint range (the bounded
        boxes crawl near a singularity). ``fixed``: the fixed point's result where it has run already and ``q0``
        is its answer; ``valley``: False where the valley search has run already."""
        q, errors = q0, None
        corrected = not req.analytic and self.model.is_corrected
        if time.perf_counter() > req.deadline:
            # the budget is spent (by the valley search, mostly): the verdict on what is there, no refinement
            # after the deadline (each stage's first step would run regardless, and the answer come late)
            if fixed is not None and np.array_equal(fixed.q, q0):
                return fixed
            return self.result(req, q0, dict(stats))
        if corrected and self.closed_form is not None:
            # ``fixed`` holds for its own answer only (a rerun with other approach directions starts elsewhere)
            ran = fixed is not None and np.array_equal(fixed.q, q0)
            result = fixed if ran else self._fixed_point_only(req, q0, stats)
            q = q0 = result.q
            if result.success:
                return result
            if result.stats.get("beyond_branch_reach"):  # no nearer on this branch: the others get the time
                return result
            found = self._valley(req, q0, stats) if valley else None
            if found is not None:
                return found
        if corrected:
            # the box keeps its own budget (its share of timeout_s), unless the valley search took the time
            q, info = self.refiner.refine(req.target, q0, req.deadline if "valley" in stats else float("inf"))
            errors = info.pop("errors", None)
            stats["refinements"] += 1
            stats.update(info)
        result = self.result(req, q, dict(stats), errors)
        if not result.success and corrected and time.perf_counter() < req.deadline:
            q, *_ = self.refiner.unbounded(req.target, q, req.deadline)
            stats["hybrid_lm"] = stats.get("hybrid_lm", 0) + 1
            result = self.result(req, q, dict(stats))
        return result

    def _valley(
        self,
        req: SolveRequest,
        q0: np.ndarray,
        stats: dict,
        nearest: np.ndarray | None = None,
        near: np.ndarray | None = None,
    ) -> IKResult | None:
        """The hybrid solution along the URDF model's singular valleys through ``q0`` and the closed forms'
        branches (or ``near``, where the caller has the rows to search: a target beyond the URDF model's reach
        has no branch, and its least-squares answers take their place), nearest ``nearest`` (else ``q0``) first
        (:mod:`~hybrid_kinematics_ros.ik.valley`); None when none is near a singularity or no root of the
        valleys reaches the target."""
        if not self._valley_time(req.deadline):
            return None
        # the valleys of every closed-form branch, one by one: at a shoulder singularity the solution can lie on
        # another branch's valley (the shoulder flipped), and the seed's wanders across the wrist's
        others = self.branches(req.target, q0) if near is None else near
        # then the exact branches past a joint limit: their valleys can enter the limits (valley.enter), where
        # the hybrid solution can lie (a UR10 with its wrist straight next to q3 = -2.8)
        past = [] if self.closed_form is None else self.closed_form.past_limits(req.target, q0)
        near = np.vstack([*([] if nearest is None else [nearest]), q0, *others, *past])
        return self._valley_rows(req, near, stats)

    def _valley_time(self, deadline: float) -> bool:
        """The valley search is on, and VALLEY_SHARE of the budget is left for it: tracing the valleys and
        settling their points take a few batched hybrid FKs."""
        return self.options.valley and deadline - time.perf_counter() >= VALLEY_SHARE * self.options.timeout_s

    def _valley_rows(self, req: SolveRequest, rows: np.ndarray, stats: dict) -> IKResult | None:
        """The search of :meth:`_valley` along the valleys through ``rows`` ``(B, n)`` alone, the first's first."""
        if not self._valley_time(req.deadline):
            return None
        starts = valley_starts(self.model, req.target, rows, self.limits, req.deadline, self.inner_tol[0])
        if starts is None:
            return None
        stats["valley"] = 0
        for q in starts:  # valley by valley, the seed's first: the next one is searched when these fail
            stats["valley"] += 1
            result = self.result(req, q, dict(stats, method="singular valley"))
            if not result.success and time.perf_counter() < req.deadline:  # a double root: LM finishes from near it
                q, *_ = self.refiner.unbounded(req.target, q, req.deadline)
                result = self.result(req, q, dict(stats, method="singular valley"))
            if result.success:
                return result
        return None

    def result(
        self, req: SolveRequest, q: np.ndarray, stats: dict, errors: tuple[float, float] | None = None
    ) -> IKResult:
        """The verdict on ``q`` for the request; ``errors`` (mm, deg) when the solver has just evaluated them
        there with the same model."""
        o = self.options
        analytic = req.analytic
        pos, rot = errors if errors is not None else self.refiner.errors(q, req.target, analytic)
        inside = self.model.in_calibrated_range_one(q)
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
        return IKResult(ok, q, pos, rot, message, time.perf_counter() - req.start, inside, stats)

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
        Where the closed forms give every exact branch (a target singular on none), those are the solutions'
        starts and no seed is searched: the seed's and ``extra_seeds``' searches would end on one of them, at a
        cost. A target just beyond the URDF model's reach (no exact branch; a hybrid target can lie there) starts
        from each branch's nearest point instead, as :meth:`solve` does: the seeds' URDF searches all fail there,
        after half the request's budget.
        """
        start = time.perf_counter()
        given = seed is not None
        target, seed = self.check(target, seed)
        origin = seed if given else None  # where the robot comes from, if the caller said (4.)
        end = float("inf") if deadline is None else deadline
        req = SolveRequest(target, seed, origin, analytic, start, end)
        found, search = self._many_starts(req, extra_seeds or [])
        found = self._searched(req, search, found, start + SEARCH_SHARE * (end - start))
        found.sort(key=lambda q: float(np.linalg.norm(q - seed)))
        return self._refined_many(req, found[:max_solutions])

    def _many_starts(self, req: SolveRequest, extra_seeds: list[np.ndarray]) -> tuple[list, list]:
        """:meth:`solve_many`'s solutions found already (the closed forms' exact branches, when the hybrid
        model refines them), and the starts the URDF model's LM searches from."""
        target, seed = req.target, req.seed
        branches = list(self.branches(target, seed))  # every branch at once: the seeds below only add the rest
        # a branch at a singularity has no closed-form answer: the spread of seeds searches for it too
        singular = self.closed_form is not None and self.closed_form.singular(target)
        # every exact solution is a checked branch (within the limits, nearest the seed); without one, a target
        # just beyond the URDF model's reach has its branches' nearest points: no seed search finds more
        starts = [] if singular else branches or list(self._beyond_reach(target, seed, np.empty((0, len(seed)))))
        if starts and not req.analytic and self.model.is_corrected:  # hybrid fixed points start from them as they are
            found: list[np.ndarray] = []
            for q in starts:
                if not any(seeding.same_solution(q, f, self.model.chain.revolute) for f in found):
                    found.append(q)
            return found, []
        if starts:  # the URDF model's own answers: LM polishes each to the inner tolerance, in a step or none
            return [], starts
        return [], [*branches, seed, *extra_seeds, *(() if branches and not singular else self.seeds.spread)]

    def _searched(
        self, req: SolveRequest, search: list[np.ndarray], found: list[np.ndarray], search_end: float
    ) -> list[np.ndarray]:
        """``found`` and the distinct solutions of the URDF model's LM from each of ``search``, until
        ``search_end``."""
        o = self.options
        tol_m, tol_rad = 1e-3 * o.position_tolerance_mm, np.radians(o.orientation_tolerance_deg)
        for s in search:
            now = time.perf_counter()
            if now > search_end:
                break
            seed_deadline = min(now + o.timeout_s, search_end)
            q, ep, er, _ = self.urdf_lm.solve(req.target, s, seed_deadline)
            if ep > tol_m or er > tol_rad:
                continue
            q = seeding.nearest_equivalent(q, req.seed, self.limits)
            if not any(seeding.same_solution(q, f, self.model.chain.revolute) for f in found):
                found.append(q)
        return found

    def _refined_many(self, req: SolveRequest, found: list[np.ndarray]) -> list[IKResult]:
        """Each of ``found`` refined through the hybrid model (the fixed points side by side where every start
        moves with the same approach directions), those that succeed, until the request's deadline."""
        target, end = req.target, req.deadline
        corrected = not req.analytic and self.model.is_corrected
        arrivals = [self._arrival(req.origin, q0) for q0 in found]
        fixed = {}
        batch = corrected and self.closed_form is not None and all(a is None for a in arrivals)
        if batch and time.perf_counter() <= end:
            fixed = dict(enumerate(self.fixed_points(target, found, end)))
        results = []
        for k, q0 in enumerate(found):
            if k not in fixed and time.perf_counter() > end:  # a fixed point run before the deadline is kept
                break
            solver = self._approaching(arrivals[k])
            result = None
            beyond = False
            if corrected and solver.closed_form is not None:
                q0, errors, beyond = fixed[k] if k in fixed else solver.fixed_point(target, q0, end)
                result = solver.result(req, q0, {"method": "closed-form fixed point"}, errors)
            if result is None or (not (result.success or beyond) and time.perf_counter() <= end):
                q, stats = solver.refiner.refine(target, q0, deadline=end) if corrected else (q0, {})
                result = solver.result(req, q, stats, stats.pop("errors", None))
            result.stats["path"] = self.path
            if result.success:
                results.append(result)
        return results

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
        n = len(targets)
        q = np.empty((n, self.model.chain.dof))
        if initial is not None:
            q[:] = np.asarray(initial, dtype=float).reshape(q.shape)
        prev = None if seed is None else np.asarray(seed, dtype=float)
        if prev is None and n and initial is None:  # no seed: the first pose's full solve picks the branch
            prev = self.solve(targets[0]).q
        path_lm = self.urdf_lm._replace(max_iterations=PATH_ITERATIONS)
        for i, target in enumerate(targets if initial is None else ()):
            target, from_q = self.check(target, prev)
            # the path's own extrapolation saves a step or two; the previous answer if that goes astray
            for start_q in ((2.0 * q[i - 1] - q[i - 2]) if i >= 2 else from_q, from_q):
                q[i], ep, er, _ = path_lm.solve(target, start_q, time.perf_counter() + self.options.timeout_s)
                if ep < seeding.NEAR_M and er < seeding.NEAR_RAD and np.abs(q[i] - from_q).max() < PATH_JUMP_RAD:
                    break
            prev = q[i]
        # each pose arrives from the one before, the first from the seed (4.)
        arrive = None
        if n and self.model.approach is not None and self.options.arrive_from_seed:
            origin = q[:1] if seed is None else np.asarray(seed, dtype=float)[None]
            arrive = approach.approach_directions(np.vstack([origin, q]), start=self.model.approach)[1:]
        conditions = None if arrive is None else self.model.conditions_with_approach(arrive)
        errors = self.refiner.batch_chord(targets, q, conditions)
        results = []
        for i in range(n):
            if np.isfinite(errors[i, 0]):
                chord = SolveRequest(targets[i], q[i], None, False, start, float("inf"))
                result = self.result(chord, q[i], {"method": "batch chord"}, tuple(errors[i]))
            else:  # from the pose before (its answer: the chord step leaves an unconverged pose's last iterate
                # in q), on the side its joints arrived from
                solver = self._approaching(None if arrive is None or not i else arrive[i - 1])
                result = solver.solve(targets[i], results[i - 1].q if i else seed)
            results.append(result)
        per_pose = (time.perf_counter() - start) / max(n, 1)
        for result in results:
            result.seconds = per_pose
        return results
