"""Every analytic IK branch of a URDF chain whose axes meet or run parallel the way most industrial arms' do.

At load, :func:`classify` reads the chain's joint axes at q = 0 and names its family (a spherical wrist, three
parallel axes, ...). For a family with closed forms, :class:`AnalyticIK` gets every exact branch from IK-Geo's
subproblem solvers (``ik-geo``, Elias and Wen 2022), in microseconds and exact near singularities, where an
iterative IK crawls. Chains of no such family (7 joints, prismatic joints, an offset wrist) have no
:class:`AnalyticIK`, and the iterative solver handles them alone.

IK-Geo's Python API answers wrongly, without an error, unless its conventions are met (``../FINDINGS.md``):
- the chain as a product of exponentials at q = 0 in the base frame: unit axes ``H (6, 3)`` and the vectors
  ``P (7, 3)`` from the base to a point on axis 1, ..., from a point on axis 6 to the tip;
- each family assumes the points where its axes meet: a URDF's joint origins are not those points, so each
  point slides along its own axis to the intersection;
- the tip's rotation at q = 0 is not part of the model: the target rotation goes in times its transpose;
- rotations go in as a list of columns; least-squares answers come mixed in with the exact ones; a wrong family
  gives NaN joints; answers lie in (-π, π].
So every branch is checked against our own FK, and folded by 2π into the joint limits, nearest the seed.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from hybrid_kinematics_ros.ik import round_kernel
from hybrid_kinematics_ros.ik.lm import joint_limits
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.se3 import error6, error6_batch

# Axes this close are parallel (rad), and lines this close meet (m). A URDF's rounded π/2 (1.57079633)
# leaves a wrist 7e-10 m from spherical: the branches are checked, and polished, on our own FK.
PARALLEL_RAD = 1e-6
MEET_M = 1e-6
# A branch whose pose (through our FK) misses the target by more than this is dropped: the family's
# assumptions do not hold well enough. Within it, the caller's LM polishes the branch in an iteration or two.
CHECK_M, CHECK_RAD = 1e-5, 1e-5
POLISH = 1e-10  # (m and rad) a branch further off gets one Newton step on our FK
TAU = 2 * np.pi
# Up to this many branches are checked one by one on the single-configuration path: a batch's FK, errors and SVD
# cost about as much for any few rows as this many rows alone; a near-singular target's search asks for its
# branches twice.
SINGLE_CHECKS = 4

# Families with closed forms in IK-Geo, most specific first (its search-based ones find nothing on a UR10).
FAMILIES = (
    "spherical_two_parallel",
    "spherical_two_intersecting",
    "three_parallel_two_intersecting",
    "spherical",
    "three_parallel",
)


@dataclass(frozen=True)
class Geometry:
    """The chain at q = 0 in the base frame: unit axes ``(n, 3)``, a point on each ``(n, 3)``, the tip ``(4, 4)``."""

    axes: np.ndarray
    points: np.ndarray
    tip: np.ndarray


def geometry(chain: Chain) -> Geometry:
    frames = fk.joint_frames(chain, np.zeros(chain.dof))[0]
    axes = np.einsum("kij,kj->ki", frames[:-1, :3, :3], chain.axes)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return Geometry(axes, frames[:-1, :3, 3].copy(), frames[-1])


def _parallel(g: Geometry, i: int, j: int) -> bool:
    return bool(np.linalg.norm(np.cross(g.axes[i], g.axes[j])) < PARALLEL_RAD)


def meeting_point(g: Geometry, i: int, j: int) -> np.ndarray | None:
    """Where the (non-parallel) axes ``i`` and ``j`` meet, or None if they pass each other."""
    if _parallel(g, i, j):
        return None
    a, b, pa, pb = g.axes[i], g.axes[j], g.points[i], g.points[j]
    # the closest points pa + s a and pb + t b: their difference is normal to both axes
    m = np.array([[a @ a, -(a @ b)], [a @ b, -(b @ b)]])
    s, t = np.linalg.solve(m, [(pb - pa) @ a, (pb - pa) @ b])
    x, y = pa + s * a, pb + t * b
    return 0.5 * (x + y) if np.linalg.norm(x - y) < MEET_M else None


def _on_axis(g: Geometry, k: int, point: np.ndarray) -> bool:
    d = point - g.points[k]
    return bool(np.linalg.norm(d - (d @ g.axes[k]) * g.axes[k]) < MEET_M)


def classify(chain: Chain) -> tuple[str, np.ndarray] | None:
    """The chain's closed-form family and the points ``(6, 3)`` on its axes that the family expects (where
    the axes meet), or None: not six revolute joints, or no family with closed forms fits."""
    if chain.dof != 6 or not np.all(chain.revolute):
        return None
    g = geometry(chain)
    points = g.points.copy()
    wrist = meeting_point(g, 3, 4)
    if wrist is not None and _on_axis(g, 5, wrist):
        points[3:6] = wrist
        if _parallel(g, 1, 2):
            return "spherical_two_parallel", points
        shoulder = meeting_point(g, 0, 1)  # IK-Geo's family: axes 1 and 2 meet (it never reads p12)
        if shoulder is not None:
            points[0:2] = shoulder
            return "spherical_two_intersecting", points
        return "spherical", points
    if _parallel(g, 1, 2) and _parallel(g, 2, 3):
        tool = meeting_point(g, 4, 5)
        if tool is not None:
            points[4:6] = tool
            return "three_parallel_two_intersecting", points
        return "three_parallel", points
    return None


class AnalyticIK:
    """Every exact closed-form branch of one chain's URDF model (see the module docstring)."""

    def __init__(self, chain: Chain, family: str, points: np.ndarray) -> None:
        """``points``: on each axis, where the family expects them (:func:`classify`)."""
        import ik_geo  # a compiled wheel: imported only where a chain has closed forms

        self.chain, self.family = chain, family
        g = geometry(chain)
        h = g.axes
        p = np.vstack([points[0], np.diff(points, axis=0), g.tip[:3, 3] - points[-1]])
        self._robot = getattr(ik_geo.Robot, family)(h.tolist(), p.tolist())
        self._tip_rotation_t = g.tip[:3, :3].T  # R_target · R_tip(0)ᵀ is what IK-Geo's model reaches
        self.lower, self.upper, _ = joint_limits(chain)  # an unlimited joint: ±2π, as the iterative solver
        self._limits = (np.ascontiguousarray(self.lower, dtype=float), np.ascontiguousarray(self.upper, dtype=float))
        self._last: tuple[bytes, tuple[np.ndarray, np.ndarray]] | None = None  # the last answers (_answers)

    @classmethod
    def of(cls, chain: Chain) -> AnalyticIK | None:
        """The chain's analytic IK, or None where it has no closed forms."""
        found = classify(chain)
        if found is None:
            return None
        try:
            return cls(chain, *found)
        except ImportError:  # ik-geo not installed (requirements.txt has it): the iterative solver, which says so
            return None

    def _answers(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IK-Geo's exact and least-squares answers, each ``(k, 6)`` in (-π, π], the NaN ones (a wrong family)
        dropped. A solve asks for both of one target (its branches, then whether it is singular): the last
        target's are kept (replaced in one assignment, so a solver shared between threads reads a consistent
        pair)."""
        key = target.tobytes()
        last = self._last
        if last is not None and last[0] == key:
            return last[1]
        rotation = target[:3, :3] @ self._tip_rotation_t
        answers = self._robot.get_ik(rotation.T.tolist(), target[:3, 3].tolist())  # columns, not rows
        split = (_finite([q for q, ls in answers if not ls]), _finite([q for q, ls in answers if ls]))
        self._last = (key, split)
        return split

    def singular(self, target: np.ndarray) -> bool:
        """Whether some branch of the target is at a singularity: there IK-Geo flags its answer as least
        squares; it reaches the target's position, and its wrist misses the orientation (the branch's
        solutions form a continuum, which the iterative solver samples nearest the seed). Least-squares
        answers of a branch out of reach miss the position by centimetres."""
        q = self._answers_of(target, least_squares=True)
        if not len(q):
            return False
        reached = fk.fk_single(self.chain, q)[:, :3, 3]  # a few answers: fk's set-up would cost four times more
        return bool(np.any(np.linalg.norm(reached - target[:3, 3], axis=1) < CHECK_M))

    def raw_branches(self, target: np.ndarray) -> np.ndarray:
        """IK-Geo's exact answers ``(k, 6)`` in (-π, π], unchecked."""
        return self._answers_of(target, least_squares=False)

    def _answers_of(self, target: np.ndarray, least_squares: bool) -> np.ndarray:
        """IK-Geo's exact (or least-squares) answers ``(k, 6)`` in (-π, π] (:meth:`_answers`)."""
        return self._answers(target)[int(least_squares)]

    def approximations(self, target: np.ndarray, seed: np.ndarray, miss_m: float, miss_rad: float) -> np.ndarray:
        """IK-Geo's least-squares answers ``(k, 6)`` within the limits that our FK takes to within ``miss_m``
        and ``miss_rad`` of the target, nearest the seed first. A hybrid model's target can lie just beyond
        its URDF model's reach (a UR arm's wrist a fraction of a millimetre inside the cylinder its shoulder
        offset leaves around axis 1): no exact branch exists, and these are where the URDF model gets
        nearest, next to the hybrid solutions."""
        q = fold(self._answers_of(target, least_squares=True), seed, self.lower, self.upper)
        if not len(q):
            return q
        e = error6_batch(target, fk.fk(self.chain, q))
        q = q[(np.linalg.norm(e[:, :3], axis=1) < miss_m) & (np.linalg.norm(e[:, 3:], axis=1) < miss_rad)]
        return q[np.argsort(np.linalg.norm(q - seed, axis=1), kind="stable")]

    def clipped(self, target: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """IK-Geo's answers ``(k, 6)``, exact and least-squares, that have no copy within the limits
        (:meth:`past_limits`), clipped into them: where the URDF model reaches the target (or gets nearest) only
        past a joint limit (a UR10 near its q2 = 0 or q3 = -2.8 limit with its wrist straight), starts for its
        nearest point within them."""
        return np.clip(self.past_limits(target, seed, least_squares=True), self.lower, self.upper)

    def past_limits(self, target: np.ndarray, seed: np.ndarray, least_squares: bool = False) -> np.ndarray:
        """IK-Geo's exact answers ``(k, 6)`` (and its least-squares ones with ``least_squares``) that have no copy
        within the limits, unchecked: each joint's copy within them nearest the seed, and where a joint has
        none, its copy nearest the limits (the one past the lower limit or the one past the upper, whichever
        is nearer; the seed does not choose: a UR10's q3 at -2.9 is 0.1 past its -2.8 limit, its copy at 3.38
        0.58 past 2.8). A hybrid target near a singularity and next to a limit can have its solution within the
        limits while every exact branch of the URDF model lies past them (a UR10 with its wrist straight next
        to q3 = -2.8): the valley search walks from these into the limits."""
        q = np.vstack(self._answers(target) if least_squares else self._answers(target)[:1]).reshape(-1, 6)
        first, last = _turn_range(q, self.lower, self.upper)
        past = (first > last).any(axis=1)
        q, first, last = q[past], first[past], last[past]
        # no copy within: q + TAU * last lies below the lower limit, q + TAU * first above the upper
        nearer = np.where(self.lower - (q + TAU * last) <= q + TAU * first - self.upper, last, first)
        inside = np.clip(np.round((seed - q) / TAU), first, last)
        return q + TAU * np.where(first <= last, inside, nearer)

    def nearest(self, target: np.ndarray, seed: np.ndarray) -> np.ndarray | None:
        """The exact branch within the limits nearest the seed, unchecked (the caller checks it on the model it
        solves for), or None."""
        q = round_kernel.nearest_copy(self.raw_branches(target), np.ascontiguousarray(seed, dtype=float), *self._limits)
        return q if len(q) else None

    def branches(self, target: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """Every exact branch ``(k, 6)`` within the joint limits, each joint shifted by 2π to lie nearest the
        seed, that our own FK takes to within CHECK_M / CHECK_RAD of the target (:meth:`_checked`); nearest
        the seed first."""
        q = self._checked(fold(self.raw_branches(target), seed, self.lower, self.upper), target)[0]
        return q[np.argsort(np.linalg.norm(q - seed, axis=1), kind="stable")]

    def nearest_checked(self, target: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The first row of :meth:`branches` for the cost of one, with its pose error ``(6,)``
        (:func:`~hybrid_kinematics_ros.kinematics.se3.error6`) and Jacobian on our FK: the exact branch within the
        limits nearest the seed, checked; None where it fails the check (another branch may then be the
        nearest that passes)."""
        q = self.nearest(target, seed)
        if q is None:
            return None
        q, e, jac = self._checked(q[None], target)
        return (q[0], e[0], jac[0]) if len(q) else None

    def _checked(self, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The rows of ``q (k, 6)`` that our own FK takes to within CHECK_M / CHECK_RAD of the target, after
        one Newton step on those further off than POLISH (a URDF's rounded angles leave the family's
        assumptions off by nanometres, which a near-singular wrist turns into microradians); with their
        pose errors ``(k, 6)``, and for one row its Jacobian ``(1, 6, 6)`` at the answer (the quick answer's
        rank check takes it; a batch's are not kept up to date after the polish, so None)."""
        if len(q) == 1:  # the single-configuration path: a batch of one costs several times more
            return self._checked_one(q, target)
        if 1 < len(q) <= SINGLE_CHECKS:
            rows = [self._checked_one(q[i : i + 1], target) for i in range(len(q))]
            return np.vstack([r[0] for r in rows]), np.vstack([r[1] for r in rows]), None
        if not len(q):
            return q, np.empty((0, 6)), None
        T, jac = fk.fk_and_jacobian(self.chain, q)
        e = error6_batch(target, T)
        rough = np.linalg.norm(e, axis=1) > POLISH
        if rough.any():
            q[rough] = np.clip(q[rough] + _newton(jac[rough], e[rough]), self.lower, self.upper)
            e[rough] = error6_batch(target, fk.fk(self.chain, q[rough]))
        ok = (np.linalg.norm(e[:, :3], axis=1) < CHECK_M) & (np.linalg.norm(e[:, 3:], axis=1) < CHECK_RAD)
        return q[ok], e[ok], None

    def _checked_one(self, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """:meth:`_checked` of one row ``q (1, 6)``, in few numpy calls (the quick answer's path)."""
        T, jac = fk.fk_and_jacobian_single(self.chain, q[0])
        e = error6(target, T)
        if e @ e > POLISH * POLISH:
            q = np.clip(q + _newton(jac[None], e[None]), self.lower, self.upper)
            T, jac = fk.fk_and_jacobian_single(self.chain, q[0])
            e = error6(target, T)
        if e[:3] @ e[:3] < CHECK_M * CHECK_M and e[3:] @ e[3:] < CHECK_RAD * CHECK_RAD:
            return q, e[None], jac[None]
        return q[:0], np.empty((0, 6)), None


_NONE = np.empty((0, 6))
_NONE.setflags(write=False)


def _finite(rows: list[list[float]]) -> np.ndarray:
    """``(k, 6)`` of the rows with every joint finite, read-only (the last target's are shared)."""
    if not rows:
        return _NONE
    q = np.array(rows, dtype=float).reshape(-1, 6)
    if not np.isfinite(q.sum()):
        q = q[np.isfinite(q).all(axis=1)]
    q.setflags(write=False)
    return q


def _newton(jac: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Least-squares steps ``(k, 6)`` for Jacobians ``(k, 6, 6)`` and errors ``(k, 6)`` (rank-deficient at a
    singularity: the pseudo-inverse, through the SVD)."""
    u, s, vt = np.linalg.svd(jac)
    inv = np.where(s > 1e-9 * s[:, :1], 1.0 / np.where(s > 0, s, 1.0), 0.0)
    return np.einsum("kji,kj,klj,kl->ki", vt, inv, u, e)


def fold(q: np.ndarray, seed: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Each row's joints shifted by a multiple of 2π to the value within ``[lower, upper]`` nearest the seed;
    rows with a joint that has no such value are dropped."""
    q = np.asarray(q, dtype=float).reshape(-1, len(seed))
    first, last = _turn_range(q, lower, upper)
    shift = np.minimum(np.maximum(np.round((seed - q) / TAU), first), last)
    return (q + TAU * shift)[(first <= last).all(axis=1)]


def _turn_range(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fewest and the most whole turns (whole floats, each ``q``'s shape) that keep each joint of ``q``
    within ``[lower, upper]``; first > last where none does."""
    return np.ceil((lower - 1e-12 - q) / TAU), np.floor((upper + 1e-12 - q) / TAU)


def turns(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Every copy of each row of ``q (k, n)`` with its joints shifted by multiples of 2π within ``[lower, upper]``
    (the rows themselves included): the same pose for the URDF model, another problem for a hybrid model, whose
    nets see raw joint values (on a UR arm's ±2π joints, 2⁶ copies of each branch)."""
    first, last = _turn_range(q, lower, upper)
    copies = [
        itertools.product(*(row[j] + TAU * np.arange(lo[j], hi[j] + 1) for j in range(len(row))))
        for row, lo, hi in zip(q, first, last, strict=True)
    ]
    return np.array(list(itertools.chain.from_iterable(copies)), dtype=float).reshape(-1, q.shape[1])
