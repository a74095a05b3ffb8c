"""The hybrid solutions near a singularity of the URDF model, by a root search along its weak direction.

At a singularity of the URDF model (a wrist with q5 = 0, the wrist centre on axis 1, the elbow stretched),
the URDF Jacobian loses a direction of the pose (``u``) and gains a joint motion that does nothing (``v``).
The hybrid model's corrections change along ``v`` by micrometres per radian, so its solutions lie somewhere
along a valley a whole turn long, where every local method (the closed forms' fixed point, whose chord
Jacobian is singular there, and LM, whose basin is a few milliradians wide) crawls or settles in a local
minimum of the valley.

The search here is global along the valley and local across it:
1. The joint ``j`` that moves most along ``v`` becomes the valley's parameter ``t``; the other five joints
   span the pose directions the URDF model keeps, with a well-conditioned 6×5 Jacobian.
2. On a grid of ``t`` over a turn, all points at once (batched hybrid FK), Gauss-Newton's chord steps in
   those five joints remove the error the model can remove; what is left is a scalar ``r(t)``: the error
   along the lost direction, signed by the 6×5 Jacobian's cofactor vector, which turns smoothly with ``t``.
3. Each sign change of ``r`` brackets a hybrid solution; a few regula falsi steps find ``r(t) = 0``, where
   the whole 6-D error vanishes up to the five joints' convergence. The caller's LM on the hybrid model
   finishes from there, in its basin.
"""

from __future__ import annotations

import time

import numpy as np

from hybrid_kinematics_ros.ik.lm import Limits, error6_batch, project
from hybrid_kinematics_ros.model.hybrid import HybridModel

# The grid over the valley's turn (batched: 24 points cost about three single hybrid FKs), the chord steps
# that settle the five joints at each point (the chord Jacobian is exact to the corrections' derivative, a
# thousandth: each step gains ~1000x), and the regula falsi steps within a bracket.
GRID_POINTS = 24
GRID_STEPS = 3
BRACKET_STEPS = 6
MAX_ROOTS = 2  # brackets searched, nearest q_near first (a valley can hold several solutions)
TOUCH_STEPS = 3  # parabola steps at a double root
SETTLE_STEPS = 2
RINGS = 3  # rounds of restarts from settled neighbours, each reaching at least one grid step further
SETTLED = 1e-5  # m (or rad): a grid point whose five joints leave more across the valley brackets nothing
# Where the URDF model counts as near-singular for this search: the Jacobian's smallest singular value (m or
# rad per rad; a regular UR10 pose has 0.05-0.5; a hybrid target at q5 = 0 gives the URDF model's answer
# 1e-4 to 2e-2, as far as its millimetres of correction take it from the singularity).
NEAR_SINGULAR = 3e-2


def weak_direction(model: HybridModel, q: np.ndarray) -> tuple[np.ndarray, float]:
    """The URDF Jacobian's weakest joint motion at ``q`` (unit) and its singular value."""
    _, sv, vt = np.linalg.svd(model.fk_and_jacobian_single(q, analytic=True)[1])
    return vt[-1], float(sv[-1])


def _normal(J5: np.ndarray) -> np.ndarray:
    """``(K, 6)``: a unit vector normal to the five columns of each ``J5 (K, 6, 5)``, from their signed 5×5
    minors (the generalised cross product), so that it turns continuously with the columns (an SVD's sign
    is arbitrary)."""
    rows = np.arange(6)
    u = np.stack([(-1) ** i * np.linalg.det(J5[:, rows != i, :]) for i in range(6)], axis=1)
    return u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)


def _poses_and_jacobians(model: HybridModel, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hybrid poses and URDF Jacobians of ``Q (K, n)``: batched, or on the single-pose path for one row
    (half the cost there)."""
    if len(Q) == 1:
        return model.fk_single(Q[0])[None], model.fk_and_jacobian_single(Q[0], analytic=True)[1][None]
    return model.fk(Q), model.fk_and_jacobian(Q, analytic=True)[1]


def settle(
    model: HybridModel, target: np.ndarray, Q: np.ndarray, free: np.ndarray, limits: Limits, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chord steps in the ``free`` joints of every row of ``Q (K, n)`` (in place), the valley joint held.
    Returns ``Q``, the signed error along the lost direction ``(K,)`` and the error left across it ``(K,)``
    (m and rad as one vector: what the five joints did not remove)."""
    free_limits = tuple(side[free] for side in limits)
    for step in range(steps + 1):
        T, J = _poses_and_jacobians(model, Q)
        e, J5 = error6_batch(target, T), J[:, :, free]
        if step == steps:  # the last evaluation measures, no step follows it
            break
        jt = J5.mT
        delta = np.linalg.solve(jt @ J5 + 1e-12 * np.eye(len(free)), jt @ e[:, :, None])[:, :, 0]
        Q[:, free] = project(Q[:, free] + delta, *free_limits)
    u = _normal(J5)
    r = np.einsum("ki,ki->k", u, e)
    return Q, r, np.linalg.norm(e - r[:, None] * u, axis=1)


def valley_starts(
    model: HybridModel, target: np.ndarray, q_near: np.ndarray, limits: Limits, deadline: float, tol: float
) -> list[np.ndarray] | None:
    """Starts next to the MAX_ROOTS hybrid solutions along the valley through ``q_near`` nearest it (module
    docstring), nearest first, each within ``tol`` (m or rad) of the target where the search converged;
    None when ``q_near`` is not near a singularity of the URDF model (no search)."""
    v, sigma = weak_direction(model, q_near)
    if sigma > NEAR_SINGULAR or time.perf_counter() > deadline:
        return None
    lower, upper, _ = limits
    j = int(np.argmax(np.abs(v)))
    free = np.flatnonzero(np.arange(len(q_near)) != j)
    t = np.linspace(max(lower[j], q_near[j] - np.pi), min(upper[j], q_near[j] + np.pi), GRID_POINTS)
    # each point starts along the weak motion (the other joints follow ``v``), where the five joints have
    # least to remove: from ``q_near`` with joint j alone turned, a rotation error near π has no clean log
    Q = q_near + np.outer((t - q_near[j]) / v[j], v)
    Q = project(Q, *limits)
    Q[:, j] = t
    Q, r, across = settle(model, target, Q, free, limits, GRID_STEPS)
    for _ in range(RINGS):  # the valley curves: points far from q_near restart from a settled neighbour
        if time.perf_counter() > deadline:
            break
        restarted = _restart_from_neighbours(Q, t, across < SETTLED, v, j, limits)
        if not len(restarted):
            break
        Q[restarted], r[restarted], across[restarted] = settle(model, target, Q[restarted], free, limits, GRID_STEPS)
    # a point whose five joints could not settle (a joint at its limit, a start too far) brackets nothing
    settled = across < SETTLED
    crossing = (np.sign(r[:-1]) * np.sign(r[1:]) <= 0) & settled[:-1] & settled[1:]
    # a target at the fold itself (q5 = 0 exactly: the pose moves along the lost direction with q5²) has a
    # double root, where r touches zero without crossing it: a local minimum of |r| between settled points
    inner = np.arange(1, len(t) - 1)
    touching = inner[
        settled[inner - 1]
        & settled[inner]
        & settled[inner + 1]
        & (np.abs(r[inner]) <= np.abs(r[inner - 1]))
        & (np.abs(r[inner]) <= np.abs(r[inner + 1]))
        & (np.sign(r[inner - 1]) == np.sign(r[inner + 1]))
        & ~crossing[inner - 1]
        & ~crossing[inner]
    ]
    candidates = [("cross", k) for k in np.flatnonzero(crossing)] + [("touch", k) for k in touching]
    # nearest q_near first: the member of the valley the solver would reach from the seed
    candidates.sort(key=lambda c: float(np.linalg.norm(Q[c[1]] - q_near)))
    starts = []
    for kind, k in candidates[:MAX_ROOTS]:
        if time.perf_counter() > deadline:
            break
        if kind == "cross":
            starts.append(_root(model, target, Q[k], Q[k + 1], r[k], r[k + 1], j, free, limits, deadline, tol))
        else:
            starts.append(_touch(model, target, Q[k - 1 : k + 2], t[k - 1 : k + 2], r[k - 1 : k + 2], j, free, limits))
    return starts


def _touch(
    model: HybridModel,
    target: np.ndarray,
    Q: np.ndarray,
    t: np.ndarray,
    r: np.ndarray,
    j: int,
    free: np.ndarray,
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
        q, rx, _ = settle(model, target, q[None], free, limits, SETTLE_STEPS)
        # the vertex with its two nearest neighbours, in order
        keep = np.argsort(np.abs(t - x))[:2]
        order = np.argsort(np.r_[t[keep], x])
        Q = np.vstack([Q[keep], q])[order]
        t, r = np.r_[t[keep], x][order], np.r_[r[keep], rx][order]
        if np.min(np.diff(t)) < 1e-12:
            break
    return Q[np.argmin(np.abs(r))]


def _restart_from_neighbours(
    Q: np.ndarray, t: np.ndarray, settled: np.ndarray, v: np.ndarray, j: int, limits: Limits
) -> np.ndarray:
    """Each unsettled grid point next to a settled one starts again from it, along the valley's tangent there
    (from the two settled points on that side, else the weak direction ``v``); returns their indices."""
    revolute = limits[2]
    restarted = []
    for k in np.flatnonzero(~settled):
        for step in (-1, 1):
            near, beyond = k + step, k + 2 * step
            if not (0 <= near < len(t) and settled[near]):
                continue
            if 0 <= beyond < len(t) and settled[beyond]:
                d = Q[near] - Q[beyond]
                d[revolute] = (d[revolute] + np.pi) % (2 * np.pi) - np.pi  # across a wrap by 2π
                tangent = d / (t[near] - t[beyond])
            else:
                tangent = v / v[j]
            Q[k] = project(Q[near] + (t[k] - t[near]) * tangent, *limits)
            Q[k, j] = t[k]
            restarted.append(k)
            break
    return np.array(restarted, dtype=int)


def _root(
    model: HybridModel,
    target: np.ndarray,
    qa: np.ndarray,
    qb: np.ndarray,
    ra: float,
    rb: float,
    j: int,
    free: np.ndarray,
    limits: Limits,
    deadline: float,
    tol: float,
) -> np.ndarray:
    """Regula falsi (Illinois) on ``r(t)`` between two settled points of opposite sign, until the error
    along and across the valley is within ``tol`` (m or rad)."""
    q = qa if abs(ra) < abs(rb) else qb
    side = 0
    for _ in range(BRACKET_STEPS):
        if ra == rb or time.perf_counter() > deadline:
            break
        w = ra / (ra - rb)
        q, r, across = settle(model, target, (qa + w * (qb - qa))[None].copy(), free, limits, SETTLE_STEPS)
        q, r = q[0], float(r[0])
        if abs(r) <= tol and across[0] <= tol:
            break
        if np.sign(r) == np.sign(ra):
            qa, ra = q, r
            rb = rb / 2 if side == -1 else rb  # Illinois: the end kept twice in a row counts half
            side = -1
        else:
            qb, rb = q, r
            ra = ra / 2 if side == 1 else ra
            side = 1
    return q
