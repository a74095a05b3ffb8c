"""Approach directions as net inputs: a cell whose joints have backlash (where each stops depends on the
direction it came from), trained with and without the directions, judged on a held-out sequence."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.fit import fit, load_stations, split
from hybrid_kinematics_ros.io.pairs import Pairs, write_pairs
from hybrid_kinematics_ros.model.approach import ApproachTracker, approach_directions, channel_names
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from test.conftest import THERMAL_PRESET

HALF_BACKLASH = np.array([4e-4, 3e-4, 3e-4, 0.0, 0.0, 0.0])  # rad: where each joint stops, either side


def test_directions_by_hand():
    q = np.array([[0.0, 0.0], [0.1, 0.0], [0.1, -0.2], [0.10005, -0.1], [0.0, -0.1]])
    expected = np.array([[0, 0], [1, 0], [1, -1], [1, 1], [-1, 1]])  # 5e-5 rad is no move; still keeps the last
    np.testing.assert_array_equal(approach_directions(q), expected)
    np.testing.assert_array_equal(approach_directions(q, start=np.array([-1.0, 1.0]))[0], [-1, 1])


def test_streaming_tracker_agrees_with_the_sequence():
    q = np.cumsum(np.random.default_rng(0).normal(0.0, 1e-3, (400, 6)), axis=0)
    tracker = ApproachTracker(6)
    streamed = np.array([tracker.update(row).copy() for row in q])
    np.testing.assert_array_equal(streamed, approach_directions(q))


def backlash_pairs(ur10, count: int, seed: int) -> Pairs:
    """A random walk of the joints (as a measurement program visits poses), measured with backlash."""
    rng = np.random.default_rng(seed)
    lower, upper = 0.8 * ur10.chain.lower, 0.8 * ur10.chain.upper
    q = np.empty((count, 6))
    q[0] = rng.uniform(lower, upper)
    for i in range(1, count):
        q[i] = np.clip(q[i - 1] + rng.uniform(-0.3, 0.3, 6), lower, upper)
    cell = VirtualCell.from_config(ur10, noise=False)
    T = cell.measure(q + HALF_BACKLASH * approach_directions(q), rng)
    return Pairs(q, T, 10**9 + 10**7 * np.arange(count), ur10.chain.joint_names, "base_link").with_approach()


@pytest.fixture(scope="module")
def backlash_models(ur10, tmp_path_factory):
    tr, va, _ = split(backlash_pairs(ur10, 3000, seed=1), seed=0)
    test = backlash_pairs(ur10, 500, seed=2)
    out = {}
    for name, conditions in (("plain", ()), ("approach", channel_names(ur10.chain.joint_names))):
        path = tmp_path_factory.mktemp("approach") / name
        fit(ur10.chain, tr, va, test, path, THERMAL_PRESET, 5.0, conditions=conditions, parametric=True)
        out[name] = HybridModel.load(path)
    return out, test


def test_the_directions_learn_what_the_joints_cannot(backlash_models):
    loaded, test = backlash_models
    plain = evaluate(loaded["plain"], test)["hybrid"]["position_mm_mean"]
    with_approach = evaluate(loaded["approach"], test)["hybrid"]["position_mm_mean"]
    # ±0.3-0.4 mrad at the shoulder, about 1 m out: ±0.3 mm that no function of the joints alone predicts
    assert plain > 0.15 and with_approach < plain / 2, (plain, with_approach)
    model = loaded["approach"]
    section = model.manifest["conditions"]
    assert [section[name]["default"] for name in channel_names(model.joint_names)] == [0.0] * 6
    assert [section[name]["lower"] for name in channel_names(model.joint_names)] == [-1.0] * 6


def test_served_paths_follow_the_current_directions(backlash_models):
    loaded, test = backlash_models
    model = loaded["approach"]
    q = test.q[:4]
    directions = np.array([1.0, -1.0, 1.0, 1.0, -1.0, 1.0])
    model.set_approach(directions)
    batch = model.fk(q)
    np.testing.assert_allclose(batch, model.fk(q, conditions=np.tile(directions, (4, 1))), atol=1e-12)
    for i in range(4):
        np.testing.assert_allclose(model.fk_single(q[i]), batch[i], atol=5e-9)
    model.set_approach(-directions)
    moved = np.linalg.norm(model.fk(q)[:, :3, 3] - batch[:, :3, 3], axis=1).mean()
    assert moved > 0.2e-3  # m: about the two sides of the shoulder's backlash
    loaded["plain"].set_approach(directions)  # a model without the inputs ignores them
    assert loaded["plain"].approach_index is None


def test_directions_are_derived_when_read_not_stored(ur10, tmp_path):
    pairs = backlash_pairs(ur10, 50, seed=3)
    write_pairs(tmp_path / "bag", pairs)
    (read,) = load_stations([tmp_path / "bag"], ur10.chain)
    for name in channel_names(ur10.chain.joint_names):
        np.testing.assert_array_equal(read.conditions[name], pairs.conditions[name])
