"""The hybrid solutions near a singularity of the URDF model, by a root search along its weak direction.

At a singularity of the URDF model (a wrist with q5 = 0, the wrist centre on axis 1, the elbow stretched),
the URDF Jacobian loses a direction of the pose (``u``) and gains a joint motion that does nothing (``v``).
The hybrid model's corrections change along ``v`` by micrometres per radian, so its solutions lie somewhere
along a valley a whole turn long, where every local method (the closed forms' fixed point, whose chord
Jacobian is singular there, and LM, whose basin is a few milliradians wide) crawls or settles in a local
minimum of the valley.

The search here is global along the valley and local across it:
1. The valley is traced on the URDF model from its first point (:func:`trace`): steps along the weak motion,
   each followed by a Newton step back onto it, one period of it or from joint limit to joint limit. No single
   joint parameterises a valley everywhere: a UR10's wrist continuum whose wrist circle crosses the arm's
   reach passes the stretched elbow and turns back in every joint there (a grid over one joint follows one
   side of it only; ``test_valley.py``).
2. At every traced point, all at once (batched hybrid FK), Gauss-Newton's chord steps in the five joints but
   the one that moves most along the valley there remove the error the model can remove; what is left is a
   scalar ``r``: the error along the lost direction, signed by the 6×5 Jacobian's cofactor vector, which
   turns smoothly along the valley (neighbours compare it in one joint's convention).
3. Each sign change of ``r`` between neighbours brackets a hybrid solution; a few regula falsi steps find
   ``r = 0``, where the whole 6-D error vanishes up to the five joints' convergence. The caller's LM on the
   hybrid model finishes from there, in its basin.
4. The chord steps move the five joints across the valley, where ``r`` does not change to first order:
   ``r`` at the traced points themselves, one batched hybrid FK, changes sign where the settled one does
   (nearly always), and a valley with a sign change there nearly always holds a solution, one without
   rarely. So a valley without one is settled and searched after the others.
5. A local minimum of ``|r|`` that does not cross zero is a double root only at the fold itself; elsewhere
   the LM from it fails, after a whole run. On each valley the crossings come first.

Every closed-form branch has its own valley, and the hybrid solution need not lie on the seed's: at a shoulder
singularity (the wrist centre on axis 1) it can lie on the valley of the shoulder flipped, and a valley that
crosses the wrist's singularity cannot be followed across it. So the valleys of all branches are searched,
one after the other, the seed's first, each only when the previous ones' starts failed: a solution on the
seed's valley then costs that valley alone, where all of them in one batch cost more than a request's budget.

A branch past a joint limit has its valley too, and the valley can cross into the limits where the hybrid
solution lies: a UR10 with its wrist straight next to its q3 = -2.8 limit can have every exact branch past it
(q3 = -3.06 and -2.67) and its solution at -2.78, which LM restarts find only after many times the budget.
Such a branch is walked along its valley into the limits (:func:`enter`) and searched from there, after the
branches within them.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np

from hybrid_kinematics_ros.ik import valley_kernel
from hybrid_kinematics_ros.ik.lm import Limits, joint_limits, project, turned, wrap
from hybrid_kinematics_ros.kinematics.se3 import error6_batch
from hybrid_kinematics_ros.model.hybrid import HybridModel

# Each valley is traced from its first point, TRACE_STEP (rad, joint space) apart, one period or from limit to
# limit, at most TRACE_POINTS points a way (a UR10's wrist continuum: 15-30 points); it has closed when it
# comes back within CLOSED steps of its start; where one Newton step moves a point further than TURN times
# the step along (a sharp turn), the step halves, up to TURN_HALVINGS times, so that the trace does not jump
# across the turn. Then POINT_STEPS chord steps settle the five joints at each point (the traced points lie on
# the URDF model's valley, millimetres from the hybrid one), a valley's points in one batch through the hybrid
# FK, and BRACKET_STEPS regula falsi steps within a bracket. TRACE_STEP and POINT_STEPS: chosen by the roots
# they find on near-singular UR10 targets (a longer step, or one chord step, finds fewer).
TRACE_STEP = 0.35
TRACE_POINTS = 40
CLOSED = 0.75
TURN, TURN_HALVINGS = 1.0, 3
POINT_STEPS = 2
BRACKET_STEPS = 6
MAX_ROOTS = 4  # brackets refined (all at once) on each valley, nearest the first q_near first
TOUCH_STEPS = 3  # parabola steps at a double root
SETTLE_STEPS = 1  # a bracket's points lie between settled ones: one chord step is enough
SINGLE_ROWS = 2  # settle's rows evaluated one by one up to this many
SETTLED = 1e-5  # m (or rad): a point whose five joints leave more across the valley brackets nothing
# Where the URDF model counts as near-singular for this search: the Jacobian's smallest singular value (m or
# rad per rad; a regular UR10 pose has 0.05-0.5; a hybrid target at q5 = 0 gives the URDF model's answer
# 1e-4 to 2e-2, as far as its millimetres of correction take it from the singularity).
NEAR_SINGULAR = 3e-2


def weak_direction(model: HybridModel, q: np.ndarray) -> tuple[np.ndarray, float]:
    """The URDF Jacobian's weakest joint motion at ``q`` (unit) and its singular value."""
    _, sv, vt = np.linalg.svd(model.fk_and_jacobian_single(q, analytic=True)[1])
    return vt[-1], float(sv[-1])


_MINORS = np.array([[r for r in range(6) if r != i] for i in range(6)])  # the rows of each 5×5 minor
_SIGNS = (-1.0) ** np.arange(6)


def _normal(J5: np.ndarray) -> np.ndarray:
    """``(K, 6)``: a unit vector normal to the five columns of each ``J5 (K, 6, 5)``, from their signed 5×5
    minors (the generalised cross product), so that it turns continuously with the columns (an SVD's sign
    is arbitrary)."""
    u = _SIGNS * np.linalg.det(J5[:, _MINORS, :])
    return u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)


def _poses_and_jacobians(model: HybridModel, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hybrid poses and URDF Jacobians of ``Q (K, n)``: batched, or row by row on the single-pose path for a
    few rows (a batch, however small, costs a few single poses)."""
    if len(Q) <= SINGLE_ROWS:
        single = [(model.fk_single(q), model.fk_and_jacobian_single(q, analytic=True)[1]) for q in Q]
        return np.stack([T for T, _ in single]), np.stack([J for _, J in single])
    return model.fk(Q), model.fk_and_jacobian(Q, analytic=True)[1]


def _onto(
    model: HybridModel, pose: np.ndarray, x: np.ndarray, border: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """One Newton step from ``x`` back onto the valley of the URDF ``pose``, along no ``border``: the point, the
    weak motion there and the step's length (inf where the bordered matrix is singular). With J's weak motion
    w, (JᵀJ + v vᵀ) w = v (w·v): the bordered matrix turns v into w, and Jᵀe has next to nothing along w (J's
    smallest singular value times the error's lost part). Compiled (:mod:`valley_kernel`)."""
    arrays = (np.ascontiguousarray(a, dtype=float) for a in (pose, x, border, v))
    return valley_kernel.onto(*arrays, *model.chain.kernel_operands)


def _advance(
    model: HybridModel, pose: np.ndarray, q: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The next point of the valley of the URDF ``pose`` from its point ``q`` along its weak motion ``v``, and
    the weak motion there: TRACE_STEP on, halved where the valley turns sharply (a Newton step back onto it
    longer than TURN times the step), up to TURN_HALVINGS times; None where no step short enough keeps to it.
    On ``q``'s turn: the caller wraps it across a seam (:func:`_across_seams`). Compiled (:mod:`valley_kernel`)."""
    q, v = (np.ascontiguousarray(a, dtype=float) for a in (q, v))
    x, w, ok = valley_kernel.advance(pose, q, v, TRACE_STEP, TURN, TURN_HALVINGS, *model.chain.kernel_operands)
    return (x, w) if ok else None


def warm_up(model: HybridModel, q: np.ndarray) -> None:
    """Loads the compiled steps (:mod:`valley_kernel`'s entry points) with a step from ``q``, so that a first
    search does not (loading them from numba's cache takes a good part of a request's budget)."""
    pose, along = model.fk_single(q, analytic=True), np.eye(len(q))[0]
    _advance(model, pose, q, along)
    _onto(model, pose, q, along, along)
    _settle_along(model, pose, q[None], np.array([0]), joint_limits(model.chain), 1)


def _across_seams(x: np.ndarray, limits: Limits) -> np.ndarray:
    """``x`` with each revolute joint whose range is at most a whole turn (a UR10's ±π) wrapped by 2π where it
    passed a limit and the wrapped value lies within them: the valley goes on across the seam. A joint of a
    wider range (an RX160's ±270°) is not: its other copy is another problem for the nets, which see raw
    joint values, and another part of the valley."""
    lower, upper, revolute = limits
    return wrap(x, lower, upper, revolute & (upper - lower <= 2.0 * np.pi + 1e-9))


def enter(
    model: HybridModel, q0: np.ndarray, v0: np.ndarray, limits: Limits, deadline: float = float("inf")
) -> tuple[np.ndarray, np.ndarray] | None:
    """A point ``q0`` of a valley past the joint limits, walked along its valley (weak motion ``v0`` at ``q0``)
    into them: the first point within them and its weak motion, or None where the valley comes no nearer to
    them either way. At a singularity the valley is a continuum of the URDF model's solutions, and a hybrid
    target's can cross the limits where every closed-form branch lies past them (a UR10 with its wrist
    straight next to its q3 = -2.8 limit: branches at q3 = -3.06, the hybrid solution at -2.78)."""
    lower, upper, _ = limits

    def past(x: np.ndarray) -> float:
        return float(np.sum(np.maximum(lower - x, 0.0) + np.maximum(x - upper, 0.0)))

    pose = model.fk_single(q0, analytic=True)
    for sign in (1.0, -1.0):
        q, v, left = q0, sign * v0, past(q0)
        for _ in range(TRACE_POINTS):
            ahead = _advance(model, pose, q, v) if time.perf_counter() < deadline else None
            x = None if ahead is None else _across_seams(ahead[0], limits)
            if x is None or past(x) >= left:
                break
            (q, v), left = (x, ahead[1]), past(x)
            if left == 0.0:
                return q, v
    return None


def trace(
    model: HybridModel, q0: np.ndarray, v0: np.ndarray, limits: Limits, deadline: float = float("inf")
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The valley of the URDF model through ``q0``, in order: points TRACE_STEP apart along its weak motion
    (``v0`` at ``q0``), each moved back onto the valley by a Newton step in the five strong directions of the
    error to the URDF pose at ``q0``. One period of it (closed: it comes back next to ``q0`` up to whole
    turns), else from joint limit to joint limit, at most TRACE_POINTS a way. Returns the points ``(m, n)``,
    their weak motions ``(m, n)`` and whether it closed.

    Along the valley, no single joint need move monotonically: where the elbow stretches on the way (a UR10's
    wrist continuum whose wrist circle crosses the arm's reach) the valley turns back in every joint, and a
    grid over one joint follows one side of it only. ``deadline``: the part traced by then (the search goes on
    with it)."""
    lower, upper, revolute = limits
    pose = model.fk_single(q0, analytic=True)
    halves, closed = [], False
    eye = np.eye(len(q0))

    for sign in (1.0, -1.0):
        q, v, points, motions = q0, sign * v0, [], []
        for _ in range(TRACE_POINTS):
            if time.perf_counter() > deadline:  # the part traced so far is searched
                break
            ahead = _advance(model, pose, q, v)
            if ahead is None:  # no step short enough keeps to it: this way ends here
                break
            x, w = ahead
            # a joint of a whole turn crosses its seam (a UR10 target with its wrist straight next to its q2 and
            # q3 limits: the valley from the branches past them enters the limits as q4 crosses π)
            wrapped = _across_seams(x, limits)
            beyond = (wrapped < lower) | (wrapped > upper)
            if beyond.any():
                # a last point on the limit, that joint held there (and settled so): a root between the
                # last point and the limit is bracketed
                reach = (np.where(x < lower, lower, upper) - q) / np.where(beyond, x - q, np.inf)
                first = int(np.argmin(np.where(beyond, reach, np.inf)))
                if reach[first] > 0.1:  # else the last point is on the limit already
                    x = project(_onto(model, pose, q + reach[first] * (x - q), eye[first], v)[0], *limits)
                    points.append(x)
                    motions.append(eye[first])
                break
            q, v = wrapped, w
            points.append(q)
            motions.append(v)
            if len(points) > 2 and np.linalg.norm(turned(q - q0, revolute)) < CLOSED * TRACE_STEP:
                closed = True
                break
        halves.append((points, motions))
        if closed:
            break
    if closed:  # the half that came back (the second, if the first ended at a limit); its last point is q0 again
        (way, way_motions), facing = halves[-1], (-1.0) ** (len(halves) - 1)
        points, motions = [q0, *way[:-1]], [facing * v0, *way_motions[:-1]]
    else:
        back, ahead = halves
        points = [*back[0][::-1], q0, *ahead[0]]
        motions = [*(-m for m in back[1][::-1]), v0, *ahead[1]]
    return np.array(points), np.array(motions), closed


def _free(j: np.ndarray, n: int) -> np.ndarray:
    """``(K, n - 1)``: each row's joints but ``j (K,)``."""
    return np.nonzero(np.arange(n) != j[:, None])[1].reshape(len(j), n - 1)


def settle(
    model: HybridModel,
    target: np.ndarray,
    Q: np.ndarray,
    j: np.ndarray,
    limits: Limits,
    steps: int,
    deadline: float = float("inf"),
    at: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chord steps in the free joints of every row of ``Q (K, n)`` (in place), each row's valley joint
    ``j (K,)`` held. Returns ``Q``, the pose errors ``(K, 6)`` and the URDF Jacobians ``(K, 6, n)`` there.
    ``deadline``: no step after it (a step of a whole valley's points takes milliseconds, and the answer would
    come after the budget); the errors and Jacobians are still those at ``Q``.
    ``at``: the errors and Jacobians at ``Q`` as given, where the caller has evaluated them already."""
    n = Q.shape[1]
    free = _free(j, n)
    rows = np.arange(len(Q))[:, None]
    free_limits = tuple(side[free] for side in limits)
    for step in range(steps + 1):
        if step == 0 and at is not None:
            e, J = at
        else:
            T, J = _poses_and_jacobians(model, Q)
            e = error6_batch(target, T)
        if step == steps or time.perf_counter() > deadline:  # the last evaluation measures, no step follows it
            break
        J5 = np.take_along_axis(J, free[:, None, :], axis=2)
        jt = J5.mT
        delta = np.linalg.solve(jt @ J5 + 1e-12 * np.eye(n - 1), jt @ e[:, :, None])[:, :, 0]
        Q[rows, free] = project(Q[rows, free] + delta, *free_limits)
    return Q, e, J


def along(e: np.ndarray, J: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The signed error along the lost direction ``(K,)``, normal to the URDF Jacobian's columns but joint
    ``j (K,)``'s, and the error left across it ``(K,)`` (m and rad as one vector: what those five joints did
    not remove). The sign depends on ``j``: compare rows in one joint's convention."""
    free = _free(j, J.shape[2])
    u = _normal(np.take_along_axis(J, free[:, None, :], axis=2))
    r = np.einsum("ki,ki->k", u, e)
    return r, np.linalg.norm(e - r[:, None] * u, axis=1)


def _settle_along(
    model: HybridModel, target: np.ndarray, Q: np.ndarray, j: np.ndarray, limits: Limits, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`settle`, then :func:`along` in each row's own joint: ``Q``, ``r`` and the error across. One row (a
    valley's first bracket, a double root) on the compiled path: in numpy, most of a bracket step is call
    overhead, not the two hybrid poses (:mod:`valley_kernel`)."""
    if len(Q) != 1:
        Q, e, J = settle(model, target, Q, j, limits, steps)
        return (Q, *along(e, J, j))
    lower, upper, _ = limits
    urdf = model.chain.kernel_operands
    q, joint = np.ascontiguousarray(Q[0], dtype=float), int(j[0])
    for _ in range(steps):
        q = valley_kernel.settle_step(target, model.fk_single(q), q, joint, lower, upper, *urdf)
    r, across = valley_kernel.along_one(target, model.fk_single(q), q, joint, *urdf)
    return q[None], np.array([r]), np.array([across])


def valley_starts(
    model: HybridModel,
    target: np.ndarray,
    q_near: np.ndarray,
    limits: Limits,
    deadline: float,
    tol: float,
) -> Iterator[np.ndarray] | None:
    """Starts next to the hybrid solutions along the valleys through ``q_near`` (``(n,)``, or ``(B, n)``: the
    closed forms' branches), valley by valley in the order of the rows (the seed's first), on each at most
    MAX_ROOTS, nearest the first row first (module docstring), each within ``tol`` (m or rad) of the target
    where the search converged; None when no row of ``q_near`` is near a singularity of the URDF model, or the
    chain has other than six joints (no search).

    Lazily: each valley is traced and searched when the caller asks for the starts after the previous
    valley's, so that a solution on the seed's valley costs that valley alone."""
    if len(limits[2]) != 6:
        return None
    rows = np.atleast_2d(q_near)
    weak = [weak_direction(model, q) for q in rows]
    singular = [(q, v) for q, (v, sigma) in zip(rows, weak, strict=True) if sigma <= NEAR_SINGULAR]
    if not singular:
        return None
    return _search(_Valley(model, target, limits, deadline, tol), singular, rows[0])


class _Valley(NamedTuple):
    """What every step of one valley search shares: the model, the target, the joint limits, the deadline
    (``time.perf_counter()`` time) and the error a root is found to (m or rad)."""

    model: HybridModel
    target: np.ndarray
    limits: Limits
    deadline: float
    tol: float


def _search(s: _Valley, singular: list[tuple[np.ndarray, np.ndarray]], near: np.ndarray) -> Iterator[np.ndarray]:
    """:func:`valley_starts`' generator: ``singular`` holds the rows near a singularity with their weak
    motions; a row on a valley traced already starts none of its own, and a row past the limits (a closed-form
    branch there) the valley it enters them on (:func:`enter`), if any. A valley whose traced points' errors
    along the lost direction change sign nowhere is searched after the others (module docstring, 4.)."""
    model, target, limits, deadline, _ = s
    traced: list[np.ndarray] = []
    later: list[tuple[tuple[np.ndarray, np.ndarray, bool], tuple[np.ndarray, np.ndarray], tuple]] = []
    lower, upper, _ = limits
    for q, v in singular:
        if time.perf_counter() > deadline:
            return
        if np.any((q < lower) | (q > upper)):  # a row past the limits starts where its valley enters them
            entered = enter(model, q, v, limits, deadline)
            if entered is None:
                continue
            q, v = entered
        # a row on a valley traced already (in raw joint values: the nets see another turn as another problem)
        if any(np.linalg.norm(points - q, axis=1).min() < TRACE_STEP for points in traced):
            continue
        path = trace(model, q, v, limits, deadline)
        traced.append(path[0])
        if time.perf_counter() > deadline:  # no valley is searched after it: no evaluation to rank this one
            return
        T, J = _poses_and_jacobians(model, path[0])
        at = (error6_batch(target, T), J)
        raw = _neighbours(path[0], *at, path[2], limits[2])
        if raw[-1].any():
            yield from _starts_along(s, path, near, at, raw)
        else:
            later.append((path, at, raw))
    for path, at, raw in later:
        yield from _starts_along(s, path, near, at, raw)


def _neighbours(
    Q: np.ndarray, e: np.ndarray, J: np.ndarray, closed: bool, revolute: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Neighbours along a valley's points ``Q (m, n)``, with their errors ``e`` and URDF Jacobians ``J``: the
    pairs' ends ``a``, ``b`` (``(k, k + 1)``, and across the seam of a closed valley), ``b`` taken to ``a``'s
    turn, the joint each pair compares ``r`` in (the one that moves most between them), ``r`` at both ends,
    and whether it changes sign between them."""
    m = len(Q)
    pairs = np.stack([np.arange(m - 1), np.arange(1, m)], axis=1)
    if closed and m > 2:
        pairs = np.vstack([pairs, [[m - 1, 0]]])
    a, b = pairs[:, 0], pairs[:, 1]
    qb = Q[a] + turned(Q[b] - Q[a], revolute)
    jb = np.argmax(np.abs(qb - Q[a]), axis=1)
    ra, rb = along(e[a], J[a], jb)[0], along(e[b], J[b], jb)[0]
    return a, b, qb, jb, ra, rb, np.sign(ra) * np.sign(rb) <= 0


def _starts_along(
    s: _Valley,
    path: tuple[np.ndarray, np.ndarray, bool],
    near: np.ndarray,
    at: tuple[np.ndarray, np.ndarray],
    raw: tuple[np.ndarray, ...],
) -> Iterator[np.ndarray]:
    """The starts along one traced valley ``path`` (:func:`trace`), whose points' errors and Jacobians are
    ``at`` and whose neighbours there are ``raw`` (:func:`_neighbours`): the crossings nearest ``near`` first,
    then the double roots; lazily, as the caller asks.

    First the pair of neighbours nearest ``near`` whose unsettled ``r`` changes sign (module docstring, 4.),
    its two points settled alone: where they still bracket a root, that root's start. Only when the caller asks
    for more are all the points settled (a chord step of a valley's 20-40 points costs a batched hybrid FK)
    and the other crossings and the double roots searched."""
    model, target, limits, deadline, _ = s
    revolute = limits[2]
    points, motions, _ = path
    if time.perf_counter() > deadline:
        return
    joint = np.argmax(np.abs(motions), axis=1)
    a, b, _, _, _, _, changes = raw
    first = None
    if changes.any():
        first = min(np.flatnonzero(changes), key=lambda k: np.linalg.norm(points[a[k]] - near))
        ends = np.array([a[first], b[first]])
        at_ends = (at[0][ends], at[1][ends])
        Q2, e2, J2 = settle(model, target, points[ends], joint[ends], limits, POINT_STEPS, deadline, at_ends)
        pair = _neighbours(Q2, e2, J2, False, revolute)
        if (along(e2, J2, joint[ends])[1] < SETTLED).all() and pair[-1][0]:
            _, _, qb, jb, ra, rb, _ = pair
            yield project(_roots(s, Q2[:1], qb, ra, rb, jb)[0], *limits)
        else:
            first = None  # settled, the pair brackets nothing: the whole valley's search may find it again
    yield from _all_starts(s, path, joint, near, at, first)


def _all_starts(
    s: _Valley,
    path: tuple[np.ndarray, np.ndarray, bool],
    joint: np.ndarray,
    near: np.ndarray,
    at: tuple[np.ndarray, np.ndarray],
    searched: int | None,
) -> Iterator[np.ndarray]:
    """:func:`_starts_along` over the whole valley, every point settled: the crossings nearest ``near`` first
    but the pair ``searched`` already (its index among the neighbours), then the double roots."""
    model, target, limits, deadline, _ = s
    revolute = limits[2]
    points, _, closed = path
    if time.perf_counter() > deadline:
        return
    Q, e, J = settle(model, target, points.copy(), joint, limits, POINT_STEPS, deadline, at)
    settled = along(e, J, joint)[1] < SETTLED  # a point whose free joints could not settle brackets nothing
    a, b, qb, jb, ra, rb, changes = _neighbours(Q, e, J, closed, revolute)
    ok = settled[a] & settled[b]
    crossing = ok & changes
    # a target at the fold itself (q5 = 0 exactly: the pose moves along the lost direction with q5²) has a
    # double root, where r touches zero without crossing it: a local minimum of |r| between settled points
    nxt = np.full(len(Q), -1)
    nxt[a] = np.arange(len(a))  # the pair that leaves each point
    k = np.flatnonzero(nxt[b] >= 0)  # pairs followed by another: triples (x, y, z)
    k2 = nxt[b[k]]
    k = k[ok[k] & ok[k2] & ~crossing[k] & ~crossing[k2]]
    k2 = nxt[b[k]]
    x, y, z = a[k], b[k], b[k2]
    three = Q[y][:, None] + turned(np.stack([Q[x], Q[y], Q[z]], axis=1) - Q[y][:, None], revolute)  # y's turn
    jt = np.argmax(np.abs(three[:, 2] - three[:, 0]), axis=1)
    t = np.take_along_axis(three, jt[:, None, None], axis=2)[:, :, 0]
    monotonic = ((t[:, 0] < t[:, 1]) & (t[:, 1] < t[:, 2])) | ((t[:, 0] > t[:, 1]) & (t[:, 1] > t[:, 2]))
    r3 = np.stack([along(e[w], J[w], jt)[0] for w in (x, y, z)], axis=1)
    touching = (
        monotonic & (np.abs(r3[:, 1]) <= np.abs(r3[:, [0, 2]]).min(axis=1)) & (np.sign(r3[:, 0]) == np.sign(r3[:, 2]))
    )
    touches = []
    for i in np.flatnonzero(touching):
        order = slice(None) if t[i, 0] < t[i, 2] else slice(None, None, -1)
        touches.append((y[i], three[i, order], t[i, order], r3[i, order], int(jt[i])))
    # nearest the first row first: the member of the valleys the solver would reach from the seed; the
    # crossings before the double roots (module docstring, 5.)
    crossings = sorted(np.flatnonzero(crossing), key=lambda k: np.linalg.norm(Q[a[k]] - near))
    doubles = sorted(range(len(touches)), key=lambda i: np.linalg.norm(Q[touches[i][0]] - near))
    candidates = [*(("cross", k) for k in crossings if k != searched), *(("touch", i) for i in doubles)]
    candidates = candidates[: MAX_ROOTS - (searched is not None)]
    cross = np.array([k for kind, k in candidates if kind == "cross"], dtype=int)

    def refined() -> Iterator[np.ndarray]:
        # the first crossing alone (a row alone takes the cheaper single-pose path, and the first crossing
        # usually holds the solution), the others together when the caller asks for them
        for part in (cross[:1], cross[1:]):
            if len(part):
                yield from _roots(s, Q[a[part]], qb[part], ra[part], rb[part], jb[part])

    roots = refined()
    for kind, k in candidates:
        if kind == "cross":
            q = next(roots)
        elif time.perf_counter() < deadline:
            _, three, t, r3, jt = touches[k]
            q = _touch(model, target, three, t, r3, jt, limits)
        else:
            continue
        # a bracket across a joint's seam (±π, the trace wraps there) is searched on its first end's turn: its
        # root wrapped back within the limits
        yield project(q, *limits)


def _touch(
    model: HybridModel,
    target: np.ndarray,
    Q: np.ndarray,
    t: np.ndarray,
    r: np.ndarray,
    j: int,
    limits: Limits,
) -> np.ndarray:
    """Where ``r`` touches zero between three settled points ``Q (3, n)`` (a double root): the vertex of the
    parabola through them, settled, then again with the best three. LM through the hybrid model finishes."""
    for _ in range(TOUCH_STEPS):
        # the parabola r0 + d01 (x - t0) + a (x - t0)(x - t1) through the three points, and its vertex
        d01, d12 = (r[1] - r[0]) / (t[1] - t[0]), (r[2] - r[1]) / (t[2] - t[1])
        a = (d12 - d01) / (t[2] - t[0])
        x = 0.5 * (t[0] + t[1]) - d01 / (2 * a) if a != 0 else t[1]
        x = float(np.clip(x, t[0], t[2]))
        w = (x - t[0]) / (t[2] - t[0])
        q = Q[0] + w * (Q[2] - Q[0])
        q[j] = x
        q, rx, _ = _settle_along(model, target, q[None], np.array([j]), limits, SETTLE_STEPS)
        # the vertex with its two nearest neighbours, in order
        keep = np.argsort(np.abs(t - x))[:2]
        order = np.argsort(np.r_[t[keep], x])
        Q = np.vstack([Q[keep], q])[order]
        t, r = np.r_[t[keep], x][order], np.r_[r[keep], rx][order]
        if np.min(np.diff(t)) < 1e-12:
            break
    return Q[np.argmin(np.abs(r))]


def _roots(s: _Valley, qa: np.ndarray, qb: np.ndarray, ra: np.ndarray, rb: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Regula falsi (Illinois) on ``r(t)`` between settled points of opposite sign, every bracket ``(K,)`` at
    once, each until the error along and across its valley is within the search's ``tol`` (m or rad)."""
    model, target, limits, deadline, tol = s
    qa, qb, ra, rb = qa.copy(), qb.copy(), ra.copy(), rb.copy()
    q = np.where((np.abs(ra) < np.abs(rb))[:, None], qa, qb)
    side = np.zeros(len(q))
    active = ra != rb
    for _ in range(BRACKET_STEPS):
        if not active.any() or time.perf_counter() > deadline:
            break
        k = np.flatnonzero(active)
        w = (ra[k] / (ra[k] - rb[k]))[:, None]
        q[k], r, across = _settle_along(model, target, qa[k] + w * (qb[k] - qa[k]), j[k], limits, SETTLE_STEPS)
        q[k] = qa[k] + turned(q[k] - qa[k], limits[2])  # on the bracket's turn, if settling wrapped a joint
        done = (np.abs(r) <= tol) & (across <= tol)
        a = np.sign(r) == np.sign(ra[k])  # the new point replaces end a, else end b
        ka, kb = k[a], k[~a]
        qa[ka], ra[ka] = q[ka], r[a]
        rb[ka] = np.where(side[ka] == -1, rb[ka] / 2, rb[ka])  # Illinois: the end kept twice counts half
        side[ka] = -1
        qb[kb], rb[kb] = q[kb], r[~a]
        ra[kb] = np.where(side[kb] == 1, ra[kb] / 2, ra[kb])
        side[kb] = 1
        active[k[done]] = False
        active &= ra != rb
    return q
