"""Approach directions as net inputs: a cell whose joints have backlash (where each stops depends on the
direction it came from), trained with and without the directions, judged on a held-out sequence."""

from __future__ import annotations

import itertools

import numpy as np

from hybrid_kinematics_ros.calibration.evaluate import evaluate
from hybrid_kinematics_ros.calibration.fit import load_stations
from hybrid_kinematics_ros.calibration.recipe import Recipe
from hybrid_kinematics_ros.io.pairs import write_pairs
from hybrid_kinematics_ros.kinematics.approach import ApproachTracker, approach_directions, channel_names
from hybrid_kinematics_ros.simulation.backlash import play
from test.conftest import backlash_pairs


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


def test_a_slow_approach_is_labelled_alike_at_any_sampling_rate_and_as_the_play_stops():
    """Moves of 2-20 mrad at 10 mrad/s, as 500 Hz joint states (20 µrad apart) and as one row per pose
    (a tracker export): the same directions at every pose, and the side the physical play stops on. Judged
    step by step, the joint states showed no move at all and the export did."""
    rng = np.random.default_rng(7)
    poses = np.cumsum(rng.choice([-1.0, 1.0], (30, 6)) * rng.uniform(2e-3, 2e-2, (30, 6)), axis=0)
    segments, at_pose = [poses[:1]], [0]
    for a, b in itertools.pairwise(poses):
        samples = int(np.ceil(np.abs(b - a).max() / 2e-5))  # 10 mrad/s at 500 Hz
        segments.append(a + (b - a) * np.linspace(0.0, 1.0, samples + 1)[1:, None])
        at_pose.append(at_pose[-1] + samples)
    dense = np.concatenate(segments)
    assert np.abs(np.diff(dense, axis=0)).max() <= 2.01e-5
    from_stream = approach_directions(dense)[at_pose]
    from_rows = approach_directions(poses)
    np.testing.assert_array_equal(from_stream[1:], from_rows[1:])
    assert np.all(from_rows[1:] != 0)
    half = np.full(6, 3e-4)
    stops = play(dense, half)[at_pose] - poses  # every move is longer than the play: a full side
    np.testing.assert_allclose(stops[1:], -half * from_rows[1:], atol=1e-12)


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
    toward = model.with_approach(directions)
    batch = toward.fk(q)
    np.testing.assert_allclose(batch, model.fk(q, conditions=np.tile(directions, (4, 1))), atol=1e-12)
    for i in range(4):
        np.testing.assert_allclose(toward.fk_single(q[i]), batch[i], atol=5e-9)
    moved = np.linalg.norm(model.with_approach(-directions).fk(q)[:, :3, 3] - batch[:, :3, 3], axis=1).mean()
    assert moved > 0.2e-3  # m: about the two sides of the shoulder's backlash
    np.testing.assert_array_equal(model.approach, np.zeros(6))  # the loaded model keeps its own
    plain = loaded["plain"]
    assert plain.approach_index is None and plain.with_approach(directions) is plain  # no inputs: ignored


def test_directions_are_derived_when_read_not_stored(ur10, tmp_path):
    pairs = backlash_pairs(ur10, 50, seed=3)
    write_pairs(tmp_path / "bag", pairs)
    (read,) = load_stations([tmp_path / "bag"], ur10.chain)
    for name in channel_names(ur10.chain.joint_names):
        np.testing.assert_array_equal(read.conditions[name], pairs.conditions[name])


def test_the_data_choose_the_directions_as_inputs(ur10, tmp_path):
    """Given neither way, ``fit`` gives the nets the approach directions where the joints have play, and
    not where they have none, and records the choice with its figures."""
    from dataclasses import replace

    from hybrid_kinematics_ros.calibration import train
    from hybrid_kinematics_ros.calibration.fit import fit, split
    from hybrid_kinematics_ros.simulation.portfolio import CellSpec, build_cell

    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", max_epochs=5, ensemble=1)
    chosen = {}
    for name, half in (("play", (3e-4, 2e-4, 2e-4)), ("none", ())):
        cell = build_cell(CellSpec(name, poses=1200, test_poses=100, half_backlash_rad=half))
        tr, va, _ = split(cell.train, 0, (0.1, 0.0))
        # the other settings fixed: only the directions' choice is under test
        recipe = Recipe(preset, 1.0, capacity={"elastic": "bending", "harmonics": 0, "map_step": 0.0})
        model, manifest = fit(ur10.chain, tr, va, va, tmp_path / name, recipe)
        decision = next(d for d in manifest["capacity"]["decisions"] if d["setting"] == "approach")
        assert [c["candidate"] for c in decision["candidates"]] == [False, True]
        chosen[name] = (decision["chosen"], model.approach_index is not None)
    assert chosen == {"play": (True, True), "none": (False, False)}
