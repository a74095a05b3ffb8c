"""The root search along a singular valley of the URDF model (ik/valley.py), through a trained hybrid model:
from the URDF model's answer a radian along the valley from the solution, where LM through the hybrid model
settles in a local minimum, it finds a hybrid configuration that reaches the target, checked on the hybrid
FK."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from bench.bench_ik_singular import cases
from hybrid_kinematics_ros.ik import seeds as seeding
from hybrid_kinematics_ros.ik import valley as valley_module
from hybrid_kinematics_ros.ik.lm import joint_limits
from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver, SolveRequest
from hybrid_kinematics_ros.ik.valley import (
    NEAR_SINGULAR,
    TRACE_STEP,
    enter,
    settle,
    trace,
    valley_starts,
    weak_direction,
)
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.se3 import error6
from hybrid_kinematics_ros.model.hybrid import HybridModel

TOL_M = 1e-8  # the solver's inner tolerance at its default 1e-4 mm
GENEROUS = IKOptions(timeout_s=5.0)  # tests check answers; bench_ik_singular measures time


def wrist_singular(model, n: int, seed: int) -> np.ndarray:
    """UR10 configurations with the wrist straight (q5 = 0): axes 4 and 6 line up."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.8 * model.chain.lower, 0.8 * model.chain.upper, (n, 6))
    q[:, 4] = 0.0
    return q


def hybrid_errors(model, q: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    T = model.fk_single(q)
    position = 1e3 * np.linalg.norm(T[:3, 3] - target[:3, 3])
    cos = np.clip(0.5 * (np.trace(T[:3, :3].T @ target[:3, :3]) - 1.0), -1.0, 1.0)
    return float(position), float(np.degrees(np.arccos(cos)))


def answered_methods(solver: IKSolver, targets: np.ndarray) -> list[str | None]:
    """Every target solved from a mid-limits seed and reached within 1e-4 mm and 1e-4° on the hybrid FK;
    returns the method of each answer."""
    methods = []
    for target in targets:
        result = solver.solve(target)
        assert result.success, result.message
        position, rotation = hybrid_errors(solver.model, result.q, target)
        assert position < 1e-4 and rotation < 1e-4
        methods.append(result.stats.get("method"))
    return methods


def test_a_start_a_radian_along_the_valley_finds_a_hybrid_solution(trained):
    _, model, _, _ = trained
    limits = joint_limits(model.chain)
    solver = IKSolver(model, GENEROUS)
    found = lm_short = searched = 0
    for q_star in wrist_singular(model, 12, seed=3):
        target = model.fk_single(q_star)
        v, sigma = weak_direction(model, q_star)
        assert sigma < 1e-6  # the URDF model is singular there
        # the URDF model's answer from a seed a radian along its weak motion (joint 4 or 6 a radian further)
        start = solver.classical(target, q_star + 1.0 / np.abs(v).max() * v, time.perf_counter() + 60.0)[0]
        starts = valley_starts(model, target, start, limits, time.perf_counter() + 60.0, TOL_M)
        if starts is None:  # that answer is another branch, away from the singularity: no valley to search
            assert weak_direction(model, start)[1] > NEAR_SINGULAR
            continue
        searched += 1
        starts = list(starts)
        assert len(starts) >= 1
        q, _, _ = solver.refiner.unbounded(target, starts[0], time.perf_counter() + 60.0)  # as the solver does
        position, rotation = hybrid_errors(model, q, target)
        found += position < 1e-4 and rotation < 1e-4
        q_lm, _, _ = solver.refiner.unbounded(target, start, time.perf_counter() + 60.0)
        position, rotation = hybrid_errors(model, q_lm, target)
        lm_short += not (position < 1e-4 and rotation < 1e-4)
    assert searched >= 8, searched
    # measured 8-9 of 11 through the valley; LM through the hybrid model alone from the same answers: 0 of 11
    assert found >= 0.6 * searched, (found, searched)
    assert lm_short >= searched // 2, (lm_short, searched)


def test_a_valleys_first_start_settles_two_points_and_the_next_the_whole_valley(trained, monkeypatch):
    """The first start of a valley comes from the pair of neighbours nearest the seed whose unsettled r changes
    sign, its two points settled alone; the caller asking for the next start settles the valley's 20-40 points
    (~0.5 ms a chord step). The first starts solve as the whole valley's first did (8-9 of 11)."""
    _, model, _, _ = trained
    limits = joint_limits(model.chain)
    solver = IKSolver(model, GENEROUS)
    rows: list[int] = []
    settle_all = valley_module.settle

    def counted(model, target, Q, *args, **kwargs):
        rows.append(len(Q))
        return settle_all(model, target, Q, *args, **kwargs)

    monkeypatch.setattr(valley_module, "settle", counted)
    paired = found = whole = 0
    for q_star in wrist_singular(model, 12, seed=3):
        target = model.fk_single(q_star)
        v, _ = weak_direction(model, q_star)
        start = solver.classical(target, q_star + 1.0 / np.abs(v).max() * v, time.perf_counter() + 60.0)[0]
        starts = valley_starts(model, target, start, limits, time.perf_counter() + 60.0, TOL_M)
        if starts is None:
            continue
        rows.clear()
        first = next(starts, None)
        if first is None or rows != [2]:  # no pair's sign changed before settling: the whole valley at once
            continue
        paired += 1
        q, _, _ = solver.refiner.unbounded(target, first, time.perf_counter() + 60.0)
        position, rotation = hybrid_errors(model, q, target)
        found += position < 1e-4 and rotation < 1e-4
        next(starts, None)
        whole += max(rows) > 2
    assert paired >= 6, paired
    assert found >= 0.6 * paired, (found, paired)
    assert whole >= paired // 2, (whole, paired)  # asked for more, the valley's points are settled


def test_no_search_away_from_a_singularity(trained):
    _, model, _, _ = trained
    q = np.array([0.3, -1.2, 1.4, -0.6, 1.1, 0.2])
    assert weak_direction(model, q)[1] > NEAR_SINGULAR
    target = model.fk_single(q)
    assert valley_starts(model, target, q, joint_limits(model.chain), time.perf_counter() + 60.0, TOL_M) is None


def test_the_solver_answers_wrist_singular_hybrid_targets_within_tolerance(trained):
    """Mid-limits seed, so the classical answer lies elsewhere on the valley: every answer reaches the target
    through the hybrid FK, and some of them come from the valley search."""
    _, model, _, _ = trained
    methods = answered_methods(IKSolver(model, GENEROUS), model.fk(wrist_singular(model, 12, seed=4)))
    assert "singular valley" in methods, methods


@pytest.mark.parametrize("robot", ["ur10", "rx160"])
def test_the_traced_valley_keeps_to_the_urdf_continuum(robot):
    """At q5 = 0 the solutions of a UR10 (joints 2, 3, 4 and 6 parallel) and of an RX160 (joints 4 and 6
    aligned) form a continuum. The trace keeps to it: every point reaches the start's URDF pose in the five
    directions the Jacobian keeps, no step is much longer than TRACE_STEP up to whole turns (a closed valley's
    seam: up to 1.75 of it), and every point lies within the limits. On the UR10, where the wrist circle crosses the
    arm's reach, the continuum passes the stretched elbow and turns back in every joint: q3 changes sign
    along it, which a grid over any one joint cannot follow."""
    chain = load_robot_config(robot).chain
    model = HybridModel.analytic_only(chain)
    limits = joint_limits(chain)
    rng = np.random.default_rng(5)
    q = rng.uniform(0.8 * chain.lower, 0.8 * chain.upper, (40, 6))
    q[:, 4] = 0.0
    across_elbow = closed_count = 0
    for start in q:
        v, sigma = weak_direction(model, start)
        assert sigma < 1e-9
        points, motions, closed = trace(model, start, v, limits)
        assert len(points) >= 3 and np.allclose(np.linalg.norm(motions, axis=1), 1.0)
        pose = model.fk_single(start, analytic=True)
        for p in points:
            u = np.linalg.svd(model.fk_and_jacobian_single(p, analytic=True)[1])[0]
            assert np.abs(u[:, :5].T @ error6(pose, model.fk_single(p, analytic=True))).max() < 1e-2
        steps = np.diff(np.vstack([points, points[:1]]) if closed else points, axis=0)
        turned = (steps + np.pi) % (2 * np.pi) - np.pi
        # up to whole turns where a joint of a whole turn (the UR10's ±π) crosses its seam, and at a closed
        # valley's seam, where the last point comes back next to the start
        seam = limits[2] & (limits[1] - limits[0] <= 2 * np.pi + 1e-9)
        steps = np.where(seam, turned, steps)
        if closed:
            steps[-1] = np.where(limits[2], turned[-1], steps[-1])
        assert np.linalg.norm(steps, axis=1).max() < 2 * TRACE_STEP  # a seam: up to 1 + CLOSED steps
        assert np.all((points >= limits[0] - 1e-12) & (points <= limits[1] + 1e-12))
        closed_count += closed
        across_elbow += points[:, 2].min() < 0 < points[:, 2].max()
    if robot == "ur10":  # measured: 15 of 40 cross the stretched elbow, 3 close (the rest end at joint limits)
        assert across_elbow >= 8 and closed_count >= 1, (across_elbow, closed_count)


def test_a_valley_across_the_stretched_elbow_holds_the_hybrid_solution(trained):
    """Hybrid targets with the wrist straight and the elbow nearly stretched (q3 0.05-0.3 rad), searched from
    the closed forms' branch on the other side of the elbow (q3 < 0): the solution lies past the point where
    the continuum turns back, and the trace follows it there."""
    _, model, _, _ = trained
    limits = joint_limits(model.chain)
    solver = IKSolver(model, GENEROUS)
    rng = np.random.default_rng(6)
    q = rng.uniform(0.8 * model.chain.lower, 0.8 * model.chain.upper, (40, 6))
    q[:, 4], q[:, 2] = 0.0, rng.uniform(0.05, 0.3, 40)
    tried = found = 0
    for q_star in q:
        target = model.fk_single(q_star)
        other = [b for b in solver.branches(target, q_star) if b[2] < 0 and abs(b[0] - q_star[0]) < 0.1]
        if not other:
            continue
        tried += 1
        for start in valley_starts(model, target, other[0], limits, time.perf_counter() + 60.0, TOL_M) or []:
            q_found, _, _ = solver.refiner.unbounded(target, start, time.perf_counter() + 60.0)
            position, rotation = hybrid_errors(model, q_found, target)
            if position < 1e-4 and rotation < 1e-4:
                found += 1
                break
    assert tried >= 15, tried
    # measured 26 of 29; the grid over one joint that the trace replaced: 18 of 29
    assert found >= 0.8 * tried, (found, tried)


def test_wrist_straight_targets_beyond_the_urdf_models_reach_are_searched_along_the_valley(trained):
    """A hybrid target made with the wrist straight lies beyond the URDF model's fold now and then (1 in 13 here): no
    exact branch, and the least-squares answers sit on the continuum, where the fixed point wanders. The valley
    search starts from those answers (it was left for the refinements, behind the other branches' LM)."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    targets = model.fk(wrist_singular(model, 150, seed=5))
    beyond = [t for t in targets if not len(solver.branches(t, model.chain.mid_limits()))]
    assert len(beyond) >= 6, len(beyond)
    methods = answered_methods(solver, np.array(beyond))
    # each by the valley search or a fixed point, none left to the other branches' LM (before: 1 of 7, 2.3 s)
    assert set(methods) <= {"singular valley", "closed-form fixed point"}, methods
    assert methods.count("singular valley") >= len(beyond) // 2, methods


def test_settle_takes_no_step_after_its_deadline(trained):
    """A settle of a whole valley's points takes 1-3 ms a step; past its deadline it steps no more, and what it
    returns is still consistent: the errors and Jacobians at the points it returns (those it was given, at a
    deadline already past), the same as a settle of no steps. With time, it moves them."""
    _, model, _, _ = trained
    limits = joint_limits(model.chain)
    q = wrist_singular(model, 12, 4)
    target = model.fk_single(q[0])
    held = np.zeros(len(q), dtype=int) + 3  # q4 held, the five others step
    late = settle(model, target, q.copy(), held, limits, 2, deadline=time.perf_counter())
    none = settle(model, target, q.copy(), held, limits, 0)
    for a, b in zip(late, none, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(late[0], q)
    moved = settle(model, target, q.copy(), held, limits, 2)[0]
    assert np.abs(moved - q).max() > 1e-6


def test_the_seeds_branch_runs_its_fixed_point_once(trained, monkeypatch):
    """Where the closed forms' fixed point from the branch nearest the seed misses (the wrist straight: its
    chord Jacobian is singular), the search that follows starts from that branch's verdict and does not run
    the same fixed point again (2-3 ms of a 50 ms budget on a slow machine). Every answer still reaches the
    target on the hybrid FK."""
    _, model, _, _ = trained
    starts: list[np.ndarray] = []
    original = IKSolver.fixed_points

    def recorded(self, target, some, *args, **kwargs):
        starts.extend(some)
        return original(self, target, some, *args, **kwargs)

    monkeypatch.setattr(IKSolver, "fixed_points", recorded)
    solver = IKSolver(model, GENEROUS)
    missed = 0
    for target in model.fk(wrist_singular(model, 12, seed=4)):
        starts.clear()
        result = solver.solve(target)
        assert result.success and max(hybrid_errors(model, result.q, target)) < 1e-4
        if result.stats.get("method") != "closed-form fixed point" or len(starts) > 1:
            missed += 1
            assert not any(np.array_equal(starts[0], q) for q in starts[1:]), result.stats
    assert missed >= 3, missed


def test_the_seeds_fixed_point_stalled_next_to_a_solution_is_finished_by_lm(trained, monkeypatch):
    """With the wrist centre on axis 1 the URDF Jacobian loses rank, and the seed's fixed point can stall
    (a least-squares round that barely cuts the error) micrometres from a solution of its own branch. There LM
    on the hybrid model finishes it in a few steps, before any other branch or valley is tried (a UR10 target
    stalled 4e-4 mm away and was solved at 50-110 ms, after the other branches and the valleys; LM from the
    stall: 1.4 ms). Each such answer reaches the target on the hybrid FK without a valley traced."""
    from bench.bench_ik_singular import cases
    from hybrid_kinematics_ros.ik import valley
    from hybrid_kinematics_ros.ik.solver import NEAR_MISS_MM

    _, model, _, _ = trained
    traced = []
    monkeypatch.setattr(valley, "trace", lambda *a, **k: traced.append(1) or trace(*a, **k))
    solver = IKSolver(model, GENEROUS)
    seed = model.chain.mid_limits()
    stalled = 0
    made = cases(model.chain, 48, np.random.default_rng(7))
    q_all = np.vstack([made[k] for k in made if k.startswith(("wrist centre", "elbow stretched"))])
    for target in model.fk(q_all):
        closed = solver.branches(target, seed)
        if len(closed) < 2:
            continue
        q, errors, beyond = solver.fixed_point(target, closed[0], time.perf_counter() + 5.0)
        if not beyond or max(errors) < 1e-4 or errors[0] >= NEAR_MISS_MM:
            continue
        q_lm, *_ = solver.refiner.unbounded(target, q, time.perf_counter() + 5.0)
        if max(hybrid_errors(model, q_lm, target)) >= 1e-4:
            continue  # LM from the stall does not reach it: the search goes on as before
        stalled += 1
        traced.clear()
        result = solver.solve(target, seed)
        assert result.success and max(hybrid_errors(model, result.q, target)) < 1e-4
        assert not traced and np.abs(result.q - q).max() < 1e-3, result.stats
    assert stalled >= 1, stalled  # measured 3 of these 288 targets


def test_a_valley_past_a_joint_limit_is_walked_into_the_limits(ur10):
    """With the wrist straight the UR10's solutions form a continuum along which q2, q3, q4 and q6 all move:
    from a member with q3 past its -2.8 limit, ``enter`` walks along it into the limits and stops at its
    first point within them, on the same URDF pose (to the tens of micrometres one Newton step a point leaves, as
    ``trace``'s points; settling removes the rest) and still singular."""
    model = HybridModel.analytic_only(ur10.chain)
    limits = joint_limits(model.chain)
    q = wrist_singular(model, 20, seed=2)
    q[:, 2] = np.random.default_rng(2).uniform(-3.05, -2.85, len(q))
    entered = 0
    for q0 in q:
        v, sigma = weak_direction(model, q0)
        assert sigma < 1e-9
        found = enter(model, q0, v, limits)
        if found is None:
            continue
        entered += 1
        inside, w = found
        assert abs(w @ weak_direction(model, inside)[0]) > 0.99  # the weak motion there, up to its sign
        e = error6(model.fk_single(q0), model.fk_single(inside))
        assert np.linalg.norm(e[:3]) < 1e-4 and np.linalg.norm(e[3:]) < 1e-6, e
        assert weak_direction(model, inside)[1] < 1e-6
    assert entered >= 10, entered  # measured 17 of 20


def test_wrist_straight_next_to_a_limit_the_valley_past_it_holds_the_solution(trained):
    """A hybrid target with the wrist straight and q3 next to its -2.8 limit can have every exact branch of the
    URDF model past that limit, its hybrid solution within it (measured on a bench model: branches at q3 =
    -3.06 and -2.67, the solution at -2.78). No classical restart finds a branch within the limits; the LM
    restarts that followed found the solution after 0.6-0.75 s. The valleys of the branches past the limit
    are walked into the limits and searched: the solution is found along them, or by a fixed point, never by
    LM restarts from other branches."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    rng = np.random.default_rng(6)
    q = rng.uniform(0.8 * model.chain.lower, 0.8 * model.chain.upper, (2000, 6))
    q[:, 2], q[:, 4] = rng.uniform(-2.8, -2.72, 2000), 0.0
    seed = model.chain.mid_limits()
    past = [
        t
        for t in model.fk(q)
        if not len(solver.branches(t, seed))
        and len(solver.closed_form.past_limits(t, seed))
        and not len(solver.closed_form.approximations(t, seed, np.inf, np.inf))
    ]
    assert len(past) >= 4, len(past)
    methods = answered_methods(solver, np.array(past))
    # measured 15 of 24 along the valleys, 6 by a fixed point, none by LM restarts; before: 4 along the
    # valleys, 11 by LM restarts
    assert "lm" not in methods, methods
    assert methods.count("singular valley") >= len(past) // 2, methods


def test_the_wrist_continuum_is_traced_across_the_seam_of_a_whole_turn_joint(ur10):
    """The UR10's q4 and q6 span ±π, a whole turn: the wrist continuum (q5 = 0) from q4 = 2.9 crosses the seam at
    ±π, where the trace wraps the joint and goes on, so that the valley closes (it stopped at the seam, and a
    solution across it was found only by LM restarts). Every point lies within the limits."""
    model = HybridModel.analytic_only(ur10.chain)
    limits = joint_limits(model.chain)
    q = wrist_singular(model, 6, seed=1)
    q[:, 3] = 2.9
    closed = 0
    for q0 in q:
        points, _, whole = trace(model, q0, weak_direction(model, q0)[0], limits)
        assert np.all((points >= limits[0]) & (points <= limits[1]))
        assert points[:, 3].min() < -2.0 and points[:, 3].max() > 2.0  # both sides of the seam
        closed += whole
    assert closed >= 4, closed  # measured 5 of 6; before: 0, each way ending at ±π


def next_to_two_limits(solver: IKSolver, n: int, seed: int) -> list[np.ndarray]:
    """Hybrid targets with the wrist straight (q5 = 0 or 1e-4 rad) and q2 and q3 within 0.3 rad of their upper
    limits where the closed forms give no branch within the limits (of ``n`` drawn)."""
    model = solver.model
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.8 * model.chain.lower, 0.8 * model.chain.upper, (n, 6))
    q[:, 1], q[:, 2], q[:, 4] = rng.uniform(-0.3, 0.0, n), rng.uniform(2.5, 2.8, n), rng.choice([0.0, 1e-4], n)
    mid = model.chain.mid_limits()
    return [t for t in model.fk(q) if not len(solver.branches(t, mid))]


def test_a_fallback_near_answer_has_its_valley_searched_before_lm(trained):
    """Wrist straight, q2 and q3 next to their upper limits: the closed forms give no branch within the limits,
    and the fallback's restarts end on URDF answers a few millimetres from the hybrid target. LM from such an
    answer stalls in the wrist's valley (a bench UR10 target: an 8 ms crawl to 0.017 mm, then the weak-direction
    restarts, solved after 35-49 ms of a 50 ms budget); the valley through it holds the solution (21-24 ms)."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    solved = {False: 0, True: 0}
    near = 0
    for target in next_to_two_limits(solver, 600, seed=6):
        if near == 20:
            break
        for start in solver.seeds.nearest(target, 8):  # as the fallback loop's restarts
            q0, ep, er, _ = solver.urdf_lm._replace(max_iterations=100).solve(target, start, np.inf)
            if ep < seeding.NEAR_M and er < seeding.NEAR_RAD:
                break
        else:
            continue
        near += 1
        for valley_first in (False, True):
            now = time.perf_counter()
            valleys = [] if valley_first else None  # none searched yet in this solve: the valley's turn
            result = solver._other_branch(
                SolveRequest(target, q0, None, False, now, now + 5.0), q0, {}, valleys=valleys
            )
            solved[valley_first] += result.success
            if valley_first and result.success:
                assert hybrid_errors(model, result.q, target)[0] < 1e-4
    assert near == 20
    # measured 2 and 18 of 20
    assert solved[False] <= 8 and solved[True] >= 15, solved


def test_where_no_branch_lies_within_the_limits_the_classical_stage_takes_the_table_alone(trained):
    """The closed forms give no branch within the limits (wrist straight, q2 and q3 next to their upper limits):
    no URDF restart can reach the target, and the nearest point the classical stage finds comes from the
    table's restarts. Random ones after them ran until its share of the budget was gone, and a larger budget
    answered later: 100-500 ms on UR10 targets solved in 2-9 ms at 50 ms. Its attempts no longer grow with
    the budget."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    targets = next_to_two_limits(solver, 200, seed=7)[:12]
    assert len(targets) == 12
    mid = model.chain.mid_limits()
    for target in targets:  # LM from the seed, then from each of the table's
        _, _, _, attempts = solver.classical(
            target, mid, time.perf_counter() + 5.0, branches=np.empty((0, 6)), continuum=False, table_only=True
        )
        assert attempts <= seeding.TABLE_RESTARTS + 1
    # the whole solve: measured 0-40 attempts, median 17; before, some 17,000 in the classical stage's 0.5 s
    attempts = [solver.solve(t).stats["attempts"] for t in targets]
    assert np.median(attempts) < 100, attempts


def test_a_solve_runs_no_near_misses_restarts_twice(trained, monkeypatch):
    """The fallback loop's starts can end, one after another, on the same near miss: with a UR10's wrist centre
    near axis 1 every start's fixed point ended on one of two, and their weak-direction restarts ran again after
    each (8 times in 29 ms). They run once per near miss."""
    _, model, _, _ = trained
    solver = IKSolver(model, GENEROUS)
    seeded: list[np.ndarray] = []
    restarts, weak = seeding.valley_seeds, solver._weak_restarts
    before_search = []  # beyond the URDF model's reach, the nearest miss's restarts run before the valley search

    def recorded(model, q, position_error_mm, limits):
        out = restarts(model, q, position_error_mm, limits)
        if out and not before_search:  # restarts came: a near miss next to a singularity
            seeded.append(np.array(q, dtype=float))
        return out

    def first(*args, **kwargs):
        before_search.append(True)
        try:
            return weak(*args, **kwargs)
        finally:
            before_search.pop()

    monkeypatch.setattr(seeding, "valley_seeds", recorded)
    monkeypatch.setattr(solver, "_weak_restarts", first)
    calls = repeated = 0
    for label in ("wrist centre on axis 1 + 0.0001 rad", "q5 = 1e-4 rad"):
        q = cases(model.chain, 60, np.random.default_rng(3))[label]
        for target in model.fk(q):
            seeded.clear()
            solver.solve(target)
            calls += len(seeded)
            repeated += sum(np.abs(a - b).max() < seeding.BRANCH_RAD for a, b in itertools.combinations(seeded, 2))
    # measured 1 and 0; before: 44 calls, 946 pairs of them from one near miss
    assert calls >= 1 and repeated == 0, (calls, repeated)
