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

Every closed-form branch has its own valley, and the hybrid solution need not lie on the seed's: at a shoulder
singularity (the wrist centre on axis 1) it can lie on the valley of the shoulder flipped, and a valley that
crosses the wrist's singularity cannot be followed across it. So the valleys of all branches are searched at
once, in one batch (RX160, wrist centre on axis 1, 60 targets at 50 ms: 82 % with the seed's valley alone,
100 % with all branches').
"""

from __future__ import annotations

import time

import numpy as np

from hybrid_kinematics_ros.ik.lm import Limits, error6_batch, project
from hybrid_kinematics_ros.model.hybrid import HybridModel

# The grid over each valley's turn, the chord steps that settle the five joints at each point (the chord
# Jacobian is exact to the corrections' derivative, a thousandth: each step gains ~1000x), and the regula falsi
# steps within a bracket. All valleys' grids go through the hybrid FK in one batch (8 branches × 16 points:
# one evaluation ~2 ms). Measured on RX160 targets with the wrist centre on axis 1 (60 at 50 ms, a model trained
# for a minute): 24 points and 3 rings of restarts 96.7-100 % at a median 38-42 ms; 16 points and 1 ring 100 % at
# 25 ms; no ring 96.7-98.3 % at 22 ms.
GRID_POINTS = 16
GRID_STEPS = 3
BRACKET_STEPS = 6
MAX_ROOTS = 4  # brackets refined (all at once), over all valleys, nearest the first q_near first
TOUCH_STEPS = 3  # parabola steps at a double root
SETTLE_STEPS = 1  # a bracket's points lie between settled ones: one chord step (2 gave the same answers, slower)
RINGS = 1  # rounds of restarts from settled neighbours, each reaching at least one grid step further
SINGLE_ROWS = 2  # settle's rows evaluated one by one up to this many
SAME_RAD = 1e-6  # rows of q_near this close start the same valley
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
    """Hybrid poses and URDF Jacobians of ``Q (K, n)``: batched, or row by row on the single-pose path for a
    few rows (a batch costs ~0.4 ms however small, a single pose 0.14 ms)."""
    if len(Q) <= SINGLE_ROWS:
        single = [(model.fk_single(q), model.fk_and_jacobian_single(q, analytic=True)[1]) for q in Q]
        return np.stack([T for T, _ in single]), np.stack([J for _, J in single])
    return model.fk(Q), model.fk_and_jacobian(Q, analytic=True)[1]


def settle(
    model: HybridModel, target: np.ndarray, Q: np.ndarray, j: np.ndarray, limits: Limits, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chord steps in the free joints of every row of ``Q (K, n)`` (in place), each row's valley joint
    ``j (K,)`` held. Returns ``Q``, the signed error along the lost direction ``(K,)`` and the error left
    across it ``(K,)`` (m and rad as one vector: what the free joints did not remove)."""
    n = Q.shape[1]
    free = np.nonzero(np.arange(n) != j[:, None])[1].reshape(len(Q), n - 1)
    rows = np.arange(len(Q))[:, None]
    free_limits = tuple(side[free] for side in limits)
    for step in range(steps + 1):
        T, J = _poses_and_jacobians(model, Q)
        e, J5 = error6_batch(target, T), np.take_along_axis(J, free[:, None, :], axis=2)
        if step == steps:  # the last evaluation measures, no step follows it
            break
        jt = J5.mT
        delta = np.linalg.solve(jt @ J5 + 1e-12 * np.eye(n - 1), jt @ e[:, :, None])[:, :, 0]
        Q[rows, free] = project(Q[rows, free] + delta, *free_limits)
    u = _normal(J5)
    r = np.einsum("ki,ki->k", u, e)
    return Q, r, np.linalg.norm(e - r[:, None] * u, axis=1)


def valley_starts(
    model: HybridModel,
    target: np.ndarray,
    q_near: np.ndarray,
    limits: Limits,
    deadline: float,
    tol: float,
) -> list[np.ndarray] | None:
    """Starts next to the hybrid solutions along the valleys through ``q_near`` (``(n,)``, or ``(B, n)``: the
    closed forms' branches, whose valleys are searched in one batch), at most MAX_ROOTS, nearest the first
    row first (module docstring), each within ``tol`` (m or rad) of the target where the search converged;
    None when no row of ``q_near`` is near a singularity of the URDF model (no search)."""
    lower, upper, _ = limits
    valleys = []  # per valley: its rows in the batch, its grid, its joint, its weak direction
    distinct = []
    for q in np.atleast_2d(q_near):
        if any(np.abs(q - d).max() < SAME_RAD for d in distinct):
            continue
        distinct.append(q)
        v, sigma = weak_direction(model, q)
        if sigma > NEAR_SINGULAR:
            continue
        j = int(np.argmax(np.abs(v)))
        t = np.linspace(max(lower[j], q[j] - np.pi), min(upper[j], q[j] + np.pi), GRID_POINTS)
        # each point starts along the weak motion (the other joints follow ``v``), where the free joints have
        # least to remove: from ``q`` with joint j alone turned, a rotation error near π has no clean log
        Q = project(q + np.outer((t - q[j]) / v[j], v), *limits)
        Q[:, j] = t
        rows = slice(len(valleys) * GRID_POINTS, (len(valleys) + 1) * GRID_POINTS)
        valleys.append((rows, t, j, v, Q))
    if not valleys or time.perf_counter() > deadline:
        return None if not valleys else []
    Q = np.vstack([valley[4] for valley in valleys])
    joint = np.repeat([valley[2] for valley in valleys], GRID_POINTS)
    Q, r, across = settle(model, target, Q, joint, limits, GRID_STEPS)
    for _ in range(RINGS):  # the valley curves: points far from q_near restart from a settled neighbour
        if time.perf_counter() > deadline:
            break
        restarted = np.concatenate(
            [
                rows.start + _restart_from_neighbours(Q[rows], t, across[rows] < SETTLED, v, j, limits)
                for rows, t, j, v, _ in valleys
            ]
        )
        if not len(restarted):
            break
        Q[restarted], r[restarted], across[restarted] = settle(
            model, target, Q[restarted], joint[restarted], limits, GRID_STEPS
        )
    # a point whose free joints could not settle (a joint at its limit, a start too far) brackets nothing
    settled = across < SETTLED
    crosses, touches = [], []
    for rows, t, _, _, _ in valleys:
        k0, rv, ok = rows.start, r[rows], settled[rows]
        crossing = (np.sign(rv[:-1]) * np.sign(rv[1:]) <= 0) & ok[:-1] & ok[1:]
        # a target at the fold itself (q5 = 0 exactly: the pose moves along the lost direction with q5²) has a
        # double root, where r touches zero without crossing it: a local minimum of |r| between settled points
        inner = np.arange(1, len(t) - 1)
        touching = inner[
            ok[inner - 1]
            & ok[inner]
            & ok[inner + 1]
            & (np.abs(rv[inner]) <= np.abs(rv[inner - 1]))
            & (np.abs(rv[inner]) <= np.abs(rv[inner + 1]))
            & (np.sign(rv[inner - 1]) == np.sign(rv[inner + 1]))
            & ~crossing[inner - 1]
            & ~crossing[inner]
        ]
        crosses += [k0 + k for k in np.flatnonzero(crossing)]
        touches += [(k0 + k, t[k - 1 : k + 2]) for k in touching]
    # nearest the first row first: the member of the valleys the solver would reach from the seed
    near = np.atleast_2d(q_near)[0]
    candidates = [(float(np.linalg.norm(Q[k] - near)), "cross", k, None) for k in crosses]
    candidates += [(float(np.linalg.norm(Q[k] - near)), "touch", k, t) for k, t in touches]
    candidates.sort(key=lambda c: c[0])
    candidates = candidates[:MAX_ROOTS]
    cross = np.array([c[2] for c in candidates if c[1] == "cross"], dtype=int)
    roots = iter(
        _roots(model, target, Q[cross], Q[cross + 1], r[cross], r[cross + 1], joint[cross], limits, deadline, tol)
    )
    starts = []
    for _, kind, k, t in candidates:
        if kind == "cross":
            starts.append(next(roots))
        elif time.perf_counter() < deadline:
            starts.append(_touch(model, target, Q[k - 1 : k + 2], t, r[k - 1 : k + 2], joint[k], limits))
    return starts


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
        q, rx, _ = settle(model, target, q[None], np.array([j]), limits, SETTLE_STEPS)
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


def _roots(
    model: HybridModel,
    target: np.ndarray,
    qa: np.ndarray,
    qb: np.ndarray,
    ra: np.ndarray,
    rb: np.ndarray,
    j: np.ndarray,
    limits: Limits,
    deadline: float,
    tol: float,
) -> np.ndarray:
    """Regula falsi (Illinois) on ``r(t)`` between settled points of opposite sign, every bracket ``(K,)`` at
    once, each until the error along and across its valley is within ``tol`` (m or rad)."""
    qa, qb, ra, rb = qa.copy(), qb.copy(), ra.copy(), rb.copy()
    q = np.where((np.abs(ra) < np.abs(rb))[:, None], qa, qb)
    side = np.zeros(len(q))
    active = ra != rb
    for _ in range(BRACKET_STEPS):
        if not active.any() or time.perf_counter() > deadline:
            break
        k = np.flatnonzero(active)
        w = (ra[k] / (ra[k] - rb[k]))[:, None]
        q[k], r, across = settle(model, target, qa[k] + w * (qb[k] - qa[k]), j[k], limits, SETTLE_STEPS)
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
