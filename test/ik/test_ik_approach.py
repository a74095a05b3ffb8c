"""IK for a model that takes the joints' approach directions: the solution is refined with the directions
the robot arrives in from the seed, not the ones it last moved in. Judged on the backlash cell's truth:
the pose the robot really reaches when it moves from the seed to the answer."""

from __future__ import annotations

from functools import partial

import numpy as np

from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.kinematics.approach import approach_directions, arrival_directions
from hybrid_kinematics_ros.simulation.backlash import BacklashCell

# a budget no loaded machine runs out of, and tolerances far below the tenths of a millimetre at stake
OPTIONS = partial(IKOptions, position_tolerance_mm=1e-3, orientation_tolerance_deg=1e-3, timeout_s=5.0)


def test_arrival_directions_by_hand():
    seed, q, current = np.array([0.0, 0.0, 0.0]), np.array([0.2, -0.1, 5e-5]), np.array([-1.0, -1.0, 1.0])
    np.testing.assert_array_equal(arrival_directions(seed, q, current), [1, -1, 1])  # 5e-5 rad: no move


def test_ik_answers_for_the_side_the_joints_arrive_from(ur10, backlash_models):
    loaded, _ = backlash_models
    model = loaded["approach"]
    cell = BacklashCell.from_config(ur10)
    rng = np.random.default_rng(5)
    lower, upper = 0.6 * ur10.chain.lower, 0.6 * ur10.chain.upper
    errors = {True: [], False: []}
    for _ in range(12):
        seed = rng.uniform(lower, upper)
        goal = np.clip(seed + rng.uniform(-0.3, 0.3, 6), lower, upper)
        arrive = np.sign(goal - seed)
        target = cell.measure(goal, arrive, rng)[0]  # where the robot stops
        for on in (True, False):
            last = model.with_approach(-arrive)  # the joints last moved the other way
            result = IKSolver(last, OPTIONS(arrive_from_seed=on)).solve(target, seed)
            assert result.success, result.message
            directions = arrival_directions(seed, result.q, -arrive)
            if on:
                np.testing.assert_array_equal(result.stats["approach"], directions)
            errors[on].append(cell.miss_mm(result.q, directions, target)[0])
    with_arrival, stale = np.mean(errors[True]), np.mean(errors[False])
    # the shoulder's ±0.3-0.4 mrad about 1 m out: a few tenths of a millimetre on the stale side
    assert stale > 0.2 and with_arrival < stale / 2, (with_arrival, stale)


def test_trajectory_poses_arrive_from_the_pose_before(ur10, backlash_models):
    loaded, _ = backlash_models
    model = loaded["approach"]
    cell = BacklashCell.from_config(ur10)
    rng = np.random.default_rng(6)
    seed = rng.uniform(0.5 * ur10.chain.lower, 0.5 * ur10.chain.upper)
    # a path that turns back: every joint reverses halfway
    steps = np.r_[np.linspace(0.0, 0.3, 8)[1:], np.linspace(0.3, 0.1, 6)[1:]]
    path = seed + np.outer(steps, rng.choice([-1.0, 1.0], 6))
    arrive = approach_directions(np.vstack([seed, path]), start=np.zeros(6))[1:]
    targets = cell.measure(path, arrive, rng)
    errors = {}
    for on in (True, False):
        results = IKSolver(model.with_approach(np.zeros(6)), OPTIONS(arrive_from_seed=on)).solve_trajectory(
            targets, seed
        )
        assert all(r.success for r in results), [r.message for r in results]
        q = np.array([r.q for r in results])
        directions = approach_directions(np.vstack([seed, q]), start=np.zeros(6))[1:]
        errors[on] = cell.miss_mm(q, directions, targets).mean()
    assert errors[False] > 0.1 and errors[True] < errors[False] / 2, errors
